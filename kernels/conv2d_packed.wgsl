//! variant f32: alias ST = f32; const IS_F16: bool = false; fn ld4(i: u32) -> vec4<f32> { return vec4<f32>(w4[i]); } fn ldx4(i: u32) -> vec4<f32> { return vec4<f32>(x4[i]); }
//! variant f16: enable f16; alias ST = f16; const IS_F16: bool = true; fn ld4(i: u32) -> vec4<f32> { let q = wq2[i]; return vec4<f32>(f16x2(q.x), f16x2(q.y)); } fn ldx4(i: u32) -> vec4<f32> { let q = xq2[i]; return vec4<f32>(f16x2(q.x), f16x2(q.y)); }
//! variant f32t: alias ST = f32; const IS_F16: bool = false; fn ld4(i: u32) -> vec4<f32> { return textureLoad(wt, texel_xy(i)); } fn ldx4(i: u32) -> vec4<f32> { return textureLoad(xt, texel_xy(i)); }
// conv2d as an implicit GEMM with pre-packed weights: the fast path for 3x3 (and any non-1x1) convs.
// Roles are swapped relative to conv2d.wgsl: rows = output positions p (TM per subgroup; lanes 0..7 load the
// input at 8 channels c0 + lane, subgroupBroadcast gives each value to all lanes), columns = output channels
// (lane l owns 4 consecutive o). The weights are first repacked from (O, C, KH, KW) to (KH, KW, C, O) (`pack`),
// so every weight load is ONE vec4 (f16: one vec2<u32>) contiguous along o: on lavapipe, where each storage
// load is a per-lane scalar loop, that is 4x (8x in f16) fewer load instructions than the gathered input
// values of conv2d.wgsl. Needs O % 4 == 0. Loop budget: KH KW (ceil(C / 8) + 1) + KH back-edges per invocation.

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
struct PackParams { o: u32, c: u32, kk: u32 }

@group(0) @binding(0) var<storage, read> x: array<ST>;
@group(0) @binding(0) var<storage, read> x4: array<vec4<ST>>;
@group(0) @binding(0) var<storage, read> xq2: array<vec2<u32>>;
@group(0) @binding(1) var<storage, read> w4: array<vec4<ST>>;
@group(0) @binding(1) var<storage, read> wq2: array<vec2<u32>>;
// variant f32t: the vector views of x and the packed weights read through the buffers' texel views (`ldx4`,
// `ld4`; src/vk/image.rs): one 16-byte fetch per lane on lavapipe instead of four bounds-checked scalar loads
@group(0) @binding(0) var xt: texture_storage_2d<rgba32float, read>;
@group(0) @binding(1) var wt: texture_storage_2d<rgba32float, read>;
@group(0) @binding(2) var<storage, read> bias: array<ST>;
@group(0) @binding(3) var<storage, read_write> y: array<ST>;
// residual added in the epilogue (p.has_res == 1; the launcher binds y here otherwise); may be y itself
@group(0) @binding(4) var<storage, read> res: array<ST>;
@group(0) @binding(1) var<storage, read_write> packed: array<ST>;
var<immediate> p: Conv2dParams;
var<immediate> pp: PackParams;

const TM: u32 = 16u;
const WG: u32 = 64u;

var<private> acc: array<vec4<f32>, TM>;
var<private> av: array<f32, TM>;
var<private> av4: array<vec4<f32>, TM>;
var<private> xoff: array<u32, TM>;
var<private> xok: array<bool, TM>;
var<private> iy0: array<i32, TM>;
var<private> ix0: array<i32, TM>;


// acc[r] += x[p_r, k_j] * bv for j = 0..7, x broadcast from lane j (constant lane).
fn fma_k0(bv: vec4<f32>) { for (var r = 0u; r < TM; r++) { acc[r] = fma(vec4<f32>(subgroupBroadcast(av[r], 0u)), bv, acc[r]); } }
fn fma_k1(bv: vec4<f32>) { for (var r = 0u; r < TM; r++) { acc[r] = fma(vec4<f32>(subgroupBroadcast(av[r], 1u)), bv, acc[r]); } }
fn fma_k2(bv: vec4<f32>) { for (var r = 0u; r < TM; r++) { acc[r] = fma(vec4<f32>(subgroupBroadcast(av[r], 2u)), bv, acc[r]); } }
fn fma_k3(bv: vec4<f32>) { for (var r = 0u; r < TM; r++) { acc[r] = fma(vec4<f32>(subgroupBroadcast(av[r], 3u)), bv, acc[r]); } }
fn fma_k4(bv: vec4<f32>) { for (var r = 0u; r < TM; r++) { acc[r] = fma(vec4<f32>(subgroupBroadcast(av[r], 4u)), bv, acc[r]); } }
fn fma_k5(bv: vec4<f32>) { for (var r = 0u; r < TM; r++) { acc[r] = fma(vec4<f32>(subgroupBroadcast(av[r], 5u)), bv, acc[r]); } }
fn fma_k6(bv: vec4<f32>) { for (var r = 0u; r < TM; r++) { acc[r] = fma(vec4<f32>(subgroupBroadcast(av[r], 6u)), bv, acc[r]); } }
fn fma_k7(bv: vec4<f32>) { for (var r = 0u; r < TM; r++) { acc[r] = fma(vec4<f32>(subgroupBroadcast(av[r], 7u)), bv, acc[r]); } }

// w: (O, C, KH, KW) -> packed: (KH, KW, C, O); flat grid over the O C KH KW inputs.
@compute @workgroup_size(256)
fn pack(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>, @builtin(local_invocation_id) lid: vec3<u32>) {
    let i = flat_index(wid, nwg, lid);
    let ckk = pp.c * pp.kk;
    if (i >= pp.o * ckk) { return; }
    let o = i / ckk;
    let c = (i % ckk) / pp.kk;
    let t = i % pp.kk;
    packed[(t * pp.c + c) * pp.o + o] = x[i];
}

// Window origins of this invocation's TM output positions (clamped into the image), accumulators zeroed.
fn init_rows(row0: u32, np: u32) {
    for (var r = 0u; r < TM; r++) {
        let q = min(row0 + r, np - 1u);
        iy0[r] = i32((q / p.ow) * p.stride) - i32(p.pt);
        ix0[r] = i32((q % p.ow) * p.stride) - i32(p.pl);
        acc[r] = vec4<f32>(0.0);
    }
}

// Input offsets (pixel index * mul + add) of the TM positions at kernel tap (ky, kx); 0 and !xok in padding.
fn tap_rows(ky: u32, kx: u32, mul: u32, add: u32) {
    for (var r = 0u; r < TM; r++) {
        let iy = iy0[r] + i32(ky);
        let ix = ix0[r] + i32(kx);
        xok[r] = iy >= 0 && iy < i32(p.h) && ix >= 0 && ix < i32(p.w);
        xoff[r] = select(0u, (u32(iy) * p.w + u32(ix)) * mul + add, xok[r]);
    }
}

// y[n, col0 + j, row0 + r] = acc[r][j] + bias (+ res) (then SiLU) (f16: saturated), guarded.
fn store_rows(n: u32, row0: u32, col0: u32, np: u32) {
    let yb = n * p.o * np;
    for (var r = 0u; r < TM; r++) {
        let q = row0 + r;
        if (q >= np) { return; }
        for (var j = 0u; j < 4u; j++) {
            let oc = col0 + j;
            if (oc < p.o) {
                var v = acc[r][j];
                if (p.has_bias == 1u) { v += f32(bias[oc]); }
                if (p.has_bias == 2u) { v += f32(bias[n * p.o + oc]); }
                let yi = yb + oc * np + q;
                if (p.has_res == 1u) { v += f32(res[yi]); }
                if (p.silu == 1u) { v = silu(v); }
                if (IS_F16) { v = clamp(v, -65504.0, 65504.0); }
                y[yi] = ST(v);
            }
        }
    }
}

// x: (N, C, H, W), packed w: (KH, KW, C, O), bias: (O) -> y: (N, O, OH, OW).
// Work groups: (ceil(O / 4 SG), ceil(OH OW / (WG / SG) TM), N).
@compute @workgroup_size(WG)
fn main(@builtin(workgroup_id) wid: vec3<u32>, @builtin(local_invocation_index) li: u32,
        @builtin(subgroup_invocation_id) lane: u32, @builtin(subgroup_size) sgs: u32) {
    let row0 = (wid.y * (WG / sgs) + li / sgs) * TM;
    // a subgroup past the last row leaves at once (uniform per subgroup; no barriers follow)
    if (row0 >= p.oh * p.ow) { return; }
    let np = p.oh * p.ow;
    let col0 = (wid.x * sgs + lane) * 4u;
    let col4 = min(col0, p.o - 4u) / 4u;
    let hw = p.h * p.w;
    let xb = wid.z * p.c * hw;
    let o4 = p.o / 4u;
    init_rows(row0, np);
    for (var ky = 0u; ky < p.kh; ky++) {
        for (var kx = 0u; kx < p.kw; kx++) {
            tap_rows(ky, kx, 1u, 0u);
            // packed row of (ky, kx, c): ((ky KW + kx) C + c) O / 4 + col4
            let wrow = (ky * p.kw + kx) * p.c;
            for (var c0 = 0u; c0 < p.c; c0 += 8u) {
                let cl = c0 + (lane & 7u);
                let xc = xb + min(cl, p.c - 1u) * hw;
                for (var r = 0u; r < TM; r++) {
                    av[r] = select(0.0, f32(x[xc + xoff[r]]), xok[r] && cl < p.c);
                }
                let wb = (wrow + c0) * o4 + col4;
                let cm = (p.c - 1u - c0) * o4;
                fma_k0(ld4(wb));
                fma_k1(ld4(wb + min(o4, cm)));
                fma_k2(ld4(wb + min(2u * o4, cm)));
                fma_k3(ld4(wb + min(3u * o4, cm)));
                fma_k4(ld4(wb + min(4u * o4, cm)));
                fma_k5(ld4(wb + min(5u * o4, cm)));
                fma_k6(ld4(wb + min(6u * o4, cm)));
                fma_k7(ld4(wb + min(7u * o4, cm)));
            }
        }
    }
    store_rows(wid.z, row0, col0, np);
}

// 4 k steps (channels c0 + 4 q .. + 3): input from component c of lane q's vec4.
fn fma_q0(b0: vec4<f32>, b1: vec4<f32>, b2: vec4<f32>, b3: vec4<f32>) { for (var r = 0u; r < TM; r++) { let v = av4[r]; acc[r] = fma(vec4<f32>(subgroupBroadcast(v.x, 0u)), b0, acc[r]); acc[r] = fma(vec4<f32>(subgroupBroadcast(v.y, 0u)), b1, acc[r]); acc[r] = fma(vec4<f32>(subgroupBroadcast(v.z, 0u)), b2, acc[r]); acc[r] = fma(vec4<f32>(subgroupBroadcast(v.w, 0u)), b3, acc[r]); } }
fn fma_q1(b0: vec4<f32>, b1: vec4<f32>, b2: vec4<f32>, b3: vec4<f32>) { for (var r = 0u; r < TM; r++) { let v = av4[r]; acc[r] = fma(vec4<f32>(subgroupBroadcast(v.x, 1u)), b0, acc[r]); acc[r] = fma(vec4<f32>(subgroupBroadcast(v.y, 1u)), b1, acc[r]); acc[r] = fma(vec4<f32>(subgroupBroadcast(v.z, 1u)), b2, acc[r]); acc[r] = fma(vec4<f32>(subgroupBroadcast(v.w, 1u)), b3, acc[r]); } }
fn fma_q2(b0: vec4<f32>, b1: vec4<f32>, b2: vec4<f32>, b3: vec4<f32>) { for (var r = 0u; r < TM; r++) { let v = av4[r]; acc[r] = fma(vec4<f32>(subgroupBroadcast(v.x, 2u)), b0, acc[r]); acc[r] = fma(vec4<f32>(subgroupBroadcast(v.y, 2u)), b1, acc[r]); acc[r] = fma(vec4<f32>(subgroupBroadcast(v.z, 2u)), b2, acc[r]); acc[r] = fma(vec4<f32>(subgroupBroadcast(v.w, 2u)), b3, acc[r]); } }
fn fma_q3(b0: vec4<f32>, b1: vec4<f32>, b2: vec4<f32>, b3: vec4<f32>) { for (var r = 0u; r < TM; r++) { let v = av4[r]; acc[r] = fma(vec4<f32>(subgroupBroadcast(v.x, 3u)), b0, acc[r]); acc[r] = fma(vec4<f32>(subgroupBroadcast(v.y, 3u)), b1, acc[r]); acc[r] = fma(vec4<f32>(subgroupBroadcast(v.z, 3u)), b2, acc[r]); acc[r] = fma(vec4<f32>(subgroupBroadcast(v.w, 3u)), b3, acc[r]); } }
fn fma_q4(b0: vec4<f32>, b1: vec4<f32>, b2: vec4<f32>, b3: vec4<f32>) { for (var r = 0u; r < TM; r++) { let v = av4[r]; acc[r] = fma(vec4<f32>(subgroupBroadcast(v.x, 4u)), b0, acc[r]); acc[r] = fma(vec4<f32>(subgroupBroadcast(v.y, 4u)), b1, acc[r]); acc[r] = fma(vec4<f32>(subgroupBroadcast(v.z, 4u)), b2, acc[r]); acc[r] = fma(vec4<f32>(subgroupBroadcast(v.w, 4u)), b3, acc[r]); } }
fn fma_q5(b0: vec4<f32>, b1: vec4<f32>, b2: vec4<f32>, b3: vec4<f32>) { for (var r = 0u; r < TM; r++) { let v = av4[r]; acc[r] = fma(vec4<f32>(subgroupBroadcast(v.x, 5u)), b0, acc[r]); acc[r] = fma(vec4<f32>(subgroupBroadcast(v.y, 5u)), b1, acc[r]); acc[r] = fma(vec4<f32>(subgroupBroadcast(v.z, 5u)), b2, acc[r]); acc[r] = fma(vec4<f32>(subgroupBroadcast(v.w, 5u)), b3, acc[r]); } }
fn fma_q6(b0: vec4<f32>, b1: vec4<f32>, b2: vec4<f32>, b3: vec4<f32>) { for (var r = 0u; r < TM; r++) { let v = av4[r]; acc[r] = fma(vec4<f32>(subgroupBroadcast(v.x, 6u)), b0, acc[r]); acc[r] = fma(vec4<f32>(subgroupBroadcast(v.y, 6u)), b1, acc[r]); acc[r] = fma(vec4<f32>(subgroupBroadcast(v.z, 6u)), b2, acc[r]); acc[r] = fma(vec4<f32>(subgroupBroadcast(v.w, 6u)), b3, acc[r]); } }
fn fma_q7(b0: vec4<f32>, b1: vec4<f32>, b2: vec4<f32>, b3: vec4<f32>) { for (var r = 0u; r < TM; r++) { let v = av4[r]; acc[r] = fma(vec4<f32>(subgroupBroadcast(v.x, 7u)), b0, acc[r]); acc[r] = fma(vec4<f32>(subgroupBroadcast(v.y, 7u)), b1, acc[r]); acc[r] = fma(vec4<f32>(subgroupBroadcast(v.z, 7u)), b2, acc[r]); acc[r] = fma(vec4<f32>(subgroupBroadcast(v.w, 7u)), b3, acc[r]); } }

// The same on the input transposed to xt: (H, W, N, C) (by `pack` with (o, c, kk) = (N C, 1, H W)): channels
// are contiguous, so lanes 0..7 load 4 channels each with ONE vec4 (f16: vec2<u32>) per position, 32 channels
// per chunk: a quarter of the input load instructions of `main`. Needs C % 4 == 0 (and O % 4 == 0).
// Loop budget: KH KW (ceil(C / 32) + 1) + KH back-edges per invocation.
@compute @workgroup_size(WG)
fn hwnc(@builtin(workgroup_id) wid: vec3<u32>, @builtin(local_invocation_index) li: u32,
        @builtin(subgroup_invocation_id) lane: u32, @builtin(subgroup_size) sgs: u32) {
    let row0 = (wid.y * (WG / sgs) + li / sgs) * TM;
    // a subgroup past the last row leaves at once (uniform per subgroup; no barriers follow)
    if (row0 >= p.oh * p.ow) { return; }
    let np = p.oh * p.ow;
    let col0 = (wid.x * sgs + lane) * 4u;
    let col4 = min(col0, p.o - 4u) / 4u;
    let o4 = p.o / 4u;
    init_rows(row0, np);
    for (var ky = 0u; ky < p.kh; ky++) {
        for (var kx = 0u; kx < p.kw; kx++) {
            tap_rows(ky, kx, p.n * p.c, wid.z * p.c);
            let wrow = (ky * p.kw + kx) * p.c;
            for (var c0 = 0u; c0 < p.c; c0 += 32u) {
                let cl = c0 + 4u * (lane & 7u);
                let clc = min(cl, p.c - 4u);
                for (var r = 0u; r < TM; r++) {
                    av4[r] = select(vec4<f32>(0.0), ldx4((xoff[r] + clc) / 4u), xok[r] && cl < p.c);
                }
                let wb = (wrow + c0) * o4 + col4;
                let cm = (p.c - 1u - c0) * o4;
                fma_q0(ld4(wb), ld4(wb + min(1u * o4, cm)), ld4(wb + min(2u * o4, cm)), ld4(wb + min(3u * o4, cm)));
                fma_q1(ld4(wb + min(4u * o4, cm)), ld4(wb + min(5u * o4, cm)), ld4(wb + min(6u * o4, cm)), ld4(wb + min(7u * o4, cm)));
                fma_q2(ld4(wb + min(8u * o4, cm)), ld4(wb + min(9u * o4, cm)), ld4(wb + min(10u * o4, cm)), ld4(wb + min(11u * o4, cm)));
                fma_q3(ld4(wb + min(12u * o4, cm)), ld4(wb + min(13u * o4, cm)), ld4(wb + min(14u * o4, cm)), ld4(wb + min(15u * o4, cm)));
                fma_q4(ld4(wb + min(16u * o4, cm)), ld4(wb + min(17u * o4, cm)), ld4(wb + min(18u * o4, cm)), ld4(wb + min(19u * o4, cm)));
                fma_q5(ld4(wb + min(20u * o4, cm)), ld4(wb + min(21u * o4, cm)), ld4(wb + min(22u * o4, cm)), ld4(wb + min(23u * o4, cm)));
                fma_q6(ld4(wb + min(24u * o4, cm)), ld4(wb + min(25u * o4, cm)), ld4(wb + min(26u * o4, cm)), ld4(wb + min(27u * o4, cm)));
                fma_q7(ld4(wb + min(28u * o4, cm)), ld4(wb + min(29u * o4, cm)), ld4(wb + min(30u * o4, cm)), ld4(wb + min(31u * o4, cm)));
            }
        }
    }
    store_rows(wid.z, row0, col0, np);
}
