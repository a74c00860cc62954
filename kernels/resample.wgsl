//! variant f32: alias ST = f32;
//! variant f16: enable f16; alias ST = f16;
// Resampling of (N*C, H, W) planes to (N*C, OH, OW), one output pixel per invocation (x fastest: contiguous).
// nearest: PyTorch F.interpolate(mode="nearest", size=...): src = min(floor(dst * (in / out)), in - 1), the scale
//   computed in f32 as PyTorch does.
// bicubic: PyTorch align_corners=False, A = -0.75: src = (dst + 0.5) * (in / out) - 0.5, 4 taps per axis with
//   indices clamped to the border, no antialiasing, no output clamping.

struct ResampleParams { planes: u32, h: u32, w: u32, oh: u32, ow: u32, sh: f32, sw: f32 }

@group(0) @binding(0) var<storage, read> x: array<ST>;
@group(0) @binding(1) var<storage, read_write> y: array<ST>;
var<immediate> p: ResampleParams;

@compute @workgroup_size(256)
fn nearest(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>, @builtin(local_invocation_id) lid: vec3<u32>) {
    let i = flat_index(wid, nwg, lid);
    if (i >= p.planes * p.oh * p.ow) { return; }
    let ox = i % p.ow;
    let oy = (i / p.ow) % p.oh;
    let pl = i / (p.ow * p.oh);
    let sx = min(u32(floor(f32(ox) * p.sw)), p.w - 1u);
    let sy = min(u32(floor(f32(oy) * p.sh)), p.h - 1u);
    y[i] = x[(pl * p.h + sy) * p.w + sx];
}

fn cubic_w(t: f32) -> vec4<f32> {
    // Keys cubic convolution with A = -0.75 (PyTorch's upsample_bicubic2d coefficients)
    let a = -0.75;
    let x1 = t + 1.0;
    let x2 = t;
    let x3 = 1.0 - t;
    let x4 = 2.0 - t;
    let w0 = ((a * x1 - 5.0 * a) * x1 + 8.0 * a) * x1 - 4.0 * a;
    let w1 = ((a + 2.0) * x2 - (a + 3.0)) * x2 * x2 + 1.0;
    let w2 = ((a + 2.0) * x3 - (a + 3.0)) * x3 * x3 + 1.0;
    let w3 = ((a * x4 - 5.0 * a) * x4 + 8.0 * a) * x4 - 4.0 * a;
    return vec4<f32>(w0, w1, w2, w3);
}

@compute @workgroup_size(256)
fn bicubic(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>, @builtin(local_invocation_id) lid: vec3<u32>) {
    let i = flat_index(wid, nwg, lid);
    if (i >= p.planes * p.oh * p.ow) { return; }
    let ox = i % p.ow;
    let oy = (i / p.ow) % p.oh;
    let pl = i / (p.ow * p.oh);
    let fx = (f32(ox) + 0.5) * p.sw - 0.5;
    let fy = (f32(oy) + 0.5) * p.sh - 0.5;
    let x0 = floor(fx);
    let y0 = floor(fy);
    let wx = cubic_w(fx - x0);
    let wy = cubic_w(fy - y0);
    let ix = i32(x0);
    let iy = i32(y0);
    let mw = i32(p.w) - 1;
    let mh = i32(p.h) - 1;
    let base = pl * p.h * p.w;
    var acc = 0.0;
    // 4 x 4 taps written out (no loops: keeps lavapipe's loop budget untouched)
    let c0 = u32(clamp(ix - 1, 0, mw)); let c1 = u32(clamp(ix, 0, mw));
    let c2 = u32(clamp(ix + 1, 0, mw)); let c3 = u32(clamp(ix + 2, 0, mw));
    let r0 = base + u32(clamp(iy - 1, 0, mh)) * p.w; let r1 = base + u32(clamp(iy, 0, mh)) * p.w;
    let r2 = base + u32(clamp(iy + 1, 0, mh)) * p.w; let r3 = base + u32(clamp(iy + 2, 0, mh)) * p.w;
    let row0 = wx.x * f32(x[r0 + c0]) + wx.y * f32(x[r0 + c1]) + wx.z * f32(x[r0 + c2]) + wx.w * f32(x[r0 + c3]);
    let row1 = wx.x * f32(x[r1 + c0]) + wx.y * f32(x[r1 + c1]) + wx.z * f32(x[r1 + c2]) + wx.w * f32(x[r1 + c3]);
    let row2 = wx.x * f32(x[r2 + c0]) + wx.y * f32(x[r2 + c1]) + wx.z * f32(x[r2 + c2]) + wx.w * f32(x[r2 + c3]);
    let row3 = wx.x * f32(x[r3 + c0]) + wx.y * f32(x[r3 + c1]) + wx.z * f32(x[r3 + c2]) + wx.w * f32(x[r3 + c3]);
    acc = wy.x * row0 + wy.y * row1 + wy.z * row2 + wy.w * row3;
    y[i] = ST(acc);
}
