//! variant f32: alias ST = f32;
// Bilinear warp of (N, C, H, W) images by a per-pixel source grid (N, H, W, 2) of (x, y) in pixel-index units
// (the centre of pixel i at i): out[n, c, y, x] = bilinear(img[n, c], grid[n, y, x]) with the taps clamped to the
// image (PyTorch grid_sample, bilinear, padding "border", align_corners false, on the normalised grid); a grid
// entry outside [-0.5, W - 0.5] x [-0.5, H - 0.5] (the host writes -1e9 for "no source") keeps the image's own
// pixel. One invocation per output value; no loops.

struct WarpParams { planes: u32, c: u32, h: u32, w: u32 }

@group(0) @binding(0) var<storage, read> x: array<ST>;
@group(0) @binding(1) var<storage, read> grid: array<f32>;
@group(0) @binding(2) var<storage, read_write> y: array<ST>;
var<immediate> p: WarpParams;

@compute @workgroup_size(256)
fn main(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>, @builtin(local_invocation_id) lid: vec3<u32>) {
    let i = flat_index(wid, nwg, lid);
    let hw = p.h * p.w;
    if (i >= p.planes * hw) { return; }
    let pix = i % hw;
    let plane = i / hw;
    let n = plane / p.c;
    let g = (n * hw + pix) * 2u;
    let gx = grid[g];
    let gy = grid[g + 1u];
    let wf = f32(p.w);
    let hf = f32(p.h);
    if (!(gx >= -0.5 && gx <= wf - 0.5 && gy >= -0.5 && gy <= hf - 0.5)) {
        y[i] = x[i];
        return;
    }
    let fx0 = floor(gx);
    let fy0 = floor(gy);
    let ax = gx - fx0;
    let ay = gy - fy0;
    let x0 = u32(clamp(i32(fx0), 0, i32(p.w) - 1));
    let x1 = u32(clamp(i32(fx0) + 1, 0, i32(p.w) - 1));
    let y0 = u32(clamp(i32(fy0), 0, i32(p.h) - 1));
    let y1 = u32(clamp(i32(fy0) + 1, 0, i32(p.h) - 1));
    let base = plane * hw;
    let top = (1.0 - ax) * f32(x[base + y0 * p.w + x0]) + ax * f32(x[base + y0 * p.w + x1]);
    let bot = (1.0 - ax) * f32(x[base + y1 * p.w + x0]) + ax * f32(x[base + y1 * p.w + x1]);
    y[i] = ST((1.0 - ay) * top + ay * bot);
}
