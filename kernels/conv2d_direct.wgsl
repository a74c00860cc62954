//! variant f32: alias ST = f32; const IS_F16: bool = false;
//! variant f16: enable f16; alias ST = f16; const IS_F16: bool = true;
// Direct conv2d: one output per invocation, plain loops over (c, ky, kx). Kept forever as the fallback and the
// oracle of the implicit-GEMM kernel (conv2d.wgsl); same parameters, bindings and f16 saturation.
// Loop budget (lavapipe: 65535 back-edges per invocation): up to C (KH KW + KH + 1) back-edges (3x3, C = 2560:
// 33280); the launcher refuses shapes past 60000.

struct Conv2dParams {
    n: u32, c: u32, h: u32, w: u32,
    o: u32, oh: u32, ow: u32,
    kh: u32, kw: u32, stride: u32,
    pt: u32, pl: u32,
    // 0 none, 1 bias (O), 2 bias (N, O) (conv2d_packed only)
    has_bias: u32,
    // 1: add res (N, O, OH, OW) in the epilogue (conv2d_packed only; the launcher adds separately elsewhere)
    has_res: u32,
    // 1: SiLU on the result (conv2d_packed only; the launcher runs a separate pass elsewhere)
    silu: u32,
}

@group(0) @binding(0) var<storage, read> x: array<ST>;
@group(0) @binding(1) var<storage, read> wt: array<ST>;
@group(0) @binding(2) var<storage, read> bias: array<ST>;
@group(0) @binding(3) var<storage, read_write> y: array<ST>;
var<immediate> p: Conv2dParams;

// x: (N, C, H, W), wt: (O, C, KH, KW), bias: (O) -> y: (N, O, OH, OW); flat grid over N O OH OW.
@compute @workgroup_size(256)
fn main(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>, @builtin(local_invocation_id) lid: vec3<u32>) {
    let i = flat_index(wid, nwg, lid);
    let np = p.oh * p.ow;
    if (i >= p.n * p.o * np) { return; }
    let q = i % np;
    let oc = (i / np) % p.o;
    let nb = i / (np * p.o);
    let iy0 = i32((q / p.ow) * p.stride) - i32(p.pt);
    let ix0 = i32((q % p.ow) * p.stride) - i32(p.pl);
    var s = 0.0;
    for (var c = 0u; c < p.c; c++) {
        let xo = (nb * p.c + c) * p.h * p.w;
        let wo = (oc * p.c + c) * p.kh * p.kw;
        for (var ky = 0u; ky < p.kh; ky++) {
            let iy = iy0 + i32(ky);
            if (iy < 0 || iy >= i32(p.h)) { continue; }
            for (var kx = 0u; kx < p.kw; kx++) {
                let ix = ix0 + i32(kx);
                if (ix >= 0 && ix < i32(p.w)) {
                    s += f32(wt[wo + ky * p.kw + kx]) * f32(x[xo + u32(iy) * p.w + u32(ix)]);
                }
            }
        }
    }
    if (p.has_bias != 0u) { s += f32(bias[oc]); }
    if (IS_F16) { s = clamp(s, -65504.0, 65504.0); }
    y[i] = ST(s);
}
