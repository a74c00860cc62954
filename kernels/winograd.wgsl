//! variant f32: alias ST = f32; const IS_F16: bool = false; fn ldm(i: u32) -> vec4<f32> { return m4[i]; } fn ldx4(i: u32) -> vec4<f32> { return vec4<f32>(x4[i]); } fn ldr4(i: u32) -> vec4<f32> { return vec4<f32>(res4[i]); }
//! variant f16: enable f16; alias ST = f16; const IS_F16: bool = true; fn ldm(i: u32) -> vec4<f32> { return m4[i]; } fn ldx4(i: u32) -> vec4<f32> { return vec4<f32>(x4[i]); } fn ldr4(i: u32) -> vec4<f32> { return vec4<f32>(res4[i]); }
//! variant f32t: alias ST = f32; const IS_F16: bool = false; fn ldm(i: u32) -> vec4<f32> { return textureLoad(mt, texel_xy(i)); } fn ldx4(i: u32) -> vec4<f32> { return textureLoad(xt, texel_xy(i)); } fn ldr4(i: u32) -> vec4<f32> { return textureLoad(rt, texel_xy(i)); }
//! variant f16t: enable f16; alias ST = f16; const IS_F16: bool = true; fn ldm(i: u32) -> vec4<f32> { return textureLoad(mt, texel_xy(i)); } fn ldx4(i: u32) -> vec4<f32> { return vec4<f32>(x4[i]); } fn ldr4(i: u32) -> vec4<f32> { return vec4<f32>(res4[i]); }
// Winograd F(4x4, 3x3) for stride-1 3x3 convs (Lavin & Gray 2015): y = A^T [ (G g G^T) * (B^T d B) ] A per 4x4
// output tile, d the 6x6 input window. The 36 products over channels form 36 independent GEMMs
// (tiles x C) . (C x O), run by the tiled matmul between the `input` and `output` transforms here; on lavapipe
// that is 4x fewer multiply-adds than the implicit GEMM, for 2.25x more (f32) intermediate traffic.
// Activations x, y in ST; the transformed tensors V, U, M are f32 (the transforms scale values by up to ~100x,
// which f16 storage would not round well). Matrices (points 0, +-1, +-2, inf):
//   B^T = [4 0 -5 0 1 0; 0 -4 -4 1 1 0; 0 4 -4 -1 1 0; 0 -2 -1 2 1 0; 0 2 -1 -2 1 0; 0 4 0 -5 0 1]
//   G = [1/4 0 0; -1/6 -1/6 -1/6; -1/6 1/6 -1/6; 1/24 1/12 1/6; 1/24 -1/12 1/6; 0 0 1]
//   A^T = [1 1 1 1 1 0; 0 1 -1 2 -2 0; 0 1 1 4 4 0; 0 1 -1 8 -8 1]
// No loops beyond the constant 6- and 4-trip ones (unrolled): nothing near lavapipe's loop budget.

struct WinoParams {
    n: u32, c: u32, h: u32, w: u32,
    o: u32, oh: u32, ow: u32,
    // tiles per image: th x tw (ceil(oh / 4), ceil(ow / 4))
    th: u32, tw: u32,
    pt: u32, pl: u32,
    // this slab: global tiles t0 .. t0 + nt (tiles numbered over (n, ty, tx))
    t0: u32, nt: u32,
    // 0 none, 1 bias (O), 2 bias (N, O)
    has_bias: u32,
    // 1: add res (N, O, OH, OW) (a fused residual; the launcher binds y at binding 3 otherwise)
    has_res: u32,
    // 1: SiLU on the result
    silu: u32,
    // 1: x is stored at half the conv's input size (h, w), read through a nearest 2x upsampling (`input`,
    // `input4s` only): the upsampled tensor is never written
    up: u32,
    // 1: `output6p` also writes per-tile-pair statistics of its output to `part` (see there)
    stats: u32,
}

@group(0) @binding(0) var<storage, read> x: array<ST>;
@group(0) @binding(1) var<storage, read_write> v: array<f32>;
// GroupNorm + SiLU prologue of the `*_gs` input entries: per (n, c) (scale, shift, x0, -) from
// `norm::group_norm_stats`; the conv reads silu((x - x0) scale + shift). Every input entry binds it (the
// launcher passes x when unused) so all input entries share one binding layout.
@group(0) @binding(2) var<storage, read> ss: array<vec4<f32>>;
// output transform: m (36, nt, O) f32 -> y (N, O, OH, OW)
@group(0) @binding(0) var<storage, read> m: array<f32>;
@group(0) @binding(1) var<storage, read> bias: array<ST>;
@group(0) @binding(2) var<storage, read_write> y: array<ST>;
@group(0) @binding(3) var<storage, read> res: array<ST>;
// weight transform: w (O, C, 3, 3) -> u (36, C, O) f32
@group(0) @binding(0) var<storage, read> wsrc: array<ST>;
@group(0) @binding(1) var<storage, read_write> u: array<f32>;
var<immediate> p: WinoParams;

const F16_MAX: f32 = 65504.0;

// (image n, tile row ty, tile column tx) of slab tile tl (tiles numbered over (n, ty, tx)).
fn tile(tl: u32) -> vec3<u32> {
    let t = p.t0 + tl;
    let tpi = p.th * p.tw;
    return vec3<u32>(t / tpi, (t % tpi) / p.tw, t % p.tw);
}

// B^T d for one 6-vector (columns of the window, then rows).
fn bt(d: array<f32, 6>) -> array<f32, 6> {
    return array<f32, 6>(
        4.0 * d[0] - 5.0 * d[2] + d[4],
        -4.0 * d[1] - 4.0 * d[2] + d[3] + d[4],
        4.0 * d[1] - 4.0 * d[2] - d[3] + d[4],
        -2.0 * d[1] - d[2] + 2.0 * d[3] + d[4],
        2.0 * d[1] - d[2] - 2.0 * d[3] + d[4],
        4.0 * d[1] - 5.0 * d[3] + d[5]);
}

// A^T s for one 6-vector.
fn at(s: array<f32, 6>) -> vec4<f32> {
    return vec4<f32>(
        s[0] + s[1] + s[2] + s[3] + s[4],
        s[1] - s[2] + 2.0 * (s[3] - s[4]),
        s[1] + s[2] + 4.0 * (s[3] + s[4]),
        s[1] - s[2] + 8.0 * (s[3] - s[4]) + s[5]);
}

// G g for one 3-vector.
fn gg(g: vec3<f32>) -> array<f32, 6> {
    return array<f32, 6>(
        0.25 * g.x,
        -(g.x + g.y + g.z) / 6.0,
        -(g.x - g.y + g.z) / 6.0,
        g.x / 24.0 + g.y / 12.0 + g.z / 6.0,
        g.x / 24.0 - g.y / 12.0 + g.z / 6.0,
        g.z);
}

// The prologue on a loaded value: identity, or silu((v - x0) scale + shift) with a = (scale, shift, x0) when
// `pre` (a literal in every entry point: NIR inlines and folds the branch, so plain entries pay nothing).
fn act(v: f32, pre: bool, a: vec4<f32>) -> f32 {
    if (!pre) { return v; }
    let t = (v - a.z) * a.x + a.y;
    return t / (1.0 + exp(-t));
}

fn act4(v: vec4<f32>, pre: bool, a: vec4<f32>) -> vec4<f32> {
    if (!pre) { return v; }
    let t = (v - a.z) * a.x + a.y;
    return t / (1.0 + exp(-t));
}

// (scale, shift, x0) of image n, channel c for the prologue (unused without it).
fn pre_of(pre: bool, n: u32, c: u32) -> vec4<f32> {
    if (!pre) { return vec4<f32>(0.0); }
    return ss[n * p.c + c];
}

// x[n, c, iy, ix] (through the prologue), 0 outside the image (the conv pads the normalised input with zeros).
// With p.up the stored plane is (h / 2, w / 2) and (iy, ix) reads its (iy / 2, ix / 2).
fn xin(base: u32, iy: i32, ix: i32, pre: bool, a: vec4<f32>) -> f32 {
    let ok = iy >= 0 && iy < i32(p.h) && ix >= 0 && ix < i32(p.w);
    let o = base + (u32(clamp(iy, 0, i32(p.h) - 1)) >> p.up) * (p.w >> p.up) + (u32(clamp(ix, 0, i32(p.w) - 1)) >> p.up);
    return select(0.0, act(f32(x[o]), pre, a), ok);
}

// Window row r (input row iy) of 6 values from column ix0.
fn xrow(base: u32, iy: i32, ix0: i32, pre: bool, a: vec4<f32>) -> array<f32, 6> {
    return array<f32, 6>(xin(base, iy, ix0, pre, a), xin(base, iy, ix0 + 1, pre, a), xin(base, iy, ix0 + 2, pre, a),
                         xin(base, iy, ix0 + 3, pre, a), xin(base, iy, ix0 + 4, pre, a), xin(base, iy, ix0 + 5, pre, a));
}

// x: (N, C, H, W) -> v: (36, nt, C); invocation = (slab tile, channel), channel fastest. `input_gs`: through
// the GroupNorm + SiLU prologue.
@compute @workgroup_size(256)
fn input(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>, @builtin(local_invocation_id) lid: vec3<u32>) {
    input_impl(flat_index(wid, nwg, lid), false);
}

@compute @workgroup_size(256)
fn input_gs(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>, @builtin(local_invocation_id) lid: vec3<u32>) {
    input_impl(flat_index(wid, nwg, lid), true);
}

fn input_impl(i: u32, pre: bool) {
    if (i >= p.nt * p.c) { return; }
    let c = i % p.c;
    let tl = i / p.c;
    let tc = tile(tl);
    let n = tc.x;
    let ty = tc.y;
    let tx = tc.z;
    let base = (n * p.c + c) * (p.h >> p.up) * (p.w >> p.up);
    let iy0 = i32(4u * ty) - i32(p.pt);
    let ix0 = i32(4u * tx) - i32(p.pl);
    let a = pre_of(pre, n, c);
    // rows of B^T d: first each input row along x (d B), then along y
    let r0 = bt(xrow(base, iy0, ix0, pre, a));
    let r1 = bt(xrow(base, iy0 + 1, ix0, pre, a));
    let r2 = bt(xrow(base, iy0 + 2, ix0, pre, a));
    let r3 = bt(xrow(base, iy0 + 3, ix0, pre, a));
    let r4 = bt(xrow(base, iy0 + 4, ix0, pre, a));
    let r5 = bt(xrow(base, iy0 + 5, ix0, pre, a));
    let st = p.nt * p.c;
    let o0 = tl * p.c + c;
    for (var j = 0u; j < 6u; j++) {
        let col = bt(array<f32, 6>(r0[j], r1[j], r2[j], r3[j], r4[j], r5[j]));
        for (var i2 = 0u; i2 < 6u; i2++) {
            v[(i2 * 6u + j) * st + o0] = col[i2];
        }
    }
}

fn out_val(val: f32) -> ST {
    if (IS_F16) { return ST(clamp(val, -F16_MAX, F16_MAX)); }
    return ST(val);
}

// m: (36, nt, O) -> y: (N, O, OH, OW) (+ bias); invocation = (slab tile, output channel), channel fastest.
@compute @workgroup_size(256)
fn output(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>, @builtin(local_invocation_id) lid: vec3<u32>) {
    let i = flat_index(wid, nwg, lid);
    if (i >= p.nt * p.o) { return; }
    let o = i % p.o;
    let tl = i / p.o;
    let tc = tile(tl);
    let n = tc.x;
    let ty = tc.y;
    let tx = tc.z;
    let st = p.nt * p.o;
    let o0 = tl * p.o + o;
    // columns of A^T M: 6 columns j, each reducing the 6 rows i
    var cols: array<vec4<f32>, 6>;
    for (var j = 0u; j < 6u; j++) {
        cols[j] = at(array<f32, 6>(m[(0u + j) * st + o0], m[(6u + j) * st + o0], m[(12u + j) * st + o0],
                                   m[(18u + j) * st + o0], m[(24u + j) * st + o0], m[(30u + j) * st + o0]));
    }
    var b = 0.0;
    if (p.has_bias == 1u) { b = f32(bias[o]); }
    if (p.has_bias == 2u) { b = f32(bias[n * p.o + o]); }
    let ybase = (n * p.o + o) * p.oh * p.ow;
    for (var r = 0u; r < 4u; r++) {
        let row = at(array<f32, 6>(cols[0][r], cols[1][r], cols[2][r], cols[3][r], cols[4][r], cols[5][r]));
        let yy = 4u * ty + r;
        if (yy < p.oh) {
            for (var s = 0u; s < 4u; s++) {
                let xx = 4u * tx + s;
                let yi = ybase + yy * p.ow + xx;
                if (xx < p.ow) {
                    var val = row[s] + b;
                    if (p.has_res == 1u) { val += f32(res[yi]); }
                    if (p.silu == 1u) { val = silu(val); }
                    y[yi] = out_val(val);
                }
            }
        }
    }
}

// w: (O, C, 3, 3) -> u: (36, C, O) = G g G^T per (o, c); flat grid over O C.
@compute @workgroup_size(256)
fn weight(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>, @builtin(local_invocation_id) lid: vec3<u32>) {
    let i = flat_index(wid, nwg, lid);
    if (i >= p.o * p.c) { return; }
    let o = i / p.c;
    let c = i % p.c;
    let b = i * 9u;
    // G g per kernel row, then G (.)^T along the rows
    let k0 = gg(vec3<f32>(f32(wsrc[b]), f32(wsrc[b + 1u]), f32(wsrc[b + 2u])));
    let k1 = gg(vec3<f32>(f32(wsrc[b + 3u]), f32(wsrc[b + 4u]), f32(wsrc[b + 5u])));
    let k2 = gg(vec3<f32>(f32(wsrc[b + 6u]), f32(wsrc[b + 7u]), f32(wsrc[b + 8u])));
    let st = p.c * p.o;
    for (var j = 0u; j < 6u; j++) {
        let col = gg(vec3<f32>(k0[j], k1[j], k2[j]));
        for (var i2 = 0u; i2 < 6u; i2++) {
            u[(i2 * 6u + j) * st + c * p.o + o] = col[i2];
        }
    }
}

// ---- vec4 forms (fewer per-lane storage accesses on lavapipe): 4 channels per invocation, rows loaded as
// vec4s. `input4` needs C % 4 == 0, W % 4 == 0 and left padding 1; `output4` needs O % 4 == 0 and OW % 4 == 0.
@group(0) @binding(0) var<storage, read> x4: array<vec4<ST>>;
@group(0) @binding(1) var<storage, read_write> v4: array<vec4<f32>>;
@group(0) @binding(0) var<storage, read> m4: array<vec4<f32>>;
// variants f32t / f16t read m4 (and f32t x4 and res4) through the buffers' texel views instead (`ldm`, `ldx4`,
// `ldr4`; src/vk/image.rs): one 16-byte fetch per lane on lavapipe instead of four bounds-checked scalar loads.
// res may be y itself: each element is read by the invocation that then writes it, read first.
@group(0) @binding(0) var mt: texture_storage_2d<rgba32float, read>;
@group(0) @binding(0) var xt: texture_storage_2d<rgba32float, read>;
@group(0) @binding(3) var rt: texture_storage_2d<rgba32float, read>;
@group(0) @binding(2) var<storage, read_write> y4: array<vec4<ST>>;
@group(0) @binding(3) var<storage, read> res4: array<vec4<ST>>;
// scalar view of x for `input4` (bound a second time by the launcher: naga refuses two views of one binding in
// one entry point)
@group(0) @binding(3) var<storage, read> xs: array<ST>;

fn bt4(d: array<vec4<f32>, 6>) -> array<vec4<f32>, 6> {
    return array<vec4<f32>, 6>(
        4.0 * d[0] - 5.0 * d[2] + d[4],
        -4.0 * d[1] - 4.0 * d[2] + d[3] + d[4],
        4.0 * d[1] - 4.0 * d[2] - d[3] + d[4],
        -2.0 * d[1] - d[2] + 2.0 * d[3] + d[4],
        2.0 * d[1] - d[2] - 2.0 * d[3] + d[4],
        4.0 * d[1] - 5.0 * d[3] + d[5]);
}

fn at4(s: array<vec4<f32>, 6>) -> array<vec4<f32>, 4> {
    return array<vec4<f32>, 4>(
        s[0] + s[1] + s[2] + s[3] + s[4],
        s[1] - s[2] + 2.0 * (s[3] - s[4]),
        s[1] + s[2] + 4.0 * (s[3] + s[4]),
        s[1] - s[2] + 8.0 * (s[3] - s[4]) + s[5]);
}

// The vec4 of row iy (of the plane at element `base`) starting at column 4 q4, 0 outside the image.
fn xq(base: u32, iy: i32, q4: i32, pre: bool, a: vec4<f32>) -> vec4<f32> {
    let ok = iy >= 0 && iy < i32(p.h) && q4 >= 0 && 4 * q4 < i32(p.w);
    let o = (base + u32(clamp(iy, 0, i32(p.h) - 1)) * p.w) / 4u + u32(clamp(q4, 0, i32(p.w / 4u) - 1));
    return select(vec4<f32>(0.0), act4(ldx4(o), pre, a), ok);
}

// Window row iy, columns 4 tx - 1 .. 4 tx + 4 (left padding 1) of one channel plane: the middle 4 as one vec4
// load, the two ends as scalar loads (on lavapipe every loaded component costs a bounds-checked load, so this
// reads 6 components instead of 3 vec4s' 12).
fn xrow4(base: u32, iy: i32, tx: i32, pre: bool, pa: vec4<f32>) -> array<f32, 6> {
    let b = xq(base, iy, tx, pre, pa);
    let ok = iy >= 0 && iy < i32(p.h);
    let rb = base + u32(clamp(iy, 0, i32(p.h) - 1)) * p.w;
    let xl = 4 * tx - 1;
    let xr = 4 * tx + 4;
    let a = select(0.0, act(f32(xs[rb + u32(max(xl, 0))]), pre, pa), ok && xl >= 0);
    let c = select(0.0, act(f32(xs[rb + u32(min(xr, i32(p.w) - 1))]), pre, pa), ok && xr < i32(p.w));
    return array<f32, 6>(a, b.x, b.y, b.z, b.w, c);
}

// One window row of 4 channel planes as vec4s over the channels; pa[k]: channel k's prologue.
fn xrow4c(base: u32, plane: u32, iy: i32, tx: i32, pre: bool, pa: array<vec4<f32>, 4>) -> array<vec4<f32>, 6> {
    let r0 = xrow4(base, iy, tx, pre, pa[0]);
    let r1 = xrow4(base + plane, iy, tx, pre, pa[1]);
    let r2 = xrow4(base + 2u * plane, iy, tx, pre, pa[2]);
    let r3 = xrow4(base + 3u * plane, iy, tx, pre, pa[3]);
    return array<vec4<f32>, 6>(vec4<f32>(r0[0], r1[0], r2[0], r3[0]), vec4<f32>(r0[1], r1[1], r2[1], r3[1]),
                               vec4<f32>(r0[2], r1[2], r2[2], r3[2]), vec4<f32>(r0[3], r1[3], r2[3], r3[3]),
                               vec4<f32>(r0[4], r1[4], r2[4], r3[4]), vec4<f32>(r0[5], r1[5], r2[5], r3[5]));
}

// `input` for 4 channels c0 .. c0 + 3 per invocation (channel quad fastest); `input4_gs` with the prologue.
@compute @workgroup_size(256)
fn input4(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>, @builtin(local_invocation_id) lid: vec3<u32>) {
    input4_impl(flat_index(wid, nwg, lid), false);
}

@compute @workgroup_size(256)
fn input4_gs(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>, @builtin(local_invocation_id) lid: vec3<u32>) {
    input4_impl(flat_index(wid, nwg, lid), true);
}

// The 4 channels' prologues.
fn pre4(pre: bool, n: u32, c0: u32) -> array<vec4<f32>, 4> {
    return array<vec4<f32>, 4>(pre_of(pre, n, c0), pre_of(pre, n, c0 + 1u), pre_of(pre, n, c0 + 2u), pre_of(pre, n, c0 + 3u));
}

fn input4_impl(i: u32, pre: bool) {
    let cq = p.c / 4u;
    if (i >= p.nt * cq) { return; }
    let c0 = 4u * (i % cq);
    let tl = i / cq;
    let tc = tile(tl);
    let n = tc.x;
    let ty = tc.y;
    let tx = i32(tc.z);
    let plane = p.h * p.w;
    let base = (n * p.c + c0) * plane;
    let iy0 = i32(4u * ty) - i32(p.pt);
    let pa = pre4(pre, n, c0);
    let r0 = bt4(xrow4c(base, plane, iy0, tx, pre, pa));
    let r1 = bt4(xrow4c(base, plane, iy0 + 1, tx, pre, pa));
    let r2 = bt4(xrow4c(base, plane, iy0 + 2, tx, pre, pa));
    let r3 = bt4(xrow4c(base, plane, iy0 + 3, tx, pre, pa));
    let r4 = bt4(xrow4c(base, plane, iy0 + 4, tx, pre, pa));
    let r5 = bt4(xrow4c(base, plane, iy0 + 5, tx, pre, pa));
    put_v4(array<array<vec4<f32>, 6>, 6>(r0, r1, r2, r3, r4, r5), p.nt * cq, tl * cq + c0 / 4u);
}

// The second half of B^T d B for 4 channels: rows r (B^T applied along x, as vec4s over the channels) -> along
// y, stored to v4: (36, nt, C / 4) at slab-tile column o0 (st = nt C / 4).
fn put_v4(r: array<array<vec4<f32>, 6>, 6>, st: u32, o0: u32) {
    for (var j = 0u; j < 6u; j++) {
        let col = bt4(array<vec4<f32>, 6>(r[0][j], r[1][j], r[2][j], r[3][j], r[4][j], r[5][j]));
        for (var i2 = 0u; i2 < 6u; i2++) {
            v4[(i2 * 6u + j) * st + o0] = col[i2];
        }
    }
}

// `output` for 4 output channels o0 .. o0 + 3 per invocation; each output row of a tile is one vec4 store.
@compute @workgroup_size(256)
fn output4(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>, @builtin(local_invocation_id) lid: vec3<u32>) {
    let i = flat_index(wid, nwg, lid);
    let oq = p.o / 4u;
    if (i >= p.nt * oq) { return; }
    let o0 = 4u * (i % oq);
    let tl = i / oq;
    let tc = tile(tl);
    let n = tc.x;
    let ty = tc.y;
    let tx = tc.z;
    let st = p.nt * oq;
    let mo = tl * oq + o0 / 4u;
    // columns j of A^T M over the 4 channels
    var cols: array<array<vec4<f32>, 4>, 6>;
    for (var j = 0u; j < 6u; j++) {
        cols[j] = at4(array<vec4<f32>, 6>(ldm((0u + j) * st + mo), ldm((6u + j) * st + mo), ldm((12u + j) * st + mo),
                                          ldm((18u + j) * st + mo), ldm((24u + j) * st + mo), ldm((30u + j) * st + mo)));
    }
    var b = vec4<f32>(0.0);
    if (p.has_bias != 0u) {
        let bo = select(o0, n * p.o + o0, p.has_bias == 2u);
        b = vec4<f32>(f32(bias[bo]), f32(bias[bo + 1u]), f32(bias[bo + 2u]), f32(bias[bo + 3u]));
    }
    let plane = p.oh * p.ow;
    for (var r = 0u; r < 4u; r++) {
        // row r of the tile for the 4 channels: at4 over the 6 columns gives its 4 pixels
        let px = at4(array<vec4<f32>, 6>(cols[0][r], cols[1][r], cols[2][r], cols[3][r], cols[4][r], cols[5][r])) ;
        let yy = 4u * ty + r;
        if (yy < p.oh) {
            let e = (yy * p.ow + 4u * tx) / 4u;
            let pb = (n * p.o + o0) * plane / 4u;
            let ps = plane / 4u;
            var v0 = vec4<f32>(px[0].x, px[1].x, px[2].x, px[3].x) + b.x;
            var v1 = vec4<f32>(px[0].y, px[1].y, px[2].y, px[3].y) + b.y;
            var v2 = vec4<f32>(px[0].z, px[1].z, px[2].z, px[3].z) + b.z;
            var v3 = vec4<f32>(px[0].w, px[1].w, px[2].w, px[3].w) + b.w;
            if (p.has_res == 1u) {
                v0 += ldr4(pb + e);
                v1 += ldr4(pb + ps + e);
                v2 += ldr4(pb + 2u * ps + e);
                v3 += ldr4(pb + 3u * ps + e);
            }
            if (p.silu == 1u) {
                v0 = v0 / (1.0 + exp(-v0));
                v1 = v1 / (1.0 + exp(-v1));
                v2 = v2 / (1.0 + exp(-v2));
                v3 = v3 / (1.0 + exp(-v3));
            }
            y4[pb + e] = vec4<ST>(out4(v0));
            y4[pb + ps + e] = vec4<ST>(out4(v1));
            y4[pb + 2u * ps + e] = vec4<ST>(out4(v2));
            y4[pb + 3u * ps + e] = vec4<ST>(out4(v3));
        }
    }
}

fn out4(v: vec4<f32>) -> vec4<f32> {
    if (IS_F16) { return clamp(v, vec4<f32>(-F16_MAX), vec4<f32>(F16_MAX)); }
    return v;
}

// `input` for 4 channels c0 .. c0 + 3 per invocation with scalar loads (any W and padding; C % 4 == 0): the 36
// transformed values of the 4 channels go out as 36 vec4 stores instead of 144 scalar ones. `input4s_gs` with
// the prologue.
@compute @workgroup_size(256)
fn input4s(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>, @builtin(local_invocation_id) lid: vec3<u32>) {
    input4s_impl(flat_index(wid, nwg, lid), false);
}

@compute @workgroup_size(256)
fn input4s_gs(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>, @builtin(local_invocation_id) lid: vec3<u32>) {
    input4s_impl(flat_index(wid, nwg, lid), true);
}

fn input4s_impl(i: u32, pre: bool) {
    let cq = p.c / 4u;
    if (i >= p.nt * cq) { return; }
    let c0 = 4u * (i % cq);
    let tl = i / cq;
    let tc = tile(tl);
    let plane = (p.h >> p.up) * (p.w >> p.up);
    let base = (tc.x * p.c + c0) * plane;
    let iy0 = i32(4u * tc.y) - i32(p.pt);
    let ix0 = i32(4u * tc.z) - i32(p.pl);
    let pa = pre4(pre, tc.x, c0);
    var rows: array<array<vec4<f32>, 6>, 6>;
    for (var r = 0u; r < 6u; r++) {
        let q0 = bt(xrow(base, iy0 + i32(r), ix0, pre, pa[0]));
        let q1 = bt(xrow(base + plane, iy0 + i32(r), ix0, pre, pa[1]));
        let q2 = bt(xrow(base + 2u * plane, iy0 + i32(r), ix0, pre, pa[2]));
        let q3 = bt(xrow(base + 3u * plane, iy0 + i32(r), ix0, pre, pa[3]));
        for (var j = 0u; j < 6u; j++) {
            rows[r][j] = vec4<f32>(q0[j], q1[j], q2[j], q3[j]);
        }
    }
    put_v4(rows, p.nt * cq, tl * cq + c0 / 4u);
}

// ---- F(6x6, 3x3): 8x8 input windows, 64 products, 6x6 output tiles (points 0, +-1, +-2, +-1/2, inf; the
// matrices of Lavin & Gray / wincnn). Per output it moves ~21 % fewer transformed values and multiply-adds than
// F(4x4) (64 / 36 against 36 / 16), at larger transform constants (f32 intermediates keep the error near 1e-6
// relative). Same parameters, bindings and prologue / upsampling reads as F(4x4); tiles are 6x6 (p.th, p.tw
// count them).
//   B^T = [1 0 -21/4 0 21/4 0 -1 0; 0 1 1 -17/4 -17/4 1 1 0; 0 -1 1 17/4 -17/4 -1 1 0;
//          0 1/2 1/4 -5/2 -5/4 2 1 0; 0 -1/2 1/4 5/2 -5/4 -2 1 0; 0 2 4 -5/2 -5 1/2 1 0;
//          0 -2 4 5/2 -5 -1/2 1 0; 0 -1 0 21/4 0 -21/4 0 1]
//   G = [1 0 0; -2/9 -2/9 -2/9; -2/9 2/9 -2/9; 1/90 1/45 2/45; 1/90 -1/45 2/45; 32/45 16/45 8/45;
//        32/45 -16/45 8/45; 0 0 1]
//   A^T = [1 1 1 1 1 1 1 0; 0 1 -1 2 -2 1/2 -1/2 0; 0 1 1 4 4 1/4 1/4 0; 0 1 -1 8 -8 1/8 -1/8 0;
//          0 1 1 16 16 1/16 1/16 0; 0 1 -1 32 -32 1/32 -1/32 1]

// B^T d for 8 values (pairs sharing their even and odd parts).
fn bt8(d: array<f32, 8>) -> array<f32, 8> {
    let a1 = d[2] - 4.25 * d[4] + d[6];
    let b1 = d[1] - 4.25 * d[3] + d[5];
    let a3 = 0.25 * d[2] - 1.25 * d[4] + d[6];
    let b3 = 0.5 * d[1] - 2.5 * d[3] + 2.0 * d[5];
    let a5 = 4.0 * d[2] - 5.0 * d[4] + d[6];
    let b5 = 2.0 * d[1] - 2.5 * d[3] + 0.5 * d[5];
    return array<f32, 8>(d[0] - d[6] + 5.25 * (d[4] - d[2]), a1 + b1, a1 - b1, a3 + b3, a3 - b3, a5 + b5, a5 - b5,
                         d[7] - d[1] + 5.25 * (d[3] - d[5]));
}

fn bt8v(d: array<vec4<f32>, 8>) -> array<vec4<f32>, 8> {
    let a1 = d[2] - 4.25 * d[4] + d[6];
    let b1 = d[1] - 4.25 * d[3] + d[5];
    let a3 = 0.25 * d[2] - 1.25 * d[4] + d[6];
    let b3 = 0.5 * d[1] - 2.5 * d[3] + 2.0 * d[5];
    let a5 = 4.0 * d[2] - 5.0 * d[4] + d[6];
    let b5 = 2.0 * d[1] - 2.5 * d[3] + 0.5 * d[5];
    return array<vec4<f32>, 8>(d[0] - d[6] + 5.25 * (d[4] - d[2]), a1 + b1, a1 - b1, a3 + b3, a3 - b3, a5 + b5,
                               a5 - b5, d[7] - d[1] + 5.25 * (d[3] - d[5]));
}

// A^T s for 8 vec4s -> 6.
fn at8v(s: array<vec4<f32>, 8>) -> array<vec4<f32>, 6> {
    let e1 = s[1] + s[2];
    let o1 = s[1] - s[2];
    let e2 = s[3] + s[4];
    let o2 = s[3] - s[4];
    let e3 = s[5] + s[6];
    let o3 = s[5] - s[6];
    return array<vec4<f32>, 6>(s[0] + e1 + e2 + e3, o1 + 2.0 * o2 + 0.5 * o3, e1 + 4.0 * e2 + 0.25 * e3,
                               o1 + 8.0 * o2 + 0.125 * o3, e1 + 16.0 * e2 + 0.0625 * e3,
                               o1 + 32.0 * o2 + 0.03125 * o3 + s[7]);
}

// G g for one 3-vector -> 8.
fn gg8(g: vec3<f32>) -> array<f32, 8> {
    let e = g.x + g.z;
    let q = g.x / 90.0 + g.z * (2.0 / 45.0);
    let r = g.x * (32.0 / 45.0) + g.z * (8.0 / 45.0);
    return array<f32, 8>(g.x, -(2.0 / 9.0) * (e + g.y), -(2.0 / 9.0) * (e - g.y), q + g.y / 45.0, q - g.y / 45.0,
                         r + g.y * (16.0 / 45.0), r - g.y * (16.0 / 45.0), g.z);
}

// Window row iy of 8 values from column ix0 (through the prologue and the upsampling, 0 outside).
fn xrow8(base: u32, iy: i32, ix0: i32, pre: bool, a: vec4<f32>) -> array<f32, 8> {
    return array<f32, 8>(xin(base, iy, ix0, pre, a), xin(base, iy, ix0 + 1, pre, a), xin(base, iy, ix0 + 2, pre, a),
                         xin(base, iy, ix0 + 3, pre, a), xin(base, iy, ix0 + 4, pre, a), xin(base, iy, ix0 + 5, pre, a),
                         xin(base, iy, ix0 + 6, pre, a), xin(base, iy, ix0 + 7, pre, a));
}

// The second half of B^T d B: rows r (B^T applied along x) -> along y, stored to v4: (64, nt, C / 4) at
// column o0 (st = nt C / 4). The scalar entries store through here too, with one channel in .x and a
// one-channel layout (st = nt C; o0 = tl C + c), writing only .x (see `put6_1`).
fn put6_4(r: array<array<vec4<f32>, 8>, 8>, st: u32, o0: u32) {
    for (var j = 0u; j < 8u; j++) {
        let col = bt8v(array<vec4<f32>, 8>(r[0][j], r[1][j], r[2][j], r[3][j], r[4][j], r[5][j], r[6][j], r[7][j]));
        for (var i2 = 0u; i2 < 8u; i2++) {
            v4[(i2 * 8u + j) * st + o0] = col[i2];
        }
    }
}

fn put6_1(r: array<array<f32, 8>, 8>, st: u32, o0: u32) {
    for (var j = 0u; j < 8u; j++) {
        let col = bt8(array<f32, 8>(r[0][j], r[1][j], r[2][j], r[3][j], r[4][j], r[5][j], r[6][j], r[7][j]));
        for (var i2 = 0u; i2 < 8u; i2++) {
            v[(i2 * 8u + j) * st + o0] = col[i2];
        }
    }
}

// x: (N, C, H, W) -> v: (64, nt, C); invocation = (slab tile, channel), channel fastest. `input6_gs`: through
// the GroupNorm + SiLU prologue.
@compute @workgroup_size(256)
fn input6(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>, @builtin(local_invocation_id) lid: vec3<u32>) {
    input6_impl(flat_index(wid, nwg, lid), false);
}

@compute @workgroup_size(256)
fn input6_gs(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>, @builtin(local_invocation_id) lid: vec3<u32>) {
    input6_impl(flat_index(wid, nwg, lid), true);
}

fn input6_impl(i: u32, pre: bool) {
    if (i >= p.nt * p.c) { return; }
    let c = i % p.c;
    let tl = i / p.c;
    let tc = tile(tl);
    let base = (tc.x * p.c + c) * (p.h >> p.up) * (p.w >> p.up);
    let iy0 = i32(6u * tc.y) - i32(p.pt);
    let ix0 = i32(6u * tc.z) - i32(p.pl);
    let a = pre_of(pre, tc.x, c);
    var rows: array<array<f32, 8>, 8>;
    for (var r = 0u; r < 8u; r++) {
        rows[r] = bt8(xrow8(base, iy0 + i32(r), ix0, pre, a));
    }
    put6_1(rows, p.nt * p.c, tl * p.c + c);
}

// `input6` for 4 channels c0 .. c0 + 3 per invocation (C % 4 == 0; channel quad fastest): 64 vec4 stores
// instead of 256 scalar ones. `input6s_gs` with the prologue.
@compute @workgroup_size(256)
fn input6s(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>, @builtin(local_invocation_id) lid: vec3<u32>) {
    input6s_impl(flat_index(wid, nwg, lid), false);
}

@compute @workgroup_size(256)
fn input6s_gs(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>, @builtin(local_invocation_id) lid: vec3<u32>) {
    input6s_impl(flat_index(wid, nwg, lid), true);
}

fn input6s_impl(i: u32, pre: bool) {
    let cq = p.c / 4u;
    if (i >= p.nt * cq) { return; }
    let c0 = 4u * (i % cq);
    let tl = i / cq;
    let tc = tile(tl);
    let plane = (p.h >> p.up) * (p.w >> p.up);
    let base = (tc.x * p.c + c0) * plane;
    let iy0 = i32(6u * tc.y) - i32(p.pt);
    let ix0 = i32(6u * tc.z) - i32(p.pl);
    let pa = pre4(pre, tc.x, c0);
    var rows: array<array<vec4<f32>, 8>, 8>;
    for (var r = 0u; r < 8u; r++) {
        let q0 = bt8(xrow8(base, iy0 + i32(r), ix0, pre, pa[0]));
        let q1 = bt8(xrow8(base + plane, iy0 + i32(r), ix0, pre, pa[1]));
        let q2 = bt8(xrow8(base + 2u * plane, iy0 + i32(r), ix0, pre, pa[2]));
        let q3 = bt8(xrow8(base + 3u * plane, iy0 + i32(r), ix0, pre, pa[3]));
        for (var j = 0u; j < 8u; j++) {
            rows[r][j] = vec4<f32>(q0[j], q1[j], q2[j], q3[j]);
        }
    }
    put6_4(rows, p.nt * cq, tl * cq + c0 / 4u);
}

// Bias + residual + SiLU + store of one output value y[yi] of channel o, image n.
fn put_y(yi: u32, val0: f32, b: f32) {
    var val = val0 + b;
    if (p.has_res == 1u) { val += f32(res[yi]); }
    if (p.silu == 1u) { val = silu(val); }
    y[yi] = out_val(val);
}

// m: (64, nt, O) -> y: (N, O, OH, OW) (+ bias, residual, SiLU); invocation = (slab tile, output channel),
// channel fastest. Values move as vec4s with the channel in .x (the arithmetic is shared with `output6q`).
@compute @workgroup_size(256)
fn output6(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>, @builtin(local_invocation_id) lid: vec3<u32>) {
    let i = flat_index(wid, nwg, lid);
    if (i >= p.nt * p.o) { return; }
    let o = i % p.o;
    let tl = i / p.o;
    let tc = tile(tl);
    let st = p.nt * p.o;
    let o0 = tl * p.o + o;
    var cols: array<array<vec4<f32>, 6>, 8>;
    for (var j = 0u; j < 8u; j++) {
        var s: array<vec4<f32>, 8>;
        for (var i2 = 0u; i2 < 8u; i2++) {
            s[i2] = vec4<f32>(m[(i2 * 8u + j) * st + o0]);
        }
        cols[j] = at8v(s);
    }
    var b = 0.0;
    if (p.has_bias == 1u) { b = f32(bias[o]); }
    if (p.has_bias == 2u) { b = f32(bias[tc.x * p.o + o]); }
    let ybase = (tc.x * p.o + o) * p.oh * p.ow;
    for (var r = 0u; r < 6u; r++) {
        let px = at8v(array<vec4<f32>, 8>(cols[0][r], cols[1][r], cols[2][r], cols[3][r], cols[4][r], cols[5][r],
                                          cols[6][r], cols[7][r]));
        let yy = 6u * tc.y + r;
        if (yy < p.oh) {
            for (var s = 0u; s < 6u; s++) {
                let xx = 6u * tc.z + s;
                if (xx < p.ow) { put_y(ybase + yy * p.ow + xx, px[s].x, b); }
            }
        }
    }
}

// `output6` for 4 output channels o0 .. o0 + 3 per invocation (O % 4 == 0): m read as vec4s.
@compute @workgroup_size(256)
fn output6q(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>, @builtin(local_invocation_id) lid: vec3<u32>) {
    let i = flat_index(wid, nwg, lid);
    let oq = p.o / 4u;
    if (i >= p.nt * oq) { return; }
    let o0 = 4u * (i % oq);
    let tl = i / oq;
    let tc = tile(tl);
    let cols = m_cols(tl, oq, o0, p.nt * oq);
    var b = vec4<f32>(0.0);
    if (p.has_bias != 0u) {
        let bo = select(o0, tc.x * p.o + o0, p.has_bias == 2u);
        b = vec4<f32>(f32(bias[bo]), f32(bias[bo + 1u]), f32(bias[bo + 2u]), f32(bias[bo + 3u]));
    }
    let plane = p.oh * p.ow;
    let ybase = (tc.x * p.o + o0) * plane;
    for (var r = 0u; r < 6u; r++) {
        let px = at8v(array<vec4<f32>, 8>(cols[0][r], cols[1][r], cols[2][r], cols[3][r], cols[4][r], cols[5][r],
                                          cols[6][r], cols[7][r]));
        let yy = 6u * tc.y + r;
        if (yy < p.oh) {
            for (var s = 0u; s < 6u; s++) {
                let xx = 6u * tc.z + s;
                if (xx < p.ow) {
                    let yi = ybase + yy * p.ow + xx;
                    put_y(yi, px[s].x, b.x);
                    put_y(yi + plane, px[s].y, b.y);
                    put_y(yi + 2u * plane, px[s].z, b.z);
                    put_y(yi + 3u * plane, px[s].w, b.w);
                }
            }
        }
    }
}

// w: (O, C, 3, 3) -> u: (64, C, O) = G g G^T per (o, c); flat grid over O C.
@compute @workgroup_size(256)
fn weight6(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>, @builtin(local_invocation_id) lid: vec3<u32>) {
    let i = flat_index(wid, nwg, lid);
    if (i >= p.o * p.c) { return; }
    let o = i / p.c;
    let c = i % p.c;
    let b = i * 9u;
    let k0 = gg8(vec3<f32>(f32(wsrc[b]), f32(wsrc[b + 1u]), f32(wsrc[b + 2u])));
    let k1 = gg8(vec3<f32>(f32(wsrc[b + 3u]), f32(wsrc[b + 4u]), f32(wsrc[b + 5u])));
    let k2 = gg8(vec3<f32>(f32(wsrc[b + 6u]), f32(wsrc[b + 7u]), f32(wsrc[b + 8u])));
    let st = p.c * p.o;
    for (var j = 0u; j < 8u; j++) {
        let col = gg8(vec3<f32>(k0[j], k1[j], k2[j]));
        for (var i2 = 0u; i2 < 8u; i2++) {
            u[(i2 * 8u + j) * st + c * p.o + o] = col[i2];
        }
    }
}

// ---- F(6x6) on horizontal tile pairs (p.tw even, slabs of whole pairs): one invocation transforms tiles
// (ty, 2q) and (ty, 2q + 1) for 4 channels. Their 8-wide windows overlap in 2 columns, so a window row pair is
// 14 values: 3 aligned vec4 loads and 2 scalars (5 per-lane access loops on lavapipe instead of 16 scalar
// ones); outputs leave as aligned vec4 rows of 12 pixels. `input6p` needs C % 4 == 0, W % 4 == 0, left
// padding 1 and no upsampling; `output6p` O % 4 == 0 and OW % 4 == 0.

// Row iy, columns x0 - 1 .. x0 + 12 (x0 % 4 == 0) of one channel plane at `base` (through the prologue), 0
// outside the image.
fn xrow14(base: u32, iy: i32, x0: u32, pre: bool, pa: vec4<f32>) -> array<f32, 14> {
    let ok = iy >= 0 && iy < i32(p.h);
    let rb = base + u32(clamp(iy, 0, i32(p.h) - 1)) * p.w;
    let q0 = select(vec4<f32>(0.0), act4(ldx4((rb + x0) / 4u), pre, pa), ok);
    let q1 = select(vec4<f32>(0.0), act4(ldx4((rb + min(x0 + 4u, p.w - 4u)) / 4u), pre, pa), ok && x0 + 4u < p.w);
    let q2 = select(vec4<f32>(0.0), act4(ldx4((rb + min(x0 + 8u, p.w - 4u)) / 4u), pre, pa), ok && x0 + 8u < p.w);
    let l = select(0.0, act(f32(xs[rb + max(x0, 1u) - 1u]), pre, pa), ok && x0 >= 1u);
    let r = select(0.0, act(f32(xs[rb + min(x0 + 12u, p.w - 1u)]), pre, pa), ok && x0 + 12u < p.w);
    return array<f32, 14>(l, q0.x, q0.y, q0.z, q0.w, q1.x, q1.y, q1.z, q1.w, q2.x, q2.y, q2.z, q2.w, r);
}

// B^T along x of the window starting at s (0: the pair's first tile, 6: its second) of a 14-value row.
fn bt8_at(q: array<f32, 14>, s: u32) -> array<f32, 8> {
    return bt8(array<f32, 8>(q[s], q[s + 1u], q[s + 2u], q[s + 3u], q[s + 4u], q[s + 5u], q[s + 6u], q[s + 7u]));
}

@compute @workgroup_size(256)
fn input6p(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>, @builtin(local_invocation_id) lid: vec3<u32>) {
    input6p_impl(flat_index(wid, nwg, lid), false);
}

@compute @workgroup_size(256)
fn input6p_gs(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>, @builtin(local_invocation_id) lid: vec3<u32>) {
    input6p_impl(flat_index(wid, nwg, lid), true);
}

fn input6p_impl(i: u32, pre: bool) {
    let cq = p.c / 4u;
    if (i >= (p.nt / 2u) * cq) { return; }
    let c0 = 4u * (i % cq);
    let tl = 2u * (i / cq);
    let tc = tile(tl);
    let plane = p.h * p.w;
    let base = (tc.x * p.c + c0) * plane;
    let iy0 = i32(6u * tc.y) - i32(p.pt);
    let x0 = 6u * tc.z;
    let pa = pre4(pre, tc.x, c0);
    var ra: array<array<vec4<f32>, 8>, 8>;
    var rb: array<array<vec4<f32>, 8>, 8>;
    for (var r = 0u; r < 8u; r++) {
        let iy = iy0 + i32(r);
        let w0 = xrow14(base, iy, x0, pre, pa[0]);
        let w1 = xrow14(base + plane, iy, x0, pre, pa[1]);
        let w2 = xrow14(base + 2u * plane, iy, x0, pre, pa[2]);
        let w3 = xrow14(base + 3u * plane, iy, x0, pre, pa[3]);
        let a0 = bt8_at(w0, 0u);
        let a1 = bt8_at(w1, 0u);
        let a2 = bt8_at(w2, 0u);
        let a3 = bt8_at(w3, 0u);
        let b0 = bt8_at(w0, 6u);
        let b1 = bt8_at(w1, 6u);
        let b2 = bt8_at(w2, 6u);
        let b3 = bt8_at(w3, 6u);
        for (var j = 0u; j < 8u; j++) {
            ra[r][j] = vec4<f32>(a0[j], a1[j], a2[j], a3[j]);
            rb[r][j] = vec4<f32>(b0[j], b1[j], b2[j], b3[j]);
        }
    }
    let st = p.nt * cq;
    put6_4(ra, st, tl * cq + c0 / 4u);
    put6_4(rb, st, (tl + 1u) * cq + c0 / 4u);
}

// A^T M along the 8 rows of each column j of slab tile tl, for output channels o0 .. o0 + 3 (st = nt O / 4).
fn m_cols(tl: u32, oq: u32, o0: u32, st: u32) -> array<array<vec4<f32>, 6>, 8> {
    let mo = tl * oq + o0 / 4u;
    var cols: array<array<vec4<f32>, 6>, 8>;
    for (var j = 0u; j < 8u; j++) {
        var s: array<vec4<f32>, 8>;
        for (var i2 = 0u; i2 < 8u; i2++) {
            s[i2] = ldm((i2 * 8u + j) * st + mo);
        }
        cols[j] = at8v(s);
    }
    return cols;
}

@compute @workgroup_size(256)
fn output6p(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>, @builtin(local_invocation_id) lid: vec3<u32>) {
    let i = flat_index(wid, nwg, lid);
    let oq = p.o / 4u;
    if (i >= (p.nt / 2u) * oq) { return; }
    let o0 = 4u * (i % oq);
    let tl = 2u * (i / oq);
    let tc = tile(tl);
    let st = p.nt * oq;
    let ca = m_cols(tl, oq, o0, st);
    let cb = m_cols(tl + 1u, oq, o0, st);
    var b = vec4<f32>(0.0);
    if (p.has_bias != 0u) {
        let bo = select(o0, tc.x * p.o + o0, p.has_bias == 2u);
        b = vec4<f32>(f32(bias[bo]), f32(bias[bo + 1u]), f32(bias[bo + 2u]), f32(bias[bo + 3u]));
    }
    let ps = p.oh * p.ow / 4u;
    let pb = (tc.x * p.o + o0) * ps;
    let x0 = 6u * tc.z;
    sh = vec4<f32>(0.0);
    ss1 = array<vec4<f32>, 4>(vec4<f32>(0.0), vec4<f32>(0.0), vec4<f32>(0.0), vec4<f32>(0.0));
    ss2 = ss1;
    cnt = 0.0;
    for (var r = 0u; r < 6u; r++) {
        let pa = at8v(array<vec4<f32>, 8>(ca[0][r], ca[1][r], ca[2][r], ca[3][r], ca[4][r], ca[5][r], ca[6][r], ca[7][r]));
        let pc = at8v(array<vec4<f32>, 8>(cb[0][r], cb[1][r], cb[2][r], cb[3][r], cb[4][r], cb[5][r], cb[6][r], cb[7][r]));
        // the row's 12 pixels, each a vec4 over the 4 channels
        let px = array<vec4<f32>, 12>(pa[0], pa[1], pa[2], pa[3], pa[4], pa[5], pc[0], pc[1], pc[2], pc[3], pc[4], pc[5]);
        let yy = 6u * tc.y + r;
        if (yy < p.oh) {
            for (var q = 0u; q < 3u; q++) {
                if (x0 + 4u * q < p.ow) {
                    let e = pb + (yy * p.ow + x0) / 4u + q;
                    let p0 = px[4u * q];
                    let p1 = px[4u * q + 1u];
                    let p2 = px[4u * q + 2u];
                    let p3 = px[4u * q + 3u];
                    var v0 = vec4<f32>(p0.x, p1.x, p2.x, p3.x) + b.x;
                    var v1 = vec4<f32>(p0.y, p1.y, p2.y, p3.y) + b.y;
                    var v2 = vec4<f32>(p0.z, p1.z, p2.z, p3.z) + b.z;
                    var v3 = vec4<f32>(p0.w, p1.w, p2.w, p3.w) + b.w;
                    if (p.has_res == 1u) {
                        v0 += ldr4(e);
                        v1 += ldr4(e + ps);
                        v2 += ldr4(e + 2u * ps);
                        v3 += ldr4(e + 3u * ps);
                    }
                    if (p.silu == 1u) {
                        v0 = v0 / (1.0 + exp(-v0));
                        v1 = v1 / (1.0 + exp(-v1));
                        v2 = v2 / (1.0 + exp(-v2));
                        v3 = v3 / (1.0 + exp(-v3));
                    }
                    let s0 = vec4<ST>(out4(v0));
                    let s1 = vec4<ST>(out4(v1));
                    let s2 = vec4<ST>(out4(v2));
                    let s3 = vec4<ST>(out4(v3));
                    y4[e] = s0;
                    y4[e + ps] = s1;
                    y4[e + 2u * ps] = s2;
                    y4[e + 3u * ps] = s3;
                    if (p.stats == 1u) {
                        // the values as stored, shifted by each channel's first value
                        let f0 = vec4<f32>(s0);
                        let f1 = vec4<f32>(s1);
                        let f2 = vec4<f32>(s2);
                        let f3 = vec4<f32>(s3);
                        if (r == 0u && q == 0u) { sh = vec4<f32>(f0.x, f1.x, f2.x, f3.x); }
                        let d0 = f0 - sh.x;
                        let d1 = f1 - sh.y;
                        let d2 = f2 - sh.z;
                        let d3 = f3 - sh.w;
                        ss1[0] += d0;
                        ss1[1] += d1;
                        ss1[2] += d2;
                        ss1[3] += d3;
                        ss2[0] = fma(d0, d0, ss2[0]);
                        ss2[1] = fma(d1, d1, ss2[1]);
                        ss2[2] = fma(d2, d2, ss2[2]);
                        ss2[3] = fma(d3, d3, ss2[3]);
                        cnt += 4.0;
                    }
                }
            }
        }
    }
    if (p.stats == 1u) {
        // slot = global tile pair (t0 and tl are even)
        let slot = (p.t0 + tl) / 2u;
        for (var k = 0u; k < 4u; k++) {
            let a = dot(ss1[k], vec4<f32>(1.0));
            let m2 = max(dot(ss2[k], vec4<f32>(1.0)) - a * a / cnt, 0.0);
            part[slot * p.o + o0 + k] = vec4<f32>(cnt, sh[k] + a / cnt, m2, 0.0);
        }
    }
}

// ---- Group-norm statistics in `output6p`'s epilogue (p.stats): per tile pair and output channel, the count,
// mean and M2 (sum of squared deviations) of the values it stored, to `part` (slots, O) of (count, mean, M2,
// -), slots numbered over the global tile pairs (n, ty, pair). `norm::group_norm_stats_parts` merges them into
// a group norm's statistics without reading the output again. The sums run on the values shifted by the
// channel's first value in the pair (a value of the data: no cancellation however large the mean, as long as
// the pair's own spread is representable); the merge across pairs uses Chan et al.'s update.
@group(0) @binding(4) var<storage, read_write> part: array<vec4<f32>>;
// per channel of the invocation: the shift, and the per-pixel-lane sums of the shifted values and their squares
var<private> sh: vec4<f32>;
var<private> ss1: array<vec4<f32>, 4>;
var<private> ss2: array<vec4<f32>, 4>;
var<private> cnt: f32;

// ---- F(4x4) output for 4 output channels per invocation with per-pixel stores (O % 4 == 0, any OW: the vec4
// rows of `output4` need OW % 4 == 0): m read as 36 vec4s instead of 144 scalars.
@compute @workgroup_size(256)
fn output4q(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>, @builtin(local_invocation_id) lid: vec3<u32>) {
    let i = flat_index(wid, nwg, lid);
    let oq = p.o / 4u;
    if (i >= p.nt * oq) { return; }
    let o0 = 4u * (i % oq);
    let tl = i / oq;
    let tc = tile(tl);
    let st = p.nt * oq;
    let mo = tl * oq + o0 / 4u;
    // columns j of A^T M over the 4 channels
    var cols: array<array<vec4<f32>, 4>, 6>;
    for (var j = 0u; j < 6u; j++) {
        cols[j] = at4(array<vec4<f32>, 6>(ldm((0u + j) * st + mo), ldm((6u + j) * st + mo), ldm((12u + j) * st + mo),
                                          ldm((18u + j) * st + mo), ldm((24u + j) * st + mo), ldm((30u + j) * st + mo)));
    }
    var b = vec4<f32>(0.0);
    if (p.has_bias != 0u) {
        let bo = select(o0, tc.x * p.o + o0, p.has_bias == 2u);
        b = vec4<f32>(f32(bias[bo]), f32(bias[bo + 1u]), f32(bias[bo + 2u]), f32(bias[bo + 3u]));
    }
    let plane = p.oh * p.ow;
    let ybase = (tc.x * p.o + o0) * plane;
    for (var r = 0u; r < 4u; r++) {
        // row r of the tile: its 4 pixels, each a vec4 over the channels
        let px = at4(array<vec4<f32>, 6>(cols[0][r], cols[1][r], cols[2][r], cols[3][r], cols[4][r], cols[5][r]));
        let yy = 4u * tc.y + r;
        if (yy < p.oh) {
            for (var s = 0u; s < 4u; s++) {
                let xx = 4u * tc.z + s;
                if (xx < p.ow) {
                    let yi = ybase + yy * p.ow + xx;
                    put_y(yi, px[s].x, b.x);
                    put_y(yi + plane, px[s].y, b.y);
                    put_y(yi + 2u * plane, px[s].z, b.z);
                    put_y(yi + 3u * plane, px[s].w, b.w);
                }
            }
        }
    }
}
