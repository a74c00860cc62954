//! variant f32: alias ST = f32; const IS_F16: bool = false; fn note_overflow() {} fn ld4(i: u32) -> vec4<f32> { return vec4<f32>(b4[i]); } fn ld8(i: u32) -> mat2x4<f32> { return mat2x4<f32>(vec4<f32>(b4[2u * i]), vec4<f32>(b4[2u * i + 1u])); } fn lda4(i: u32) -> vec4<f32> { return vec4<f32>(a4[i]); }
//! variant f16: enable f16; alias ST = f16; const IS_F16: bool = true; fn note_overflow() {} fn ld4(i: u32) -> vec4<f32> { let q = bq2[i]; return vec4<f32>(f16x2(q.x), f16x2(q.y)); } fn ld8(i: u32) -> mat2x4<f32> { let q = bq4[i]; return mat2x4<f32>(vec4<f32>(f16x2(q.x), f16x2(q.y)), vec4<f32>(f16x2(q.z), f16x2(q.w))); } fn lda4(i: u32) -> vec4<f32> { let q = aq2[i]; return vec4<f32>(f16x2(q.x), f16x2(q.y)); }
//! variant f16chk [nn, nn4, nn4a, nt, nt4, nt8, nt8a, nt8a4]: enable f16; alias ST = f16; const IS_F16: bool = true; @group(0) @binding(5) var<storage, read_write> flag: array<u32>; fn note_overflow() { flag[0] = 0x3f800000u; } fn ld4(i: u32) -> vec4<f32> { let q = bq2[i]; return vec4<f32>(f16x2(q.x), f16x2(q.y)); } fn ld8(i: u32) -> mat2x4<f32> { let q = bq4[i]; return mat2x4<f32>(vec4<f32>(f16x2(q.x), f16x2(q.y)), vec4<f32>(f16x2(q.z), f16x2(q.w))); } fn lda4(i: u32) -> vec4<f32> { let q = aq2[i]; return vec4<f32>(f16x2(q.x), f16x2(q.y)); }
//! variant f32t [nn, nn4, nn4a, nt, nt4, nt8, nt8a, nt8a4]: alias ST = f32; const IS_F16: bool = false; fn note_overflow() {} fn ld4(i: u32) -> vec4<f32> { return textureLoad(bt, texel_xy(i)); } fn ld8(i: u32) -> mat2x4<f32> { return mat2x4<f32>(textureLoad(bt, texel_xy(2u * i)), textureLoad(bt, texel_xy(2u * i + 1u))); } fn lda4(i: u32) -> vec4<f32> { return textureLoad(at, texel_xy(i)); }
// Batched matmul C = A B (+ bias), register-tiled for llvmpipe (lavapipe), storage ST, arithmetic f32.
//
// Mapping: the invocations of one subgroup (SG lanes; 8 on lavapipe = one llvmpipe SIMD vector) share TM
// output rows; each lane owns 4 output columns. Per chunk of 8 k values lanes 0..7 each load ONE A value per
// row (A[m, k0 + lane]) and subgroupBroadcast with a constant lane gives it to every lane (measured no slower
// than the subgroupShuffle of the spec's experiment, and independent of the subgroup size). B values differ
// per lane. The `a4` kernels at the end load A as vec4 in 32-k chunks (K % 4 == 0).
// Every storage load on lavapipe 22.3 is a per-lane scalar loop (gallivm's load_ssbo), so the design
// minimises load instructions per FMA: vec4 loads where the layout allows, TM rows reusing each B value.
// No shared memory (work-group barriers are slow on llvmpipe). Work-group tile: (WG / SG) TM rows x 4 SG columns.
// Edges: row and k indices are clamped for loads (A masked to 0 past K), stores are guarded.
// Loop budget (lavapipe: 65535 back-edges per invocation): one back-edge per 8 k (K = 23040 -> 2880; the
// `a4` kernels one per 32 k); the inner loops have constant trip counts and are unrolled by NIR.
// f16 outputs saturate at +-65504 (never Inf from overflow; NaN stays NaN); variant f16chk also sets flag[0] to the bits of 1.0f.

struct MatmulParams {
    m: u32, n: u32, k: u32,
    // batch strides (elements) of A and B; 0 broadcasts the operand over the batch
    sa: u32, sb: u32,
    // 0 none, 1 bias[n] per column (linear), 2 bias[m] per row (conv as GEMM)
    bias_mode: u32,
    // batch count (grid z)
    batch: u32,
    // 1: add res (same shape and layout as C) in the epilogue (a fused residual connection)
    res: u32,
}

@group(0) @binding(0) var<storage, read> a: array<ST>;
// vector views of A for the 32-k-chunk kernels: lda4(i) = elements 4i..4i+3 (per variant, like ld4)
@group(0) @binding(0) var<storage, read> a4: array<vec4<ST>>;
@group(0) @binding(0) var<storage, read> aq2: array<vec2<u32>>;
// variant f32t: the vector views of A and B read through the buffers' texel views instead (src/vk/image.rs:
// one 16-byte fetch per lane on lavapipe instead of four bounds-checked scalar loads)
@group(0) @binding(0) var at: texture_storage_2d<rgba32float, read>;
@group(0) @binding(1) var bt: texture_storage_2d<rgba32float, read>;
@group(0) @binding(1) var<storage, read> b: array<ST>;
// vector views of B: ld4(i) = elements 4i..4i+3, ld8(i) = 8i..8i+7 (defined per variant; f16 reads packed u32
// pairs, halving the load instructions, which dominate on lavapipe)
@group(0) @binding(1) var<storage, read> b4: array<vec4<ST>>;
@group(0) @binding(1) var<storage, read> bq2: array<vec2<u32>>;
@group(0) @binding(1) var<storage, read> bq4: array<vec4<u32>>;
@group(0) @binding(2) var<storage, read> bias: array<ST>;
@group(0) @binding(3) var<storage, read_write> c: array<ST>;
// vec4 views for `store_tile4` (N % 4 == 0): one store per row instead of four (each a per-lane loop on lavapipe)
@group(0) @binding(2) var<storage, read> bias4: array<vec4<ST>>;
@group(0) @binding(3) var<storage, read_write> c4v: array<vec4<ST>>;
// residual added to the output (p.res == 1; the launcher binds C here otherwise); res may be C itself (in place:
// each element is read and written by the same invocation)
@group(0) @binding(4) var<storage, read> res: array<ST>;
@group(0) @binding(4) var<storage, read> res4: array<vec4<ST>>;
var<immediate> p: MatmulParams;


const TM: u32 = 16u;
const WG: u32 = 64u;

var<private> acc: array<vec4<f32>, TM>;
var<private> av: array<f32, TM>;
var<private> av4: array<vec4<f32>, TM>;
var<private> aoff: array<u32, TM>;

const F16_MAX: f32 = 65504.0;

fn out_val(x: f32) -> ST {
    if (IS_F16 && abs(x) > F16_MAX) {
        note_overflow();
        return ST(clamp(x, -F16_MAX, F16_MAX));
    }
    return ST(x);
}

// Row offsets of this invocation's TM rows (clamped into the matrix), accumulators zeroed.
fn setup_rows(abase: u32, row0: u32) {
    for (var r = 0u; r < TM; r++) {
        aoff[r] = abase + min(row0 + r, p.m - 1u) * p.k;
        acc[r] = vec4<f32>(0.0);
    }
}

// Element offsets of the W rows (PyTorch Linear layout (N, K)) of a lane's 4 columns col0 + step j (j < 4),
// clamped to the last row (their results are never stored), plus `bbase` (the batch's offset).
fn w_rows(col0: u32, step: u32, bbase: u32) -> vec4<u32> {
    let cols = vec4<u32>(col0, col0 + step, col0 + 2u * step, col0 + 3u * step);
    return min(cols, vec4<u32>(p.n - 1u)) * p.k + bbase;
}

// Lane `lane` loads A[m_r, k0 + lane] for its TM rows (0 past K).
fn load_a(k0: u32, lane: u32) {
    let k = k0 + lane;
    let kc = min(k, p.k - 1u);
    for (var r = 0u; r < TM; r++) {
        av[r] = select(0.0, f32(a[aoff[r] + kc]), k < p.k);
    }
}

// acc[r] += A[m_r, k0 + j] * bv for j = 0..7, A broadcast from lane j (subgroupBroadcast needs a constant lane).
fn fma_k0(bv: vec4<f32>) { for (var r = 0u; r < TM; r++) { acc[r] = fma(vec4<f32>(subgroupBroadcast(av[r], 0u)), bv, acc[r]); } }
fn fma_k1(bv: vec4<f32>) { for (var r = 0u; r < TM; r++) { acc[r] = fma(vec4<f32>(subgroupBroadcast(av[r], 1u)), bv, acc[r]); } }
fn fma_k2(bv: vec4<f32>) { for (var r = 0u; r < TM; r++) { acc[r] = fma(vec4<f32>(subgroupBroadcast(av[r], 2u)), bv, acc[r]); } }
fn fma_k3(bv: vec4<f32>) { for (var r = 0u; r < TM; r++) { acc[r] = fma(vec4<f32>(subgroupBroadcast(av[r], 3u)), bv, acc[r]); } }
fn fma_k4(bv: vec4<f32>) { for (var r = 0u; r < TM; r++) { acc[r] = fma(vec4<f32>(subgroupBroadcast(av[r], 4u)), bv, acc[r]); } }
fn fma_k5(bv: vec4<f32>) { for (var r = 0u; r < TM; r++) { acc[r] = fma(vec4<f32>(subgroupBroadcast(av[r], 5u)), bv, acc[r]); } }
fn fma_k6(bv: vec4<f32>) { for (var r = 0u; r < TM; r++) { acc[r] = fma(vec4<f32>(subgroupBroadcast(av[r], 6u)), bv, acc[r]); } }
fn fma_k7(bv: vec4<f32>) { for (var r = 0u; r < TM; r++) { acc[r] = fma(vec4<f32>(subgroupBroadcast(av[r], 7u)), bv, acc[r]); } }

// C[m, col0 + j * cs] for j < 4 (+ bias), guarded.
fn store_tile(cbase: u32, row0: u32, col0: u32, cs: u32) {
    for (var r = 0u; r < TM; r++) {
        let m = row0 + r;
        if (m >= p.m) { return; }
        for (var j = 0u; j < 4u; j++) {
            let n = col0 + j * cs;
            if (n < p.n) {
                var v = acc[r][j];
                if (p.bias_mode == 1u) { v += f32(bias[n]); }
                if (p.bias_mode == 2u) { v += f32(bias[m]); }
                if (p.res == 1u) { v += f32(res[cbase + m * p.n + n]); }
                c[cbase + m * p.n + n] = out_val(v);
            }
        }
    }
}

fn out_val4(x: vec4<f32>) -> vec4<ST> {
    if (IS_F16 && any(abs(x) > vec4<f32>(F16_MAX))) {
        note_overflow();
        return vec4<ST>(clamp(x, vec4<f32>(-F16_MAX), vec4<f32>(F16_MAX)));
    }
    return vec4<ST>(x);
}

// store_tile for 4 consecutive columns col0 .. col0 + 3 per lane (col0 % 4 == 0, N % 4 == 0): vec4 stores, the
// column bias loaded once. Bias buffers are allocated in 16-byte units, so bias4[m / 4] is in bounds.
fn store_tile4(cbase: u32, row0: u32, col0: u32) {
    if (col0 >= p.n) { return; }
    var bv = vec4<f32>(0.0);
    if (p.bias_mode == 1u) { bv = vec4<f32>(bias4[col0 / 4u]); }
    for (var r = 0u; r < TM; r++) {
        let m = row0 + r;
        if (m >= p.m) { return; }
        var v = acc[r] + bv;
        if (p.bias_mode == 2u) { v += vec4<f32>(f32(bias4[m / 4u][m % 4u])); }
        let o4 = (cbase + m * p.n + col0) / 4u;
        if (p.res == 1u) { v += vec4<f32>(res4[o4]); }
        c4v[o4] = out_val4(v);
    }
}

// B row k (clamped), 4 consecutive columns starting at col (clamped to N - 1 each).
fn b_row_scalar(bbase: u32, k: u32, cols: vec4<u32>) -> vec4<f32> {
    let o = bbase + min(k, p.k - 1u) * p.n;
    return vec4<f32>(f32(b[o + cols.x]), f32(b[o + cols.y]), f32(b[o + cols.z]), f32(b[o + cols.w]));
}

// A: (B?, M, K), B: (B?, K, N) -> C: (B, M, N). Work groups: (ceil(N / 4 SG), ceil(M / (WG / SG) TM), batch).
// `nn4` needs N % 4 == 0 (vec4 loads of B); `nn` takes any N.
@compute @workgroup_size(WG)
fn nn(@builtin(workgroup_id) wid: vec3<u32>, @builtin(local_invocation_index) li: u32,
      @builtin(subgroup_invocation_id) lane: u32, @builtin(subgroup_size) sgs: u32) {
    let row0 = (wid.y * (WG / sgs) + li / sgs) * TM;
    // a subgroup past the last row leaves at once (uniform per subgroup; no barriers follow)
    if (row0 >= p.m) { return; }
    let col0 = (wid.x * sgs + lane) * 4u;
    let nm = p.n - 1u;
    let cols = vec4<u32>(min(col0, nm), min(col0 + 1u, nm), min(col0 + 2u, nm), min(col0 + 3u, nm));
    let bbase = wid.z * p.sb;
    setup_rows(wid.z * p.sa, row0);
    for (var k0 = 0u; k0 < p.k; k0 += 8u) {
        load_a(k0, lane & 7u);
        fma_k0(b_row_scalar(bbase, k0, cols));
        fma_k1(b_row_scalar(bbase, k0 + 1u, cols));
        fma_k2(b_row_scalar(bbase, k0 + 2u, cols));
        fma_k3(b_row_scalar(bbase, k0 + 3u, cols));
        fma_k4(b_row_scalar(bbase, k0 + 4u, cols));
        fma_k5(b_row_scalar(bbase, k0 + 5u, cols));
        fma_k6(b_row_scalar(bbase, k0 + 6u, cols));
        fma_k7(b_row_scalar(bbase, k0 + 7u, cols));
    }
    store_tile(wid.z * p.m * p.n, row0, col0, 1u);
}

fn b_row_vec4(bbase4: u32, k: u32, col4: u32) -> vec4<f32> {
    return ld4(bbase4 + min(k, p.k - 1u) * (p.n / 4u) + col4);
}

@compute @workgroup_size(WG)
fn nn4(@builtin(workgroup_id) wid: vec3<u32>, @builtin(local_invocation_index) li: u32,
       @builtin(subgroup_invocation_id) lane: u32, @builtin(subgroup_size) sgs: u32) {
    let row0 = (wid.y * (WG / sgs) + li / sgs) * TM;
    // a subgroup past the last row leaves at once (uniform per subgroup; no barriers follow)
    if (row0 >= p.m) { return; }
    let col0 = (wid.x * sgs + lane) * 4u;
    let col4 = min(col0, p.n - 4u) / 4u;
    let bbase4 = wid.z * p.sb / 4u;
    setup_rows(wid.z * p.sa, row0);
    for (var k0 = 0u; k0 < p.k; k0 += 8u) {
        load_a(k0, lane & 7u);
        fma_k0(b_row_vec4(bbase4, k0, col4));
        fma_k1(b_row_vec4(bbase4, k0 + 1u, col4));
        fma_k2(b_row_vec4(bbase4, k0 + 2u, col4));
        fma_k3(b_row_vec4(bbase4, k0 + 3u, col4));
        fma_k4(b_row_vec4(bbase4, k0 + 4u, col4));
        fma_k5(b_row_vec4(bbase4, k0 + 5u, col4));
        fma_k6(b_row_vec4(bbase4, k0 + 6u, col4));
        fma_k7(b_row_vec4(bbase4, k0 + 7u, col4));
    }
    store_tile4(wid.z * p.m * p.n, row0, col0);
}

// W[n, k0 .. k0 + 4] (clamped; the A side is 0 past K). Scalar loads, any K.
fn w_quad_scalar(o: u32, k0: u32) -> vec4<f32> {
    let km = p.k - 1u;
    return vec4<f32>(f32(b[o + min(k0, km)]), f32(b[o + min(k0 + 1u, km)]),
                     f32(b[o + min(k0 + 2u, km)]), f32(b[o + min(k0 + 3u, km)]));
}

// One vec4 load; needs K % 4 == 0 and o % 4 == 0.
fn w_quad_vec4(o: u32, k0: u32) -> vec4<f32> {
    return ld4((o + min(k0, p.k - 4u)) / 4u);
}

// 8 k steps from the four columns' W values w0..w3 (each 2 quads: k0..k0+3, k0+4..k0+7).
fn fma_nt(w0a: vec4<f32>, w0b: vec4<f32>, w1a: vec4<f32>, w1b: vec4<f32>,
          w2a: vec4<f32>, w2b: vec4<f32>, w3a: vec4<f32>, w3b: vec4<f32>) {
    fma_k0(vec4<f32>(w0a.x, w1a.x, w2a.x, w3a.x));
    fma_k1(vec4<f32>(w0a.y, w1a.y, w2a.y, w3a.y));
    fma_k2(vec4<f32>(w0a.z, w1a.z, w2a.z, w3a.z));
    fma_k3(vec4<f32>(w0a.w, w1a.w, w2a.w, w3a.w));
    fma_k4(vec4<f32>(w0b.x, w1b.x, w2b.x, w3b.x));
    fma_k5(vec4<f32>(w0b.y, w1b.y, w2b.y, w3b.y));
    fma_k6(vec4<f32>(w0b.z, w1b.z, w2b.z, w3b.z));
    fma_k7(vec4<f32>(w0b.w, w1b.w, w2b.w, w3b.w));
}

// A: (B?, M, K), W: (B?, N, K) (PyTorch Linear weight) -> C = A W^T: (B, M, N).
// Lane l owns columns col0 + l + SG j (j < 4). Work groups as for `nn`. `nt4` needs K % 4 == 0.
@compute @workgroup_size(WG)
fn nt(@builtin(workgroup_id) wid: vec3<u32>, @builtin(local_invocation_index) li: u32,
      @builtin(subgroup_invocation_id) lane: u32, @builtin(subgroup_size) sgs: u32) {
    let row0 = (wid.y * (WG / sgs) + li / sgs) * TM;
    // a subgroup past the last row leaves at once (uniform per subgroup; no barriers follow)
    if (row0 >= p.m) { return; }
    let col0 = wid.x * 4u * sgs + lane;
    let bbase = wid.z * p.sb;
    let wo = w_rows(col0, sgs, bbase);
    setup_rows(wid.z * p.sa, row0);
    for (var k0 = 0u; k0 < p.k; k0 += 8u) {
        load_a(k0, lane & 7u);
        fma_nt(w_quad_scalar(wo.x, k0), w_quad_scalar(wo.x, k0 + 4u), w_quad_scalar(wo.y, k0), w_quad_scalar(wo.y, k0 + 4u),
               w_quad_scalar(wo.z, k0), w_quad_scalar(wo.z, k0 + 4u), w_quad_scalar(wo.w, k0), w_quad_scalar(wo.w, k0 + 4u));
    }
    store_tile(wid.z * p.m * p.n, row0, col0, sgs);
}

@compute @workgroup_size(WG)
fn nt4(@builtin(workgroup_id) wid: vec3<u32>, @builtin(local_invocation_index) li: u32,
       @builtin(subgroup_invocation_id) lane: u32, @builtin(subgroup_size) sgs: u32) {
    let row0 = (wid.y * (WG / sgs) + li / sgs) * TM;
    // a subgroup past the last row leaves at once (uniform per subgroup; no barriers follow)
    if (row0 >= p.m) { return; }
    let col0 = wid.x * 4u * sgs + lane;
    let bbase = wid.z * p.sb;
    let wo = w_rows(col0, sgs, bbase);
    setup_rows(wid.z * p.sa, row0);
    for (var k0 = 0u; k0 < p.k; k0 += 8u) {
        load_a(k0, lane & 7u);
        fma_nt(w_quad_vec4(wo.x, k0), w_quad_vec4(wo.x, k0 + 4u), w_quad_vec4(wo.y, k0), w_quad_vec4(wo.y, k0 + 4u),
               w_quad_vec4(wo.z, k0), w_quad_vec4(wo.z, k0 + 4u), w_quad_vec4(wo.w, k0), w_quad_vec4(wo.w, k0 + 4u));
    }
    store_tile(wid.z * p.m * p.n, row0, col0, sgs);
}

// `nt` with K % 8 == 0: one ld8 per column and chunk (f16: a single vec4<u32> load).
@compute @workgroup_size(WG)
fn nt8(@builtin(workgroup_id) wid: vec3<u32>, @builtin(local_invocation_index) li: u32,
       @builtin(subgroup_invocation_id) lane: u32, @builtin(subgroup_size) sgs: u32) {
    let row0 = (wid.y * (WG / sgs) + li / sgs) * TM;
    // a subgroup past the last row leaves at once (uniform per subgroup; no barriers follow)
    if (row0 >= p.m) { return; }
    let col0 = wid.x * 4u * sgs + lane;
    let wo = w_rows(col0, sgs, wid.z * p.sb) / 8u;
    setup_rows(wid.z * p.sa, row0);
    for (var k0 = 0u; k0 < p.k; k0 += 8u) {
        load_a(k0, lane & 7u);
        let k8 = k0 / 8u;
        let w0 = ld8(wo.x + k8);
        let w1 = ld8(wo.y + k8);
        let w2 = ld8(wo.z + k8);
        let w3 = ld8(wo.w + k8);
        fma_nt(w0[0], w0[1], w1[0], w1[1], w2[0], w2[1], w3[0], w3[1]);
    }
    store_tile(wid.z * p.m * p.n, row0, col0, sgs);
}

// ---- 32-k chunks with vec4 A loads (K % 4 == 0): lanes 0..7 each load A[m, k0 + 4 l .. + 3] per row, a
// quarter of the A load instructions of the kernels above (A loads were ~20% of the time on lavapipe).
// 4 k steps (k0 + 4 q .. + 3): A from component c of lane q's vec4 (the `a4` kernels below).
fn fma_q0(b0: vec4<f32>, b1: vec4<f32>, b2: vec4<f32>, b3: vec4<f32>) { for (var r = 0u; r < TM; r++) { let x = av4[r]; acc[r] = fma(vec4<f32>(subgroupBroadcast(x.x, 0u)), b0, acc[r]); acc[r] = fma(vec4<f32>(subgroupBroadcast(x.y, 0u)), b1, acc[r]); acc[r] = fma(vec4<f32>(subgroupBroadcast(x.z, 0u)), b2, acc[r]); acc[r] = fma(vec4<f32>(subgroupBroadcast(x.w, 0u)), b3, acc[r]); } }
fn fma_q1(b0: vec4<f32>, b1: vec4<f32>, b2: vec4<f32>, b3: vec4<f32>) { for (var r = 0u; r < TM; r++) { let x = av4[r]; acc[r] = fma(vec4<f32>(subgroupBroadcast(x.x, 1u)), b0, acc[r]); acc[r] = fma(vec4<f32>(subgroupBroadcast(x.y, 1u)), b1, acc[r]); acc[r] = fma(vec4<f32>(subgroupBroadcast(x.z, 1u)), b2, acc[r]); acc[r] = fma(vec4<f32>(subgroupBroadcast(x.w, 1u)), b3, acc[r]); } }
fn fma_q2(b0: vec4<f32>, b1: vec4<f32>, b2: vec4<f32>, b3: vec4<f32>) { for (var r = 0u; r < TM; r++) { let x = av4[r]; acc[r] = fma(vec4<f32>(subgroupBroadcast(x.x, 2u)), b0, acc[r]); acc[r] = fma(vec4<f32>(subgroupBroadcast(x.y, 2u)), b1, acc[r]); acc[r] = fma(vec4<f32>(subgroupBroadcast(x.z, 2u)), b2, acc[r]); acc[r] = fma(vec4<f32>(subgroupBroadcast(x.w, 2u)), b3, acc[r]); } }
fn fma_q3(b0: vec4<f32>, b1: vec4<f32>, b2: vec4<f32>, b3: vec4<f32>) { for (var r = 0u; r < TM; r++) { let x = av4[r]; acc[r] = fma(vec4<f32>(subgroupBroadcast(x.x, 3u)), b0, acc[r]); acc[r] = fma(vec4<f32>(subgroupBroadcast(x.y, 3u)), b1, acc[r]); acc[r] = fma(vec4<f32>(subgroupBroadcast(x.z, 3u)), b2, acc[r]); acc[r] = fma(vec4<f32>(subgroupBroadcast(x.w, 3u)), b3, acc[r]); } }
fn fma_q4(b0: vec4<f32>, b1: vec4<f32>, b2: vec4<f32>, b3: vec4<f32>) { for (var r = 0u; r < TM; r++) { let x = av4[r]; acc[r] = fma(vec4<f32>(subgroupBroadcast(x.x, 4u)), b0, acc[r]); acc[r] = fma(vec4<f32>(subgroupBroadcast(x.y, 4u)), b1, acc[r]); acc[r] = fma(vec4<f32>(subgroupBroadcast(x.z, 4u)), b2, acc[r]); acc[r] = fma(vec4<f32>(subgroupBroadcast(x.w, 4u)), b3, acc[r]); } }
fn fma_q5(b0: vec4<f32>, b1: vec4<f32>, b2: vec4<f32>, b3: vec4<f32>) { for (var r = 0u; r < TM; r++) { let x = av4[r]; acc[r] = fma(vec4<f32>(subgroupBroadcast(x.x, 5u)), b0, acc[r]); acc[r] = fma(vec4<f32>(subgroupBroadcast(x.y, 5u)), b1, acc[r]); acc[r] = fma(vec4<f32>(subgroupBroadcast(x.z, 5u)), b2, acc[r]); acc[r] = fma(vec4<f32>(subgroupBroadcast(x.w, 5u)), b3, acc[r]); } }
fn fma_q6(b0: vec4<f32>, b1: vec4<f32>, b2: vec4<f32>, b3: vec4<f32>) { for (var r = 0u; r < TM; r++) { let x = av4[r]; acc[r] = fma(vec4<f32>(subgroupBroadcast(x.x, 6u)), b0, acc[r]); acc[r] = fma(vec4<f32>(subgroupBroadcast(x.y, 6u)), b1, acc[r]); acc[r] = fma(vec4<f32>(subgroupBroadcast(x.z, 6u)), b2, acc[r]); acc[r] = fma(vec4<f32>(subgroupBroadcast(x.w, 6u)), b3, acc[r]); } }
fn fma_q7(b0: vec4<f32>, b1: vec4<f32>, b2: vec4<f32>, b3: vec4<f32>) { for (var r = 0u; r < TM; r++) { let x = av4[r]; acc[r] = fma(vec4<f32>(subgroupBroadcast(x.x, 7u)), b0, acc[r]); acc[r] = fma(vec4<f32>(subgroupBroadcast(x.y, 7u)), b1, acc[r]); acc[r] = fma(vec4<f32>(subgroupBroadcast(x.z, 7u)), b2, acc[r]); acc[r] = fma(vec4<f32>(subgroupBroadcast(x.w, 7u)), b3, acc[r]); } }

// Lane `lane` (< 8) loads A[m_r, k0 + 4 lane .. + 3] for its TM rows (0 past K; K % 4 == 0).
fn load_a4(k0: u32, lane: u32) {
    let k = k0 + 4u * lane;
    let kc = min(k, p.k - 4u);
    for (var r = 0u; r < TM; r++) {
        av4[r] = select(vec4<f32>(0.0), lda4((aoff[r] + kc) / 4u), k < p.k);
    }
}

// `nn4` with K % 4 == 0 (and A's batch stride % 4 == 0).
@compute @workgroup_size(WG)
fn nn4a(@builtin(workgroup_id) wid: vec3<u32>, @builtin(local_invocation_index) li: u32,
        @builtin(subgroup_invocation_id) lane: u32, @builtin(subgroup_size) sgs: u32) {
    let row0 = (wid.y * (WG / sgs) + li / sgs) * TM;
    // a subgroup past the last row leaves at once (uniform per subgroup; no barriers follow)
    if (row0 >= p.m) { return; }
    let col0 = (wid.x * sgs + lane) * 4u;
    let col4 = min(col0, p.n - 4u) / 4u;
    let bb = wid.z * p.sb / 4u;
    setup_rows(wid.z * p.sa, row0);
    for (var k0 = 0u; k0 < p.k; k0 += 32u) {
        load_a4(k0, lane & 7u);
        fma_q0(b_row_vec4(bb, k0, col4), b_row_vec4(bb, k0 + 1u, col4), b_row_vec4(bb, k0 + 2u, col4), b_row_vec4(bb, k0 + 3u, col4));
        fma_q1(b_row_vec4(bb, k0 + 4u, col4), b_row_vec4(bb, k0 + 5u, col4), b_row_vec4(bb, k0 + 6u, col4), b_row_vec4(bb, k0 + 7u, col4));
        fma_q2(b_row_vec4(bb, k0 + 8u, col4), b_row_vec4(bb, k0 + 9u, col4), b_row_vec4(bb, k0 + 10u, col4), b_row_vec4(bb, k0 + 11u, col4));
        fma_q3(b_row_vec4(bb, k0 + 12u, col4), b_row_vec4(bb, k0 + 13u, col4), b_row_vec4(bb, k0 + 14u, col4), b_row_vec4(bb, k0 + 15u, col4));
        fma_q4(b_row_vec4(bb, k0 + 16u, col4), b_row_vec4(bb, k0 + 17u, col4), b_row_vec4(bb, k0 + 18u, col4), b_row_vec4(bb, k0 + 19u, col4));
        fma_q5(b_row_vec4(bb, k0 + 20u, col4), b_row_vec4(bb, k0 + 21u, col4), b_row_vec4(bb, k0 + 22u, col4), b_row_vec4(bb, k0 + 23u, col4));
        fma_q6(b_row_vec4(bb, k0 + 24u, col4), b_row_vec4(bb, k0 + 25u, col4), b_row_vec4(bb, k0 + 26u, col4), b_row_vec4(bb, k0 + 27u, col4));
        fma_q7(b_row_vec4(bb, k0 + 28u, col4), b_row_vec4(bb, k0 + 29u, col4), b_row_vec4(bb, k0 + 30u, col4), b_row_vec4(bb, k0 + 31u, col4));
    }
    store_tile4(wid.z * p.m * p.n, row0, col0);
}

// k values h * 4 .. h * 4 + 3 of the 8 in w (one column each) as 4 k-step vectors over the 4 columns.
fn tcol(w0: vec4<f32>, w1: vec4<f32>, w2: vec4<f32>, w3: vec4<f32>, i: u32) -> vec4<f32> {
    return vec4<f32>(w0[i], w1[i], w2[i], w3[i]);
}

// `nt8` with 32-k chunks; W rows (K % 8 == 0) read 8 k at a time, clamped past K (A is 0 there).
@compute @workgroup_size(WG)
fn nt8a(@builtin(workgroup_id) wid: vec3<u32>, @builtin(local_invocation_index) li: u32,
        @builtin(subgroup_invocation_id) lane: u32, @builtin(subgroup_size) sgs: u32) {
    let row0 = (wid.y * (WG / sgs) + li / sgs) * TM;
    // a subgroup past the last row leaves at once (uniform per subgroup; no barriers follow)
    if (row0 >= p.m) { return; }
    let col0 = wid.x * 4u * sgs + lane;
    let wo = w_rows(col0, sgs, wid.z * p.sb) / 8u;
    nt8a_k(wo, row0, lane, wid.z * p.sa);
    store_tile(wid.z * p.m * p.n, row0, col0, sgs);
}

// The k loop of `nt8a` / `nt8a4`: W rows wo (in 8-element units, batch offset included), rows from row0.
fn nt8a_k(wo: vec4<u32>, row0: u32, lane: u32, abase: u32) {
    let k8m = p.k / 8u - 1u;
    setup_rows(abase, row0);
    for (var k0 = 0u; k0 < p.k; k0 += 32u) {
        load_a4(k0, lane & 7u);
        let k8 = k0 / 8u;
        var o = k8;
        var w0 = ld8(wo.x + o); var w1 = ld8(wo.y + o); var w2 = ld8(wo.z + o); var w3 = ld8(wo.w + o);
        fma_q0(tcol(w0[0], w1[0], w2[0], w3[0], 0u), tcol(w0[0], w1[0], w2[0], w3[0], 1u), tcol(w0[0], w1[0], w2[0], w3[0], 2u), tcol(w0[0], w1[0], w2[0], w3[0], 3u));
        fma_q1(tcol(w0[1], w1[1], w2[1], w3[1], 0u), tcol(w0[1], w1[1], w2[1], w3[1], 1u), tcol(w0[1], w1[1], w2[1], w3[1], 2u), tcol(w0[1], w1[1], w2[1], w3[1], 3u));
        o = min(k8 + 1u, k8m);
        w0 = ld8(wo.x + o); w1 = ld8(wo.y + o); w2 = ld8(wo.z + o); w3 = ld8(wo.w + o);
        fma_q2(tcol(w0[0], w1[0], w2[0], w3[0], 0u), tcol(w0[0], w1[0], w2[0], w3[0], 1u), tcol(w0[0], w1[0], w2[0], w3[0], 2u), tcol(w0[0], w1[0], w2[0], w3[0], 3u));
        fma_q3(tcol(w0[1], w1[1], w2[1], w3[1], 0u), tcol(w0[1], w1[1], w2[1], w3[1], 1u), tcol(w0[1], w1[1], w2[1], w3[1], 2u), tcol(w0[1], w1[1], w2[1], w3[1], 3u));
        o = min(k8 + 2u, k8m);
        w0 = ld8(wo.x + o); w1 = ld8(wo.y + o); w2 = ld8(wo.z + o); w3 = ld8(wo.w + o);
        fma_q4(tcol(w0[0], w1[0], w2[0], w3[0], 0u), tcol(w0[0], w1[0], w2[0], w3[0], 1u), tcol(w0[0], w1[0], w2[0], w3[0], 2u), tcol(w0[0], w1[0], w2[0], w3[0], 3u));
        fma_q5(tcol(w0[1], w1[1], w2[1], w3[1], 0u), tcol(w0[1], w1[1], w2[1], w3[1], 1u), tcol(w0[1], w1[1], w2[1], w3[1], 2u), tcol(w0[1], w1[1], w2[1], w3[1], 3u));
        o = min(k8 + 3u, k8m);
        w0 = ld8(wo.x + o); w1 = ld8(wo.y + o); w2 = ld8(wo.z + o); w3 = ld8(wo.w + o);
        fma_q6(tcol(w0[0], w1[0], w2[0], w3[0], 0u), tcol(w0[0], w1[0], w2[0], w3[0], 1u), tcol(w0[0], w1[0], w2[0], w3[0], 2u), tcol(w0[0], w1[0], w2[0], w3[0], 3u));
        fma_q7(tcol(w0[1], w1[1], w2[1], w3[1], 0u), tcol(w0[1], w1[1], w2[1], w3[1], 1u), tcol(w0[1], w1[1], w2[1], w3[1], 2u), tcol(w0[1], w1[1], w2[1], w3[1], 3u));
    }
}

// `nt8a` with lane l owning the 4 consecutive columns col0 + 4 l .. + 3 (N % 4 == 0), stored as vec4s.
@compute @workgroup_size(WG)
fn nt8a4(@builtin(workgroup_id) wid: vec3<u32>, @builtin(local_invocation_index) li: u32,
        @builtin(subgroup_invocation_id) lane: u32, @builtin(subgroup_size) sgs: u32) {
    let row0 = (wid.y * (WG / sgs) + li / sgs) * TM;
    // a subgroup past the last row leaves at once (uniform per subgroup; no barriers follow)
    if (row0 >= p.m) { return; }
    let col0 = (wid.x * sgs + lane) * 4u;
    let wo = w_rows(col0, 1u, wid.z * p.sb) / 8u;
    nt8a_k(wo, row0, lane, wid.z * p.sa);
    store_tile4(wid.z * p.m * p.n, row0, col0);
}

// ---- GEGLU feed-forward input: C (B, M, N / 2) = a * gelu(g) (+ res) with [a | g] = A W^T + bias, W: (N, K)
// permuted at load (`matmul::geglu_permutation`) so that in each block of 4 SG columns the lane's column j
// (col0 + SG j) holds value column blk 2 SG + (j / 2) SG + lane for even j and its gate column for odd j: one
// lane holds both halves of its two output columns, and the (M, N) pre-activation never goes to memory (one
// pass instead of a GEMM store, a GEGLU read and its store). Needs N % (4 SG) == 0, K % 8 == 0 (as nt8a). The
// residual (p.res) exists so every entry of this file binds 0..4 (the f16chk flag is binding 5).
fn store_geglu(cbase: u32, row0: u32, oc: u32, col0: u32, sgs: u32) {
    let d = p.n / 2u;
    var bv = vec4<f32>(0.0);
    if (p.bias_mode == 1u) {
        bv = vec4<f32>(f32(bias[col0]), f32(bias[col0 + sgs]), f32(bias[col0 + 2u * sgs]), f32(bias[col0 + 3u * sgs]));
    }
    for (var r = 0u; r < TM; r++) {
        let m = row0 + r;
        if (m >= p.m) { return; }
        let v = acc[r] + bv;
        let o = cbase + m * d + oc;
        var y0 = v.x * gelu_erf(v.y);
        var y1 = v.z * gelu_erf(v.w);
        if (p.res == 1u) { y0 += f32(res[o]); y1 += f32(res[o + sgs]); }
        c[o] = out_val(y0);
        c[o + sgs] = out_val(y1);
    }
}

@compute @workgroup_size(WG)
fn nt8a_geglu(@builtin(workgroup_id) wid: vec3<u32>, @builtin(local_invocation_index) li: u32,
              @builtin(subgroup_invocation_id) lane: u32, @builtin(subgroup_size) sgs: u32) {
    let row0 = (wid.y * (WG / sgs) + li / sgs) * TM;
    // a subgroup past the last row leaves at once (uniform per subgroup; no barriers follow)
    if (row0 >= p.m) { return; }
    let col0 = wid.x * 4u * sgs + lane;
    let wo = w_rows(col0, sgs, wid.z * p.sb) / 8u;
    nt8a_k(wo, row0, lane, wid.z * p.sa);
    store_geglu(wid.z * p.m * (p.n / 2u), row0, wid.x * 2u * sgs + lane, col0, sgs);
}
