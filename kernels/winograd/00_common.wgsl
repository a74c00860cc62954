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
// This kernel is the folder kernels/winograd/, its files concatenated in name order (build.rs): 00_common
// (parameters, bindings, the GroupNorm + SiLU prologue reads every form shares), 10_f4 (F(4x4)), 20_f6
// (F(6x6)), 30_f6_pairs (F(6x6) on tile pairs, with the group-norm statistics epilogue).

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
