//! variant f32: alias ST = f32; const IS_F16: bool = false;
//! variant f16: enable f16; alias ST = f16; const IS_F16: bool = true;
// 3x3 stride-1 conv with few output channels (O <= 4: a model's last conv, to RGB or latents), optionally
// through a GroupNorm + SiLU prologue (`norm::group_norm_stats`, as the Winograd input transforms). The implicit
// GEMM puts O on its 16-row register tile (13 of 16 rows idle at O = 3) and loads the input once per tap; here an
// invocation owns 8 consecutive output pixels of one row for all O channels and, per input channel, loads its
// 3 x 10 input window once (vec4 loads where W % 4 == 0 and the left padding is 1). Weights: per chunk of 8
// input channels, lane l loads channel c0 + l's O x 9 taps and the others read them with subgroupBroadcast
// (loads spread over the lanes instead of every lane loading every weight). Every invocation of a subgroup runs to the end (the shuffles
// need all lanes); those past the output only skip their stores.
// Loop budget: ceil(C / 8) chunks x 8 channels (+ 3 constant-trip loops) per invocation: C = 2560 -> ~2600.

struct NarrowParams {
    n: u32, c: u32, h: u32, w: u32,
    o: u32, oh: u32, ow: u32,
    pt: u32, pl: u32,
    // 0 none, 1 bias (O), 2 bias (N, O)
    has_bias: u32,
    // 1: add res (N, O, OH, OW) (the launcher binds y otherwise)
    has_res: u32,
    // 1: SiLU on the result
    silu: u32,
    // 1: x read through the prologue silu((x - x0) scale + shift), ss: (N, C) (scale, shift, x0, -)
    pre: u32,
    // 1: window rows as vec4 loads (W % 4 == 0, left padding 1)
    rows4: u32,
}

@group(0) @binding(0) var<storage, read> x: array<ST>;
@group(0) @binding(1) var<storage, read> wt: array<ST>;
@group(0) @binding(2) var<storage, read> bias: array<ST>;
@group(0) @binding(3) var<storage, read_write> y: array<ST>;
@group(0) @binding(4) var<storage, read> res: array<ST>;
// the prologue's statistics (the launcher binds x when unused)
@group(0) @binding(5) var<storage, read> ss: array<vec4<f32>>;
// x again as vec4s (naga refuses two views of one binding in one entry point)
@group(0) @binding(6) var<storage, read> x4: array<vec4<ST>>;
var<immediate> p: NarrowParams;

const F16_MAX: f32 = 65504.0;

// One loaded input value through the prologue (when p.pre), 0 where `ok` is false (the conv pads the
// normalised input with zeros).
fn pro(v: f32, ok: bool, a: vec4<f32>) -> f32 {
    var t = v;
    if (p.pre == 1u) {
        t = (v - a.z) * a.x + a.y;
        t = t / (1.0 + exp(-t));
    }
    return select(0.0, t, ok);
}

// Input row iy, columns ix0 .. ix0 + 9 of the plane at `base`.
fn xrow10(base: u32, iy: i32, ix0: i32, a: vec4<f32>) -> array<f32, 10> {
    var r: array<f32, 10>;
    let rok = iy >= 0 && iy < i32(p.h);
    let rb = base + u32(clamp(iy, 0, i32(p.h) - 1)) * p.w;
    if (p.rows4 == 1u) {
        // ix0 = 8 q - 1: columns 8 q .. 8 q + 7 are two aligned vec4s
        let x0 = u32(ix0 + 1);
        let q0 = vec4<f32>(x4[(rb + min(x0, p.w - 4u)) / 4u]);
        let q1 = vec4<f32>(x4[(rb + min(x0 + 4u, p.w - 4u)) / 4u]);
        let ok0 = rok && x0 < p.w;
        let ok1 = rok && x0 + 4u < p.w;
        r[0] = pro(f32(x[rb + max(x0, 1u) - 1u]), rok && x0 >= 1u, a);
        for (var k = 0u; k < 4u; k++) {
            r[1u + k] = pro(q0[k], ok0, a);
            r[5u + k] = pro(q1[k], ok1, a);
        }
        r[9] = pro(f32(x[rb + min(x0 + 8u, p.w - 1u)]), rok && x0 + 8u < p.w, a);
    } else {
        for (var k = 0; k < 10; k++) {
            let ix = ix0 + k;
            let ok = rok && ix >= 0 && ix < i32(p.w);
            r[k] = pro(f32(x[rb + u32(clamp(ix, 0, i32(p.w) - 1))]), ok, a);
        }
    }
    return r;
}

// acc[k]: output pixel k of the strip, a vec4 over the (up to 4) output channels. Every loop below has a
// constant trip count and is unrolled by NIR, so all private arrays are indexed statically (dynamic indexing
// of private arrays is a per-lane memory loop on lavapipe).
var<private> acc: array<vec4<f32>, 8>;

// acc += kernel row ky of one input channel: r its input row, wk[ky * 3 + kx] the tap's weights over o.
fn add_row(r: array<f32, 10>, wk: array<vec4<f32>, 9>, ky: u32) {
    for (var kx = 0u; kx < 3u; kx++) {
        let wv = wk[ky * 3u + kx];
        for (var k = 0u; k < 8u; k++) {
            acc[k] = fma(wv, vec4<f32>(r[k + kx]), acc[k]);
        }
    }
}

// One input channel c of image n: its 3 window rows against its weights wk.
fn channel(n: u32, c: u32, iy0: i32, ix0: i32, wk: array<vec4<f32>, 9>) {
    var a = vec4<f32>(0.0);
    if (p.pre == 1u) { a = ss[n * p.c + c]; }
    let base = (n * p.c + c) * p.h * p.w;
    add_row(xrow10(base, iy0, ix0, a), wk, 0u);
    add_row(xrow10(base, iy0 + 1, ix0, a), wk, 1u);
    add_row(xrow10(base, iy0 + 2, ix0, a), wk, 2u);
}

// The weights of lane j (subgroupBroadcast needs a constant lane: one function per lane).
fn bw0(w: array<vec4<f32>, 9>) -> array<vec4<f32>, 9> { var r: array<vec4<f32>, 9>; for (var t = 0u; t < 9u; t++) { r[t] = subgroupBroadcast(w[t], 0u); } return r; }
fn bw1(w: array<vec4<f32>, 9>) -> array<vec4<f32>, 9> { var r: array<vec4<f32>, 9>; for (var t = 0u; t < 9u; t++) { r[t] = subgroupBroadcast(w[t], 1u); } return r; }
fn bw2(w: array<vec4<f32>, 9>) -> array<vec4<f32>, 9> { var r: array<vec4<f32>, 9>; for (var t = 0u; t < 9u; t++) { r[t] = subgroupBroadcast(w[t], 2u); } return r; }
fn bw3(w: array<vec4<f32>, 9>) -> array<vec4<f32>, 9> { var r: array<vec4<f32>, 9>; for (var t = 0u; t < 9u; t++) { r[t] = subgroupBroadcast(w[t], 3u); } return r; }
fn bw4(w: array<vec4<f32>, 9>) -> array<vec4<f32>, 9> { var r: array<vec4<f32>, 9>; for (var t = 0u; t < 9u; t++) { r[t] = subgroupBroadcast(w[t], 4u); } return r; }
fn bw5(w: array<vec4<f32>, 9>) -> array<vec4<f32>, 9> { var r: array<vec4<f32>, 9>; for (var t = 0u; t < 9u; t++) { r[t] = subgroupBroadcast(w[t], 5u); } return r; }
fn bw6(w: array<vec4<f32>, 9>) -> array<vec4<f32>, 9> { var r: array<vec4<f32>, 9>; for (var t = 0u; t < 9u; t++) { r[t] = subgroupBroadcast(w[t], 6u); } return r; }
fn bw7(w: array<vec4<f32>, 9>) -> array<vec4<f32>, 9> { var r: array<vec4<f32>, 9>; for (var t = 0u; t < 9u; t++) { r[t] = subgroupBroadcast(w[t], 7u); } return r; }

// x: (N, C, H, W), wt: (O, C, 3, 3) -> y: (N, O, OH, OW); invocation = (n, oy, 8-pixel strip), strip fastest.
@compute @workgroup_size(256)
fn main(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>, @builtin(local_invocation_id) lid: vec3<u32>,
        @builtin(subgroup_invocation_id) lane: u32) {
    let strips = (p.ow + 7u) / 8u;
    let total = p.n * p.oh * strips;
    let i0 = flat_index(wid, nwg, lid);
    let live = i0 < total;
    let i = min(i0, total - 1u);
    let sx = i % strips;
    let oy = (i / strips) % p.oh;
    let n = i / (strips * p.oh);
    let ox0 = 8u * sx;
    let iy0 = i32(oy) - i32(p.pt);
    let ix0 = i32(ox0) - i32(p.pl);
    for (var k = 0u; k < 8u; k++) {
        acc[k] = vec4<f32>(0.0);
    }
    let l8 = lane & 7u;
    for (var c0 = 0u; c0 < p.c; c0 += 8u) {
        // this lane's channel of the chunk: its 9 taps, each a vec4 over o (0 for o >= O)
        let cl = min(c0 + l8, p.c - 1u);
        var wl: array<vec4<f32>, 9>;
        for (var t = 0u; t < 9u; t++) {
            var v = vec4<f32>(0.0);
            for (var o = 0u; o < 4u; o++) {
                v[o] = select(0.0, f32(wt[(min(o, p.o - 1u) * p.c + cl) * 9u + t]), o < p.o);
            }
            wl[t] = v;
        }
        // uniform over the subgroup: every lane takes the same branches
        channel(n, c0, iy0, ix0, bw0(wl));
        if (c0 + 1u < p.c) { channel(n, c0 + 1u, iy0, ix0, bw1(wl)); }
        if (c0 + 2u < p.c) { channel(n, c0 + 2u, iy0, ix0, bw2(wl)); }
        if (c0 + 3u < p.c) { channel(n, c0 + 3u, iy0, ix0, bw3(wl)); }
        if (c0 + 4u < p.c) { channel(n, c0 + 4u, iy0, ix0, bw4(wl)); }
        if (c0 + 5u < p.c) { channel(n, c0 + 5u, iy0, ix0, bw5(wl)); }
        if (c0 + 6u < p.c) { channel(n, c0 + 6u, iy0, ix0, bw6(wl)); }
        if (c0 + 7u < p.c) { channel(n, c0 + 7u, iy0, ix0, bw7(wl)); }
    }
    if (!live) { return; }
    for (var o = 0u; o < 4u; o++) {
        if (o < p.o) {
            var b = 0.0;
            if (p.has_bias == 1u) { b = f32(bias[o]); }
            if (p.has_bias == 2u) { b = f32(bias[n * p.o + o]); }
            let yb = ((n * p.o + o) * p.oh + oy) * p.ow;
            for (var k = 0u; k < 8u; k++) {
                let ox = ox0 + k;
                if (ox < p.ow) {
                    var v = acc[k][o] + b;
                    if (p.has_res == 1u) { v += f32(res[yb + ox]); }
                    if (p.silu == 1u) { v = silu(v); }
                    if (IS_F16) { v = clamp(v, -F16_MAX, F16_MAX); }
                    y[yb + ox] = ST(v);
                }
            }
        }
    }
}
