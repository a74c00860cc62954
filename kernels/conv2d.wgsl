//! variant f32: alias ST = f32; const IS_F16: bool = false;
//! variant f16: enable f16; alias ST = f16; const IS_F16: bool = true;
// conv2d as an implicit GEMM (im2col on the fly), tiled like matmul.wgsl (read its header first):
// rows = output channels O (weights, lanes 0..7 load 8 k values, subgroupBroadcast gives them to all lanes),
// columns = output positions p = oy * OW + ox (lane l owns p0 + l + SG j, j < 4), k = (kh, kw, c), c innermost
// in chunks of 8. Padding: input reads outside the image are masked to 0 (index clamped in bounds).
// Loop budget: KH KW (ceil(C / 8) + 1) + KH back-edges per invocation (3x3, C = 2560: 2910).
// f16 outputs saturate at +-65504 (see matmul.rs).

struct Conv2dParams {
    n: u32, c: u32, h: u32, w: u32,
    o: u32, oh: u32, ow: u32,
    kh: u32, kw: u32, stride: u32,
    // top and left padding (bottom/right only shape OH, OW)
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

const TM: u32 = 16u;
const WG: u32 = 64u;

var<private> acc: array<vec4<f32>, TM>;
var<private> av: array<f32, TM>;
var<private> aoff: array<u32, TM>;

const F16_MAX: f32 = 65504.0;

fn out_val(v: f32) -> ST {
    if (IS_F16) { return ST(clamp(v, -F16_MAX, F16_MAX)); }
    return ST(v);
}

// acc[r] += W[o_r, k_j] * bv for j = 0..7, the weight broadcast from lane j (constant lane: see matmul.wgsl).
fn fma_k0(bv: vec4<f32>) { for (var r = 0u; r < TM; r++) { acc[r] = fma(vec4<f32>(subgroupBroadcast(av[r], 0u)), bv, acc[r]); } }
fn fma_k1(bv: vec4<f32>) { for (var r = 0u; r < TM; r++) { acc[r] = fma(vec4<f32>(subgroupBroadcast(av[r], 1u)), bv, acc[r]); } }
fn fma_k2(bv: vec4<f32>) { for (var r = 0u; r < TM; r++) { acc[r] = fma(vec4<f32>(subgroupBroadcast(av[r], 2u)), bv, acc[r]); } }
fn fma_k3(bv: vec4<f32>) { for (var r = 0u; r < TM; r++) { acc[r] = fma(vec4<f32>(subgroupBroadcast(av[r], 3u)), bv, acc[r]); } }
fn fma_k4(bv: vec4<f32>) { for (var r = 0u; r < TM; r++) { acc[r] = fma(vec4<f32>(subgroupBroadcast(av[r], 4u)), bv, acc[r]); } }
fn fma_k5(bv: vec4<f32>) { for (var r = 0u; r < TM; r++) { acc[r] = fma(vec4<f32>(subgroupBroadcast(av[r], 5u)), bv, acc[r]); } }
fn fma_k6(bv: vec4<f32>) { for (var r = 0u; r < TM; r++) { acc[r] = fma(vec4<f32>(subgroupBroadcast(av[r], 6u)), bv, acc[r]); } }
fn fma_k7(bv: vec4<f32>) { for (var r = 0u; r < TM; r++) { acc[r] = fma(vec4<f32>(subgroupBroadcast(av[r], 7u)), bv, acc[r]); } }

// Input value of channel c at the 4 columns' offsets `off` (0 where `ok` is false).
fn x_quad(xb: u32, c: u32, off: vec4<u32>, ok: vec4<bool>) -> vec4<f32> {
    let o = xb + min(c, p.c - 1u) * p.h * p.w;
    return select(vec4<f32>(0.0), vec4<f32>(f32(x[o + off.x]), f32(x[o + off.y]), f32(x[o + off.z]), f32(x[o + off.w])), ok);
}

// x: (N, C, H, W), wt: (O, C, KH, KW), bias: (O) -> y: (N, O, OH, OW).
// Work groups: (ceil(OH OW / 4 SG), ceil(O / (WG / SG) TM), N).
@compute @workgroup_size(WG)
fn main(@builtin(workgroup_id) wid: vec3<u32>, @builtin(local_invocation_index) li: u32,
        @builtin(subgroup_invocation_id) lane: u32, @builtin(subgroup_size) sgs: u32) {
    let row0 = (wid.y * (WG / sgs) + li / sgs) * TM;
    // a subgroup past the last row (output channel) leaves at once (uniform per subgroup; no barriers follow)
    if (row0 >= p.o) { return; }
    let np = p.oh * p.ow;
    let col0 = wid.x * 4u * sgs + lane;
    let cols = min(vec4<u32>(col0, col0 + sgs, col0 + 2u * sgs, col0 + 3u * sgs), vec4<u32>(np - 1u));
    // top-left input corner of each column's window (may be negative: i32)
    let iy0 = vec4<i32>((cols / p.ow) * p.stride) - i32(p.pt);
    let ix0 = vec4<i32>((cols % p.ow) * p.stride) - i32(p.pl);
    let ksz = p.kh * p.kw;
    for (var r = 0u; r < TM; r++) {
        aoff[r] = min(row0 + r, p.o - 1u) * p.c * ksz;
        acc[r] = vec4<f32>(0.0);
    }
    let xb = wid.z * p.c * p.h * p.w;
    for (var ky = 0u; ky < p.kh; ky++) {
        let iy = iy0 + i32(ky);
        let oky = (iy >= vec4<i32>(0)) & (iy < vec4<i32>(i32(p.h)));
        for (var kx = 0u; kx < p.kw; kx++) {
            let ix = ix0 + i32(kx);
            let ok = oky & (ix >= vec4<i32>(0)) & (ix < vec4<i32>(i32(p.w)));
            let off = select(vec4<u32>(0u), vec4<u32>(iy * i32(p.w) + ix), ok);
            let kt = ky * p.kw + kx;
            for (var c0 = 0u; c0 < p.c; c0 += 8u) {
                let cl = c0 + (lane & 7u);
                let wk = min(cl, p.c - 1u) * ksz + kt;
                for (var r = 0u; r < TM; r++) {
                    av[r] = select(0.0, f32(wt[aoff[r] + wk]), cl < p.c);
                }
                fma_k0(x_quad(xb, c0, off, ok));
                fma_k1(x_quad(xb, c0 + 1u, off, ok));
                fma_k2(x_quad(xb, c0 + 2u, off, ok));
                fma_k3(x_quad(xb, c0 + 3u, off, ok));
                fma_k4(x_quad(xb, c0 + 4u, off, ok));
                fma_k5(x_quad(xb, c0 + 5u, off, ok));
                fma_k6(x_quad(xb, c0 + 6u, off, ok));
                fma_k7(x_quad(xb, c0 + 7u, off, ok));
            }
        }
    }
    let yb = wid.z * p.o * np;
    for (var r = 0u; r < TM; r++) {
        let oc = row0 + r;
        if (oc >= p.o) { return; }
        var bv = 0.0;
        if (p.has_bias != 0u) { bv = f32(bias[oc]); }
        for (var j = 0u; j < 4u; j++) {
            let q = col0 + sgs * j;
            if (q < np) { y[yb + oc * np + q] = out_val(acc[r][j] + bv); }
        }
    }
}
