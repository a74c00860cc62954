//! variant f32_d8 [main]: alias ST = f32; const D4: u32 = 2u; const R: u32 = 1u; alias KT = vec4<ST>; const CPL: u32 = 1u; fn unpack(x: KT, part: u32) -> vec4<f32> { return vec4<f32>(x); } fn ldk(i: u32) -> KT { return k[i]; } fn ldv(i: u32) -> KT { return v[i]; }
//! variant f32_d8r4 [main]: alias ST = f32; const D4: u32 = 2u; const R: u32 = 4u; alias KT = vec4<ST>; const CPL: u32 = 1u; fn unpack(x: KT, part: u32) -> vec4<f32> { return vec4<f32>(x); } fn ldk(i: u32) -> KT { return k[i]; } fn ldv(i: u32) -> KT { return v[i]; }
//! variant f32_d40 [main]: alias ST = f32; const D4: u32 = 10u; const R: u32 = 1u; alias KT = vec4<ST>; const CPL: u32 = 1u; fn unpack(x: KT, part: u32) -> vec4<f32> { return vec4<f32>(x); } fn ldk(i: u32) -> KT { return k[i]; } fn ldv(i: u32) -> KT { return v[i]; }
//! variant f32_d40r2 [main]: alias ST = f32; const D4: u32 = 10u; const R: u32 = 2u; alias KT = vec4<ST>; const CPL: u32 = 1u; fn unpack(x: KT, part: u32) -> vec4<f32> { return vec4<f32>(x); } fn ldk(i: u32) -> KT { return k[i]; } fn ldv(i: u32) -> KT { return v[i]; }
//! variant f32_d40r4 [main]: alias ST = f32; const D4: u32 = 10u; const R: u32 = 4u; alias KT = vec4<ST>; const CPL: u32 = 1u; fn unpack(x: KT, part: u32) -> vec4<f32> { return vec4<f32>(x); } fn ldk(i: u32) -> KT { return k[i]; } fn ldv(i: u32) -> KT { return v[i]; }
//! variant f32_d80 [main]: alias ST = f32; const D4: u32 = 20u; const R: u32 = 1u; alias KT = vec4<ST>; const CPL: u32 = 1u; fn unpack(x: KT, part: u32) -> vec4<f32> { return vec4<f32>(x); } fn ldk(i: u32) -> KT { return k[i]; } fn ldv(i: u32) -> KT { return v[i]; }
//! variant f32_d80r2 [main]: alias ST = f32; const D4: u32 = 20u; const R: u32 = 2u; alias KT = vec4<ST>; const CPL: u32 = 1u; fn unpack(x: KT, part: u32) -> vec4<f32> { return vec4<f32>(x); } fn ldk(i: u32) -> KT { return k[i]; } fn ldv(i: u32) -> KT { return v[i]; }
//! variant f32_d160 [main]: alias ST = f32; const D4: u32 = 40u; const R: u32 = 1u; alias KT = vec4<ST>; const CPL: u32 = 1u; fn unpack(x: KT, part: u32) -> vec4<f32> { return vec4<f32>(x); } fn ldk(i: u32) -> KT { return k[i]; } fn ldv(i: u32) -> KT { return v[i]; }
//! variant f32_w128 [wide]: alias ST = f32; const D4: u32 = 32u; const R: u32 = 1u; alias KT = vec4<ST>; const CPL: u32 = 1u; fn unpack(x: KT, part: u32) -> vec4<f32> { return vec4<f32>(x); } fn ldk(i: u32) -> KT { return k[i]; } fn ldv(i: u32) -> KT { return v[i]; }
//! variant f16_d8 [main]: enable f16; alias ST = f16; const D4: u32 = 2u; const R: u32 = 1u; alias KT = vec4<ST>; const CPL: u32 = 1u; fn unpack(x: KT, part: u32) -> vec4<f32> { return vec4<f32>(x); } fn ldk(i: u32) -> KT { return k[i]; } fn ldv(i: u32) -> KT { return v[i]; }
//! variant f16_d8r4 [main]: enable f16; alias ST = f16; const D4: u32 = 2u; const R: u32 = 4u; alias KT = vec4<ST>; const CPL: u32 = 1u; fn unpack(x: KT, part: u32) -> vec4<f32> { return vec4<f32>(x); } fn ldk(i: u32) -> KT { return k[i]; } fn ldv(i: u32) -> KT { return v[i]; }
//! variant f16_d40 [main]: enable f16; alias ST = f16; const D4: u32 = 10u; const R: u32 = 1u; alias KT = vec4<ST>; const CPL: u32 = 1u; fn unpack(x: KT, part: u32) -> vec4<f32> { return vec4<f32>(x); } fn ldk(i: u32) -> KT { return k[i]; } fn ldv(i: u32) -> KT { return v[i]; }
//! variant f16_d40r2 [main]: enable f16; alias ST = f16; const D4: u32 = 10u; const R: u32 = 2u; alias KT = vec4<ST>; const CPL: u32 = 1u; fn unpack(x: KT, part: u32) -> vec4<f32> { return vec4<f32>(x); } fn ldk(i: u32) -> KT { return k[i]; } fn ldv(i: u32) -> KT { return v[i]; }
//! variant f16_d40r4 [main]: enable f16; alias ST = f16; const D4: u32 = 10u; const R: u32 = 4u; alias KT = vec4<ST>; const CPL: u32 = 1u; fn unpack(x: KT, part: u32) -> vec4<f32> { return vec4<f32>(x); } fn ldk(i: u32) -> KT { return k[i]; } fn ldv(i: u32) -> KT { return v[i]; }
//! variant f16_d80 [main]: enable f16; alias ST = f16; const D4: u32 = 20u; const R: u32 = 1u; alias KT = vec4<ST>; const CPL: u32 = 1u; fn unpack(x: KT, part: u32) -> vec4<f32> { return vec4<f32>(x); } fn ldk(i: u32) -> KT { return k[i]; } fn ldv(i: u32) -> KT { return v[i]; }
//! variant f16_d80r2 [main]: enable f16; alias ST = f16; const D4: u32 = 20u; const R: u32 = 2u; alias KT = vec4<ST>; const CPL: u32 = 1u; fn unpack(x: KT, part: u32) -> vec4<f32> { return vec4<f32>(x); } fn ldk(i: u32) -> KT { return k[i]; } fn ldv(i: u32) -> KT { return v[i]; }
//! variant f16_d160 [main]: enable f16; alias ST = f16; const D4: u32 = 40u; const R: u32 = 1u; alias KT = vec4<ST>; const CPL: u32 = 1u; fn unpack(x: KT, part: u32) -> vec4<f32> { return vec4<f32>(x); } fn ldk(i: u32) -> KT { return k[i]; } fn ldv(i: u32) -> KT { return v[i]; }
//! variant f16_w128 [wide]: enable f16; alias ST = f16; const D4: u32 = 32u; const R: u32 = 1u; alias KT = vec4<ST>; const CPL: u32 = 1u; fn unpack(x: KT, part: u32) -> vec4<f32> { return vec4<f32>(x); } fn ldk(i: u32) -> KT { return k[i]; } fn ldv(i: u32) -> KT { return v[i]; }
//! variant f16p_d8r4 [main]: enable f16; alias ST = f16; const D4: u32 = 2u; const R: u32 = 4u; alias KT = vec4<u32>; const CPL: u32 = 2u; fn unpack(x: KT, part: u32) -> vec4<f32> { let w = select(x.xy, x.zw, vec2<bool>(part == 1u)); return halves_to_f32(vec4<u32>(w.x & 0xffffu, w.x >> 16u, w.y & 0xffffu, w.y >> 16u)); } fn ldk(i: u32) -> KT { return k[i]; } fn ldv(i: u32) -> KT { return v[i]; }
//! variant f16p_d40r2 [main]: enable f16; alias ST = f16; const D4: u32 = 10u; const R: u32 = 2u; alias KT = vec4<u32>; const CPL: u32 = 2u; fn unpack(x: KT, part: u32) -> vec4<f32> { let w = select(x.xy, x.zw, vec2<bool>(part == 1u)); return halves_to_f32(vec4<u32>(w.x & 0xffffu, w.x >> 16u, w.y & 0xffffu, w.y >> 16u)); } fn ldk(i: u32) -> KT { return k[i]; } fn ldv(i: u32) -> KT { return v[i]; }
//! variant f16p_d40r4 [main]: enable f16; alias ST = f16; const D4: u32 = 10u; const R: u32 = 4u; alias KT = vec4<u32>; const CPL: u32 = 2u; fn unpack(x: KT, part: u32) -> vec4<f32> { let w = select(x.xy, x.zw, vec2<bool>(part == 1u)); return halves_to_f32(vec4<u32>(w.x & 0xffffu, w.x >> 16u, w.y & 0xffffu, w.y >> 16u)); } fn ldk(i: u32) -> KT { return k[i]; } fn ldv(i: u32) -> KT { return v[i]; }
//! variant f16p_d80r2 [main]: enable f16; alias ST = f16; const D4: u32 = 20u; const R: u32 = 2u; alias KT = vec4<u32>; const CPL: u32 = 2u; fn unpack(x: KT, part: u32) -> vec4<f32> { let w = select(x.xy, x.zw, vec2<bool>(part == 1u)); return halves_to_f32(vec4<u32>(w.x & 0xffffu, w.x >> 16u, w.y & 0xffffu, w.y >> 16u)); } fn ldk(i: u32) -> KT { return k[i]; } fn ldv(i: u32) -> KT { return v[i]; }
//! variant f32_d8r8 [main]: alias ST = f32; const D4: u32 = 2u; const R: u32 = 8u; alias KT = vec4<ST>; const CPL: u32 = 1u; fn unpack(x: KT, part: u32) -> vec4<f32> { return vec4<f32>(x); } fn ldk(i: u32) -> KT { return k[i]; } fn ldv(i: u32) -> KT { return v[i]; }
//! variant f32_d16r4 [main]: alias ST = f32; const D4: u32 = 4u; const R: u32 = 4u; alias KT = vec4<ST>; const CPL: u32 = 1u; fn unpack(x: KT, part: u32) -> vec4<f32> { return vec4<f32>(x); } fn ldk(i: u32) -> KT { return k[i]; } fn ldv(i: u32) -> KT { return v[i]; }
//! variant f32_d32r4 [main]: alias ST = f32; const D4: u32 = 8u; const R: u32 = 4u; alias KT = vec4<ST>; const CPL: u32 = 1u; fn unpack(x: KT, part: u32) -> vec4<f32> { return vec4<f32>(x); } fn ldk(i: u32) -> KT { return k[i]; } fn ldv(i: u32) -> KT { return v[i]; }
//! variant f16_d16r4 [main]: enable f16; alias ST = f16; const D4: u32 = 4u; const R: u32 = 4u; alias KT = vec4<ST>; const CPL: u32 = 1u; fn unpack(x: KT, part: u32) -> vec4<f32> { return vec4<f32>(x); } fn ldk(i: u32) -> KT { return k[i]; } fn ldv(i: u32) -> KT { return v[i]; }
//! variant f16_d32r4 [main]: enable f16; alias ST = f16; const D4: u32 = 8u; const R: u32 = 4u; alias KT = vec4<ST>; const CPL: u32 = 1u; fn unpack(x: KT, part: u32) -> vec4<f32> { return vec4<f32>(x); } fn ldk(i: u32) -> KT { return k[i]; } fn ldv(i: u32) -> KT { return v[i]; }
//! variant f16p_d16r4 [main]: enable f16; alias ST = f16; const D4: u32 = 4u; const R: u32 = 4u; alias KT = vec4<u32>; const CPL: u32 = 2u; fn unpack(x: KT, part: u32) -> vec4<f32> { let w = select(x.xy, x.zw, vec2<bool>(part == 1u)); return halves_to_f32(vec4<u32>(w.x & 0xffffu, w.x >> 16u, w.y & 0xffffu, w.y >> 16u)); } fn ldk(i: u32) -> KT { return k[i]; } fn ldv(i: u32) -> KT { return v[i]; }
//! variant f16p_d32r4 [main]: enable f16; alias ST = f16; const D4: u32 = 8u; const R: u32 = 4u; alias KT = vec4<u32>; const CPL: u32 = 2u; fn unpack(x: KT, part: u32) -> vec4<f32> { let w = select(x.xy, x.zw, vec2<bool>(part == 1u)); return halves_to_f32(vec4<u32>(w.x & 0xffffu, w.x >> 16u, w.y & 0xffffu, w.y >> 16u)); } fn ldk(i: u32) -> KT { return k[i]; } fn ldv(i: u32) -> KT { return v[i]; }
//! variant f32t_d8 [main]: alias ST = f32; const D4: u32 = 2u; const R: u32 = 1u; alias KT = vec4<ST>; const CPL: u32 = 1u; fn unpack(x: KT, part: u32) -> vec4<f32> { return vec4<f32>(x); } fn ldk(i: u32) -> KT { return textureLoad(kt, texel_xy(i)); } fn ldv(i: u32) -> KT { return textureLoad(vt, texel_xy(i)); }
//! variant f32t_d8r4 [main]: alias ST = f32; const D4: u32 = 2u; const R: u32 = 4u; alias KT = vec4<ST>; const CPL: u32 = 1u; fn unpack(x: KT, part: u32) -> vec4<f32> { return vec4<f32>(x); } fn ldk(i: u32) -> KT { return textureLoad(kt, texel_xy(i)); } fn ldv(i: u32) -> KT { return textureLoad(vt, texel_xy(i)); }
//! variant f32t_d40 [main]: alias ST = f32; const D4: u32 = 10u; const R: u32 = 1u; alias KT = vec4<ST>; const CPL: u32 = 1u; fn unpack(x: KT, part: u32) -> vec4<f32> { return vec4<f32>(x); } fn ldk(i: u32) -> KT { return textureLoad(kt, texel_xy(i)); } fn ldv(i: u32) -> KT { return textureLoad(vt, texel_xy(i)); }
//! variant f32t_d40r2 [main]: alias ST = f32; const D4: u32 = 10u; const R: u32 = 2u; alias KT = vec4<ST>; const CPL: u32 = 1u; fn unpack(x: KT, part: u32) -> vec4<f32> { return vec4<f32>(x); } fn ldk(i: u32) -> KT { return textureLoad(kt, texel_xy(i)); } fn ldv(i: u32) -> KT { return textureLoad(vt, texel_xy(i)); }
//! variant f32t_d40r4 [main]: alias ST = f32; const D4: u32 = 10u; const R: u32 = 4u; alias KT = vec4<ST>; const CPL: u32 = 1u; fn unpack(x: KT, part: u32) -> vec4<f32> { return vec4<f32>(x); } fn ldk(i: u32) -> KT { return textureLoad(kt, texel_xy(i)); } fn ldv(i: u32) -> KT { return textureLoad(vt, texel_xy(i)); }
//! variant f32t_d80 [main]: alias ST = f32; const D4: u32 = 20u; const R: u32 = 1u; alias KT = vec4<ST>; const CPL: u32 = 1u; fn unpack(x: KT, part: u32) -> vec4<f32> { return vec4<f32>(x); } fn ldk(i: u32) -> KT { return textureLoad(kt, texel_xy(i)); } fn ldv(i: u32) -> KT { return textureLoad(vt, texel_xy(i)); }
//! variant f32t_d80r2 [main]: alias ST = f32; const D4: u32 = 20u; const R: u32 = 2u; alias KT = vec4<ST>; const CPL: u32 = 1u; fn unpack(x: KT, part: u32) -> vec4<f32> { return vec4<f32>(x); } fn ldk(i: u32) -> KT { return textureLoad(kt, texel_xy(i)); } fn ldv(i: u32) -> KT { return textureLoad(vt, texel_xy(i)); }
//! variant f32t_d160 [main]: alias ST = f32; const D4: u32 = 40u; const R: u32 = 1u; alias KT = vec4<ST>; const CPL: u32 = 1u; fn unpack(x: KT, part: u32) -> vec4<f32> { return vec4<f32>(x); } fn ldk(i: u32) -> KT { return textureLoad(kt, texel_xy(i)); } fn ldv(i: u32) -> KT { return textureLoad(vt, texel_xy(i)); }
//! variant f32t_w128 [wide]: alias ST = f32; const D4: u32 = 32u; const R: u32 = 1u; alias KT = vec4<ST>; const CPL: u32 = 1u; fn unpack(x: KT, part: u32) -> vec4<f32> { return vec4<f32>(x); } fn ldk(i: u32) -> KT { return textureLoad(kt, texel_xy(i)); } fn ldv(i: u32) -> KT { return textureLoad(vt, texel_xy(i)); }
//! variant f32t_d8r8 [main]: alias ST = f32; const D4: u32 = 2u; const R: u32 = 8u; alias KT = vec4<ST>; const CPL: u32 = 1u; fn unpack(x: KT, part: u32) -> vec4<f32> { return vec4<f32>(x); } fn ldk(i: u32) -> KT { return textureLoad(kt, texel_xy(i)); } fn ldv(i: u32) -> KT { return textureLoad(vt, texel_xy(i)); }
//! variant f32t_d16r4 [main]: alias ST = f32; const D4: u32 = 4u; const R: u32 = 4u; alias KT = vec4<ST>; const CPL: u32 = 1u; fn unpack(x: KT, part: u32) -> vec4<f32> { return vec4<f32>(x); } fn ldk(i: u32) -> KT { return textureLoad(kt, texel_xy(i)); } fn ldv(i: u32) -> KT { return textureLoad(vt, texel_xy(i)); }
//! variant f32t_d32r4 [main]: alias ST = f32; const D4: u32 = 8u; const R: u32 = 4u; alias KT = vec4<ST>; const CPL: u32 = 1u; fn unpack(x: KT, part: u32) -> vec4<f32> { return vec4<f32>(x); } fn ldk(i: u32) -> KT { return textureLoad(kt, texel_xy(i)); } fn ldv(i: u32) -> KT { return textureLoad(vt, texel_xy(i)); }
// Multi-head attention, flash style (online softmax), storage type ST, all arithmetic in f32.
//
// Layout (token-major, as the UNet's linear projections produce it; heads interleaved in the last dim):
//   q: (B, Lq, H*d), k: (B, Lk, H*d), v: (B, Lk, H*d) -> o: (B, Lq, H*d); head h owns columns [h*d, h*d + d).
// Buffers are read as vec4 (d % 4 == 0; nc = d / 4 chunks per head row, w4 = H * nc chunks per token row).
// Every global load in lavapipe 22.3 is a branchy loop over the 8 lanes, so load instructions, not FLOPs, set the
// speed: the `f16p` variants read k and v as vec4<u32> (two f16 chunks per load, d % 8 == 0) and unpack them.
//
// Mapping for llvmpipe (8-wide SIMD across invocations, lavapipe's subgroup size 8). A work group is 8
// invocations = one subgroup; lane l owns the R query rows qb*8R + 8r + l (r < R) of one (batch, head): their q
// (pre-scaled) and output accumulators live in registers (`array<array<vec4<f32>, D4>, R>` indexed only by
// constants once the loops are unrolled). Keys go by tiles of 8: lane l loads chunk c of key j0 + l (one vec4
// per lane: every lane's load is useful), and subgroupBroadcast with a constant lane index (a register shuffle
// in llvmpipe) hands key j0 + t's chunk to all lanes. So each global load feeds 32 R multiply-adds per lane and
// there are no barriers, no shared memory, no gathers of uniform data. Per tile and row: logits s (8 per lane),
// running max m and sum l, rescale acc by exp(m_old - m_new), acc += p * V. Masked keys get logit -3e38
// (exp -> 0, never inf - inf). Measured on lavapipe (1400 tokens, d 40): R = 1 -> 2 -> 4 gains ~1.5x, R = 8 no
// more (register pressure); loading k/v for only every other chunk (a wrong-result probe) was ~1.9x faster, so
// the remaining time is mostly the per-lane load loops. Small heads (b2dr-tiny: d 8, 16, 32) have their own
// variants instead of running in d 40's registers: at d 8, R = 8 beats R = 4 (1400 tokens x 7 calls in the
// tiny step: 58-59 vs 65 ms); d 16 with R = 4 took 8.4-8.7 ms where d 40's kernel took 19 (R = 8: no better).
//
// On GPUs with wider subgroups (32, 64) the work group of 8 is still one subgroup (lanes 0..7); subgroups
// narrower than 8 are not supported.
//
// Loop budget (lavapipe: 65535 loop back-edges per invocation, then loops silently exit): the key loop runs
// ceil(Lk / 8) times. lavapipe's NIR unrolls constant loops of up to 32 trips, so for D4 <= 32 the chunk and row
// loops disappear; D4 = 40 keeps its chunk loops (R * (ceil(Lk / 8) * (2 D4 + 1) + 2 D4) back-edges), `wide`
// adds its runtime q.k loop (nc / 2 a tile). The launcher refuses shapes over 60000; tests run a shape near the
// bound for each kind (440,000 keys at d 40, 5,000 at d 160) and would see a truncated loop.
//
// `main` needs d <= 4 * D4. `wide` (any d % 8 == 0, used for d > 160, e.g. the VAE's 512, from the w128
// variants: D4 = 32 is the largest chunk loop NIR unrolls) streams q chunks from memory for the logits and splits
// the output columns into slices of 4 * D4 (one slice per work group), recomputing the logits per slice.

// IEEE half bit patterns (low 16 bits) -> f32: normal numbers by rebiasing the exponent, subnormals as m * 2^-24,
// inf/NaN kept (an overflowed input must not turn into a finite output). bitcast<vec2<f16>>(u32) compiled but
// gave wrong values on lavapipe 22.3, and unpack2x16float needs a naga capability build.rs does not enable.
fn halves_to_f32(b: vec4<u32>) -> vec4<f32> {
    let e = (b >> vec4<u32>(10u)) & vec4<u32>(0x1fu);
    let m = b & vec4<u32>(0x3ffu);
    let sgn = (b & vec4<u32>(0x8000u)) << vec4<u32>(16u);
    let normal = bitcast<vec4<f32>>(sgn | ((e + vec4<u32>(112u)) << vec4<u32>(23u)) | (m << vec4<u32>(13u)));
    let sub = bitcast<vec4<f32>>(sgn | vec4<u32>(0x3f800000u)) * vec4<f32>(m) * 5.9604645e-8;
    let special = bitcast<vec4<f32>>(sgn | vec4<u32>(0x7f800000u) | (m << vec4<u32>(13u)));
    return select(select(normal, sub, e == vec4<u32>(0u)), special, e == vec4<u32>(31u));
}

struct AttnParams {
    lq: u32, lk: u32, heads: u32, nc: u32, w4: u32,
    qblocks: u32, slices: u32, groups: u32, scale: f32,
}

@group(0) @binding(0) var<storage, read> q: array<vec4<ST>>;
@group(0) @binding(1) var<storage, read> k: array<KT>;
@group(0) @binding(2) var<storage, read> v: array<KT>;
// the f32t variants read k and v through the buffers' texel views (`ldk`, `ldv`; src/vk/image.rs): one 16-byte
// fetch per lane on lavapipe instead of four bounds-checked scalar loads
@group(0) @binding(1) var kt: texture_storage_2d<rgba32float, read>;
@group(0) @binding(2) var vt: texture_storage_2d<rgba32float, read>;
@group(0) @binding(3) var<storage, read_write> o: array<vec4<ST>>;

var<immediate> a: AttnParams;

const NEG_BIG: f32 = -3.0e38;

// Logits of keys j0 + 0..3 (`lo`) and j0 + 4..7 (`hi`) for one chunk: q chunk . (key j0 + t's chunk, held by lane
// t of `kc`).
fn logits_lo(qc: vec4<f32>, kc: vec4<f32>) -> vec4<f32> {
    return vec4<f32>(dot(qc, subgroupBroadcast(kc, 0u)), dot(qc, subgroupBroadcast(kc, 1u)),
                     dot(qc, subgroupBroadcast(kc, 2u)), dot(qc, subgroupBroadcast(kc, 3u)));
}

fn logits_hi(qc: vec4<f32>, kc: vec4<f32>) -> vec4<f32> {
    return vec4<f32>(dot(qc, subgroupBroadcast(kc, 4u)), dot(qc, subgroupBroadcast(kc, 5u)),
                     dot(qc, subgroupBroadcast(kc, 6u)), dot(qc, subgroupBroadcast(kc, 7u)));
}

// acc chunk * alpha + sum_t p[t] * (value chunk of key j0 + t, held by lane t of `vc`).
fn values_step(acc: vec4<f32>, alpha: f32, p0: vec4<f32>, p1: vec4<f32>, vc: vec4<f32>) -> vec4<f32> {
    var r = acc * alpha;
    r += p0.x * subgroupBroadcast(vc, 0u) + p0.y * subgroupBroadcast(vc, 1u)
       + p0.z * subgroupBroadcast(vc, 2u) + p0.w * subgroupBroadcast(vc, 3u);
    r += p1.x * subgroupBroadcast(vc, 4u) + p1.y * subgroupBroadcast(vc, 5u)
       + p1.z * subgroupBroadcast(vc, 6u) + p1.w * subgroupBroadcast(vc, 7u);
    return r;
}

// Online-softmax state of one query row after a tile: running max m and sum l, the factor alpha that rescales
// the accumulator, and the tile's weights p0 (keys j0 + 0..3), p1 (j0 + 4..7).
struct Online { m: f32, l: f32, alpha: f32, p0: vec4<f32>, p1: vec4<f32> }

// Masks keys >= Lk (logit -3e38: exp gives 0 and max never sees it), then updates (m, l).
fn online_step(j0: u32, s0in: vec4<f32>, s1in: vec4<f32>, m: f32, l: f32) -> Online {
    let nval = vec4<u32>(a.lk - j0);
    let s0 = select(vec4<f32>(NEG_BIG), s0in, vec4<u32>(0u, 1u, 2u, 3u) < nval);
    let s1 = select(vec4<f32>(NEG_BIG), s1in, vec4<u32>(4u, 5u, 6u, 7u) < nval);
    let t = max(s0, s1);
    let mn = max(m, max(max(t.x, t.y), max(t.z, t.w)));
    // logits are in log2 units (the launcher folds log2(e) into the scale), so exp2 gives the softmax weights
    // without exp's extra multiply
    let alpha = exp2(m - mn);
    let p0 = exp2(s0 - mn);
    let p1 = exp2(s1 - mn);
    return Online(mn, l * alpha + dot(p0 + p1, vec4<f32>(1.0)), alpha, p0, p1);
}

// q: (B, Lq, H*d), k, v: (B, Lk, H*d) -> o: (B, Lq, H*d), d <= 4 * D4.
// grid: B * H * ceil(Lq / (8 R)) work groups of 8 (folded into x, y); group g -> (b, h, query block); lane l owns
// query rows qb * 8R + 8r + l for r < R (R rows per lane share every key/value load and broadcast).
@compute @workgroup_size(8)
fn main(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
        @builtin(subgroup_invocation_id) lane: u32) {
    let g = wid.y * nwg.x + wid.x;
    if (g >= a.groups) { return; }
    let qb = g % a.qblocks;
    let bh = g / a.qblocks;
    let h = bh % a.heads;
    let b = bh / a.heads;
    let kbase = b * a.lk * a.w4 + h * a.nc;
    let last = a.nc - 1u;
    // Chunks past nc: q is zero (no effect on the logits), values are re-read from a valid chunk, never stored.
    // Arrays are indexed by loop counters whose trip count equals the array length, so NIR unrolls the loops
    // (up to 32 trips) and the arrays become registers.
    var qr: array<array<vec4<f32>, D4>, R>;
    var acc: array<array<vec4<f32>, D4>, R>;
    var m: array<f32, R>;
    var l: array<f32, R>;
    for (var r = 0u; r < R; r++) {
        let qrow = (b * a.lq + min(qb * 8u * R + 8u * r + lane, a.lq - 1u)) * a.w4 + h * a.nc;
        for (var c = 0u; c < D4; c++) {
            qr[r][c] = vec4<f32>(q[qrow + min(c, last)]) * select(0.0, a.scale, c < a.nc);
            acc[r][c] = vec4<f32>(0.0);
        }
        m[r] = NEG_BIG;
        l[r] = 0.0;
    }
    for (var j0 = 0u; j0 < a.lk; j0 += 8u) {
        let krow = kbase + min(j0 + lane, a.lk - 1u) * a.w4;
        var s0: array<vec4<f32>, R>;
        var s1: array<vec4<f32>, R>;
        for (var r = 0u; r < R; r++) {
            s0[r] = vec4<f32>(0.0);
            s1[r] = vec4<f32>(0.0);
        }
        var raw: KT;
        for (var c = 0u; c < D4; c++) {
            // CPL chunks per load; c is a constant after unrolling, so the branch and the unpack part fold.
            if (c % CPL == 0u) { raw = ldk((krow + min(c, last)) / CPL); }
            let kc = unpack(raw, c % CPL);
            for (var r = 0u; r < R; r++) {
                s0[r] += logits_lo(qr[r][c], kc);
                s1[r] += logits_hi(qr[r][c], kc);
            }
        }
        var st: array<Online, R>;
        for (var r = 0u; r < R; r++) {
            st[r] = online_step(j0, s0[r], s1[r], m[r], l[r]);
            m[r] = st[r].m;
            l[r] = st[r].l;
        }
        for (var c = 0u; c < D4; c++) {
            if (c % CPL == 0u) { raw = ldv((krow + min(c, last)) / CPL); }
            let vc = unpack(raw, c % CPL);
            for (var r = 0u; r < R; r++) {
                acc[r][c] = values_step(acc[r][c], st[r].alpha, st[r].p0, st[r].p1, vc);
            }
        }
    }
    for (var r = 0u; r < R; r++) {
        let i = qb * 8u * R + 8u * r + lane;
        if (i < a.lq) {
            let inv = 1.0 / l[r];
            let orow = (b * a.lq + i) * a.w4 + h * a.nc;
            for (var c = 0u; c < D4; c++) {
                if (c < a.nc) { o[orow + c] = vec4<ST>(acc[r][c] * inv); }
            }
        }
    }
}

// Same shapes as `main` for d % 8 == 0 of any size; grid: B * H * ceil(Lq / 8) * slices work groups,
// group g -> (slice = g % slices, then as main); this group writes columns [slice * 4 * D4, (slice + 1) * 4 * D4).
@compute @workgroup_size(8)
fn wide(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
        @builtin(subgroup_invocation_id) lane: u32) {
    let gs = wid.y * nwg.x + wid.x;
    if (gs >= a.groups) { return; }
    let sl = gs % a.slices;
    let g = gs / a.slices;
    let qb = g % a.qblocks;
    let bh = g / a.qblocks;
    let h = bh % a.heads;
    let b = bh / a.heads;
    let i = qb * 8u + lane;
    let qrow = (b * a.lq + min(i, a.lq - 1u)) * a.w4 + h * a.nc;
    let kbase = b * a.lk * a.w4 + h * a.nc;
    let last = a.nc - 1u;
    let c0 = sl * D4;
    var acc: array<vec4<f32>, D4>;
    for (var c = 0u; c < D4; c++) {
        acc[c] = vec4<f32>(0.0);
    }
    var m = NEG_BIG;
    var l = 0.0;
    for (var j0 = 0u; j0 < a.lk; j0 += 8u) {
        let krow = kbase + min(j0 + lane, a.lk - 1u) * a.w4;
        var s0 = vec4<f32>(0.0);
        var s1 = vec4<f32>(0.0);
        // Two chunks per trip halves this loop's share of the budget (nc is even: d % 8 == 0).
        for (var c = 0u; c < a.nc; c += 2u) {
            let qa = vec4<f32>(q[qrow + c]) * a.scale;
            let ka = unpack(ldk((krow + c) / CPL), (krow + c) % CPL);
            let qb2 = vec4<f32>(q[qrow + c + 1u]) * a.scale;
            let kb = unpack(ldk((krow + c + 1u) / CPL), (krow + c + 1u) % CPL);
            s0 += logits_lo(qa, ka) + logits_lo(qb2, kb);
            s1 += logits_hi(qa, ka) + logits_hi(qb2, kb);
        }
        let st = online_step(j0, s0, s1, m, l);
        m = st.m;
        l = st.l;
        for (var c = 0u; c < D4; c++) {
            acc[c] = values_step(acc[c], st.alpha, st.p0, st.p1, unpack(ldv((krow + min(c0 + c, last)) / CPL), (krow + min(c0 + c, last)) % CPL));
        }
    }
    if (i < a.lq) {
        let inv = 1.0 / l;
        let orow = (b * a.lq + i) * a.w4 + h * a.nc;
        for (var c = 0u; c < D4; c++) {
            if (c0 + c < a.nc) { o[orow + c0 + c] = vec4<ST>(acc[c] * inv); }
        }
    }
}
