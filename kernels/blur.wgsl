//! variant f32: alias ST = f32;
//! variant f16: enable f16; alias ST = f16;
// Separable Gaussian blur of (N*C, H, W) planes: one pass along x (axis 0) or y (axis 1) per dispatch.
// Taps k = -r..r, weight exp(-k^2 / (2 sigma^2)) normalised to sum 1 (torchvision's gaussian_blur kernel);
// borders reflect without repeating the edge pixel (torchvision's "reflect" padding): -1 -> 1, n -> n - 2.
// Loop budget: 2r + 1 iterations per invocation (r <= 32 enforced by the launcher).

struct BlurParams { planes: u32, h: u32, w: u32, axis: u32, radius: u32, sigma: f32 }

@group(0) @binding(0) var<storage, read> x: array<ST>;
@group(0) @binding(1) var<storage, read_write> y: array<ST>;
var<immediate> p: BlurParams;

fn reflect_idx(i: i32, n: i32) -> i32 {
    var j = i;
    if (j < 0) { j = -j; }
    if (j >= n) { j = 2 * n - 2 - j; }
    return clamp(j, 0, n - 1);
}

@compute @workgroup_size(256)
fn main(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>, @builtin(local_invocation_id) lid: vec3<u32>) {
    let i = flat_index(wid, nwg, lid);
    if (i >= p.planes * p.h * p.w) { return; }
    let px = i32(i % p.w);
    let py = i32((i / p.w) % p.h);
    let base = (i / (p.w * p.h)) * p.h * p.w;
    let r = i32(p.radius);
    let inv = -0.5 / (p.sigma * p.sigma);
    var acc = 0.0;
    var wsum = 0.0;
    for (var k = -r; k <= r; k++) {
        let wk = exp(f32(k * k) * inv);
        var idx: u32;
        if (p.axis == 0u) {
            idx = base + u32(py) * p.w + u32(reflect_idx(px + k, i32(p.w)));
        } else {
            idx = base + u32(reflect_idx(py + k, i32(p.h))) * p.w + u32(px);
        }
        acc += wk * f32(x[idx]);
        wsum += wk;
    }
    y[i] = ST(acc / wsum);
}
