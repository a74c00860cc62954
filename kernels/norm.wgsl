//! variant f32: alias ST = f32;
//! variant f16: enable f16; alias ST = f16;
// Group norm and layer norm as one kernel: normalise contiguous segments.
// group_norm x: (N, C, H, W), G groups -> segment = one (n, g) = (C/G) * H * W contiguous values;
//   gamma/beta index = g * (C/G) + i / (H*W).
// layer_norm x: (rows, D) -> segment = one row; gamma/beta index = i.
// One work group (256 invocations) per segment. Statistics in f32 on values shifted by the segment's first
// element (x - x0 is exact for nearby values, Sterbenz), then a second pass for the variance of the shifted
// values: near-constant segments (100 +- 1e-3) keep full precision and a constant one gives var 0 -> beta.
// Loop budget: ceil(len / 256) iterations per pass, 3 passes (SD VAE worst case 358400 / 256 * 3 = 4200).
// (`gn4` below, used whenever len % 4 == 0, has one statistics pass instead of two.)

struct NormParams {
    len: u32,          // segment length
    segs_per_item: u32,// G for group norm, 1 for layer norm
    ch_per_seg: u32,   // C/G for group norm, D for layer norm
    inner: u32,        // H*W for group norm, 1 for layer norm
    eps: f32,
    silu: u32,         // 1: apply SiLU after the affine transform
    tokens: u32,       // group norm: 1 writes y as (N, H W, C) tokens (a transformer's input layout)
}

@group(0) @binding(0) var<storage, read> x: array<ST>;
@group(0) @binding(1) var<storage, read> gamma: array<ST>;
@group(0) @binding(2) var<storage, read> beta: array<ST>;
@group(0) @binding(3) var<storage, read_write> y: array<ST>;
// vec4 views (`gn4`, `gn_stats`, `layer_norm_sg4`)
@group(0) @binding(0) var<storage, read> x4: array<vec4<ST>>;
@group(0) @binding(1) var<storage, read> gv4: array<vec4<ST>>;
@group(0) @binding(2) var<storage, read> bv4: array<vec4<ST>>;
@group(0) @binding(3) var<storage, read_write> y4: array<vec4<ST>>;
var<immediate> p: NormParams;
var<workgroup> red: array<f32, 256>;

fn reduce_sum(v: f32, l: u32) -> f32 {
    red[l] = v;
    workgroupBarrier();
    for (var s = 128u; s > 0u; s = s >> 1u) {
        if (l < s) { red[l] = red[l] + red[l + s]; }
        workgroupBarrier();
    }
    let r = red[0];
    workgroupBarrier();
    return r;
}

@compute @workgroup_size(256)
fn main(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>, @builtin(local_invocation_id) lid: vec3<u32>) {
    let seg = wid.y * nwg.x + wid.x;
    let l = lid.x;
    let base = seg * p.len;
    let x0 = f32(x[base]);
    var s = 0.0;
    for (var i = l; i < p.len; i += 256u) { s += f32(x[base + i]) - x0; }
    let mean = reduce_sum(s, l) / f32(p.len); // mean of the shifted values
    var q = 0.0;
    for (var i = l; i < p.len; i += 256u) { let d = (f32(x[base + i]) - x0) - mean; q += d * d; }
    let var_ = reduce_sum(q, l) / f32(p.len);
    let rstd = inverseSqrt(var_ + p.eps);
    let cbase = (seg % p.segs_per_item) * p.ch_per_seg;
    if (p.inner == 1u) {
        // layer norm: one affine parameter per element
        for (var i = l; i < p.len; i += 256u) {
            var v = ((f32(x[base + i]) - x0) - mean) * rstd * f32(gamma[cbase + i]) + f32(beta[cbase + i]);
            if (p.silu == 1u) { v = silu(v); }
            y[base + i] = ST(v);
        }
    } else {
        // group norm: loop per channel so gamma/beta are uniform and no per-element integer division is needed
        // (llvmpipe has no vector integer divide). Iterations: ch_per_seg * ceil(inner / 256).
        for (var c = 0u; c < p.ch_per_seg; c++) {
            let g = rstd * f32(gamma[cbase + c]);
            let b = f32(beta[cbase + c]) - mean * g;
            let cb = base + c * p.inner;
            // token layout: element (n, c_all, j) goes to (n, j, c_all)
            let ctot = p.segs_per_item * p.ch_per_seg;
            let tb = (seg / p.segs_per_item) * p.inner * ctot + cbase + c;
            for (var j = l; j < p.inner; j += 256u) {
                var v = (f32(x[cb + j]) - x0) * g + b;
                if (p.silu == 1u) { v = silu(v); }
                let yi = select(cb + j, tb + j * ctot, p.tokens == 1u);
                y[yi] = ST(v);
            }
        }
    }
}

// layer_norm_sg: one subgroup per row, no barriers (llvmpipe's work-group barriers are expensive and a
// 256-wide group wastes lanes on short rows). Work group of 64 invocations = 64 / subgroup_size rows; lanes
// stride over the row (contiguous across lanes); sums through subgroupAdd. Same shifted two-pass statistics
// as `main`. p.len = D, p.ch_per_seg = rows. Loop budget: 3 * ceil(D / subgroup_size).
@compute @workgroup_size(64)
fn layer_norm_sg(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
                 @builtin(subgroup_invocation_id) lane: u32, @builtin(subgroup_size) sg: u32,
                 @builtin(local_invocation_index) li: u32) {
    let row = (wid.y * nwg.x + wid.x) * (64u / sg) + li / sg;
    if (row >= p.ch_per_seg) { return; }
    let d = p.len;
    let base = row * d;
    let x0 = f32(x[base]);
    var s = 0.0;
    for (var i = lane; i < d; i += sg) { s += f32(x[base + i]) - x0; }
    let mean = subgroupAdd(s) / f32(d);
    var q = 0.0;
    for (var i = lane; i < d; i += sg) { let t = (f32(x[base + i]) - x0) - mean; q += t * t; }
    let rstd = inverseSqrt(subgroupAdd(q) / f32(d) + p.eps);
    for (var i = lane; i < d; i += sg) {
        y[base + i] = ST(((f32(x[base + i]) - x0) - mean) * rstd * f32(gamma[i]) + f32(beta[i]));
    }
}

// group_norm with vec4 statistics (segment length % 4 == 0): one read pass for the statistics instead of two,
// Welford per lane on the shifted values d = x - x0 (x0 the segment's first element, as in `main`; each of a
// lane's vec4 components is its own stream, all with the lane's count k), merged across components and then
// across the work group (`reduce_welford`). On lavapipe every storage access is a per-lane
// loop, so the passes over x set the cost: 2 reads + 1 write per element instead of 3 + 1. Welford keeps the
// precision of the two-pass form: M2 accumulates squared deviations from the running mean, never a difference
// of large sums, and the shift keeps near-constant segments (100 +- 1e-3) exact. The normalise pass is vec4
// when the channel plane is (H W % 4 == 0), else scalar per channel (gamma/beta stay uniform either way).
// Loop budget: ceil(len / 1024) + ch_per_seg * ceil(inner / 256) iterations (+ 256 / (sg sg) in the reduction).
var<workgroup> red4: array<vec4<f32>, 256>;
// scalar views of x and y for `gn4`'s per-channel pass when H W % 4 != 0: naga refuses two views of one binding
// in one entry point, so the launcher binds x and y a second time here
@group(0) @binding(4) var<storage, read> xs: array<ST>;
@group(0) @binding(5) var<storage, read_write> ys: array<ST>;

// (count, mean, M2) of the union of the sets of a subgroup's lanes, the same in every lane: the exact
// decomposition M2 = sum_i (M2_i + n_i (mean_i - mean)^2) with mean = sum_i n_i mean_i / n, through subgroupAdd
// (on llvmpipe a subgroup is one SIMD vector: a horizontal add, no memory traffic). All terms are >= 0.
fn merge_sg(v: vec3<f32>) -> vec3<f32> {
    let n = subgroupAdd(v.x);
    let mean = subgroupAdd(v.x * v.y) / max(n, 1.0);
    let d = v.y - mean;
    return vec3<f32>(n, mean, subgroupAdd(v.z + v.x * d * d));
}

// Work-group merge of per-lane (count, mean, M2): within each subgroup by `merge_sg`, then every subgroup reads
// the WG / sg partials back from shared memory (a strided share per lane) and merges them the same way. One
// barrier, a few shared accesses per lane (a barrier tree would need 8 rounds of per-lane shared loads and
// stores, which on lavapipe cost as much as a pass over a small group's data).
fn reduce_welford(v: vec3<f32>, l: u32, lane: u32, sg: u32) -> vec3<f32> {
    return reduce_welford_wg(v, l, lane, sg, 256u);
}

// `reduce_welford` for a work group of `wg` invocations (a literal: the loop bound folds).
fn reduce_welford_wg(v: vec3<f32>, l: u32, lane: u32, sg: u32, wg: u32) -> vec3<f32> {
    let s = merge_sg(v);
    if (lane == 0u) { red4[l / sg] = vec4<f32>(s, 0.0); }
    workgroupBarrier();
    var a = vec3<f32>(0.0);
    for (var i = lane; i < wg / sg; i += sg) {
        a = chan_merge(a, red4[i].xyz);
    }
    return merge_sg(a);
}

// Pairwise merge of two (count, mean, M2) (Chan et al.).
fn chan_merge(a: vec3<f32>, b: vec3<f32>) -> vec3<f32> {
    let n = a.x + b.x;
    let f = b.x / max(n, 1.0);
    let d = b.y - a.y;
    return vec3<f32>(n, a.y + d * f, a.z + b.z + d * d * a.x * f);
}

// gstats for segment seg (image, group) from its statistics st = (count, mean of the values shifted by x0, M2)
// over len values: per channel (scale = gamma rstd, shift = beta - mean scale, x0, 0); lanes l, l + wg, ..
fn put_gstats(seg: u32, st: vec3<f32>, len: f32, x0: f32, l: u32, wg: u32) {
    let rstd = inverseSqrt(st.z / len + p.eps);
    let cbase = (seg % p.segs_per_item) * p.ch_per_seg;
    let ob = (seg / p.segs_per_item) * p.segs_per_item * p.ch_per_seg + cbase;
    for (var c = l; c < p.ch_per_seg; c += wg) {
        let g = rstd * f32(gamma[cbase + c]);
        gstats[ob + c] = vec4<f32>(g, f32(beta[cbase + c]) - st.y * g, x0, 0.0);
    }
}

// Welford over the vec4s x4[b4 + i] for i = start, start + stride, .. < n4, on the values shifted by x0 (each
// vec4 component its own stream, all with the lane's count k), the 4 streams merged: this lane's (count, mean,
// M2) for `reduce_welford` / `merge_sg`.
fn welford4(b4: u32, n4: u32, x0: f32, start: u32, stride: u32) -> vec3<f32> {
    var k = 0.0;
    var m = vec4<f32>(0.0);
    var q = vec4<f32>(0.0);
    for (var i = start; i < n4; i += stride) {
        let d = vec4<f32>(x4[b4 + i]) - x0;
        k += 1.0;
        let dm = d - m;
        m += dm / k;
        q += dm * (d - m);
    }
    let mm = (m.x + m.y + m.z + m.w) * 0.25;
    let dc = m - mm;
    return vec3<f32>(4.0 * k, mm, q.x + q.y + q.z + q.w + k * dot(dc, dc));
}

@compute @workgroup_size(256)
fn gn4(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>, @builtin(local_invocation_id) lid: vec3<u32>,
       @builtin(subgroup_invocation_id) lane: u32, @builtin(subgroup_size) sg: u32) {
    gn4_impl(wid.y * nwg.x + wid.x, lid.x, lane, sg, 256u);
}

// `gn4` with work groups of 64 (small segments: fewer idle invocations per group on lavapipe).
@compute @workgroup_size(64)
fn gn4_64(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>, @builtin(local_invocation_id) lid: vec3<u32>,
          @builtin(subgroup_invocation_id) lane: u32, @builtin(subgroup_size) sg: u32) {
    gn4_impl(wid.y * nwg.x + wid.x, lid.x, lane, sg, 64u);
}

// One (image, group) segment per work group of `wg` invocations.
fn gn4_impl(seg: u32, l: u32, lane: u32, sg: u32, wg: u32) {
    let base = seg * p.len;
    let b4 = base / 4u;
    let x0 = f32(x4[b4].x);
    let st = reduce_welford_wg(welford4(b4, p.len / 4u, x0, l, wg), l, lane, sg, wg);
    let mean = st.y; // mean of the shifted values
    let rstd = inverseSqrt(st.z / f32(p.len) + p.eps);
    let cbase = (seg % p.segs_per_item) * p.ch_per_seg;
    let ctot = p.segs_per_item * p.ch_per_seg;
    if (p.inner % 4u == 0u) {
        let in4 = p.inner / 4u;
        for (var c = 0u; c < p.ch_per_seg; c++) {
            let g = rstd * f32(gamma[cbase + c]);
            let b = f32(beta[cbase + c]) - mean * g;
            let cb = b4 + c * in4;
            let tb = (seg / p.segs_per_item) * p.inner * ctot + cbase + c;
            for (var j = l; j < in4; j += wg) {
                var v = (vec4<f32>(x4[cb + j]) - x0) * g + b;
                if (p.silu == 1u) { v = v / (1.0 + exp(-v)); }
                if (p.tokens == 1u) {
                    // token layout: the 4 positions of this vec4 are C apart
                    let t = tb + 4u * j * ctot;
                    ys[t] = ST(v.x);
                    ys[t + ctot] = ST(v.y);
                    ys[t + 2u * ctot] = ST(v.z);
                    ys[t + 3u * ctot] = ST(v.w);
                } else {
                    y4[cb + j] = vec4<ST>(v);
                }
            }
        }
    } else {
        for (var c = 0u; c < p.ch_per_seg; c++) {
            let g = rstd * f32(gamma[cbase + c]);
            let b = f32(beta[cbase + c]) - mean * g;
            let cb = base + c * p.inner;
            let tb = (seg / p.segs_per_item) * p.inner * ctot + cbase + c;
            for (var j = l; j < p.inner; j += wg) {
                var v = (f32(xs[cb + j]) - x0) * g + b;
                if (p.silu == 1u) { v = silu(v); }
                ys[select(cb + j, tb + j * ctot, p.tokens == 1u)] = ST(v);
            }
        }
    }
}

// `layer_norm_sg` on vec4s (D % 4 == 0): lanes stride over the row's vec4s; the statistics in one pass, Welford
// per lane on the values shifted by the row's first element (as `gn4`), merged by `merge_sg`. 2 reads + 1 write
// per element instead of 3 + 1. Loop budget: 2 * ceil(D / 4 sg).
@compute @workgroup_size(64)
fn layer_norm_sg4(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
                  @builtin(subgroup_invocation_id) lane: u32, @builtin(subgroup_size) sg: u32,
                  @builtin(local_invocation_index) li: u32) {
    let row = (wid.y * nwg.x + wid.x) * (64u / sg) + li / sg;
    if (row >= p.ch_per_seg) { return; }
    let d4 = p.len / 4u;
    let base = row * d4;
    let x0 = f32(x4[base].x);
    let st = merge_sg(welford4(base, d4, x0, lane, sg));
    let mean = st.y;
    let rstd = inverseSqrt(st.z / f32(p.len) + p.eps);
    for (var i = lane; i < d4; i += sg) {
        y4[base + i] = vec4<ST>(((vec4<f32>(x4[base + i]) - x0) - mean) * rstd * vec4<f32>(gv4[i]) + vec4<f32>(bv4[i]));
    }
}

// group_norm_stats: the statistics of `gn4` only, as a per-(n, c) prologue for a following conv, which reads
// silu((x - x0) scale + shift) (kernels/winograd.wgsl `*_gs`): the normalised tensor is never written, the
// conv's own loads apply it. out (N, C) vec4 f32: (scale = gamma rstd, shift = beta - mean scale, x0, 0) with
// mean the mean of the values shifted by x0 (as in `gn4`, so near-constant groups keep their precision).
// vec4 statistics when len % 4 == 0, scalar otherwise.
@group(0) @binding(3) var<storage, read_write> gstats: array<vec4<f32>>;

@compute @workgroup_size(256)
fn gn_stats(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>, @builtin(local_invocation_id) lid: vec3<u32>,
            @builtin(subgroup_invocation_id) lane: u32, @builtin(subgroup_size) sg: u32) {
    gn_stats_impl(wid.y * nwg.x + wid.x, lid.x, lane, sg, 256u);
}

// `gn_stats` with work groups of 64 (small segments).
@compute @workgroup_size(64)
fn gn_stats_64(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>, @builtin(local_invocation_id) lid: vec3<u32>,
               @builtin(subgroup_invocation_id) lane: u32, @builtin(subgroup_size) sg: u32) {
    gn_stats_impl(wid.y * nwg.x + wid.x, lid.x, lane, sg, 64u);
}

fn gn_stats_impl(seg: u32, l: u32, lane: u32, sg: u32, wg: u32) {
    let base = seg * p.len;
    let x0 = f32(xs[base]);
    var lane_st: vec3<f32>;
    if (p.len % 4u == 0u) {
        lane_st = welford4(base / 4u, p.len / 4u, x0, l, wg);
    } else {
        // scalar Welford (the vec4 one with a single stream)
        var k = 0.0;
        var m = 0.0;
        var q = 0.0;
        for (var i = l; i < p.len; i += wg) {
            let d = f32(xs[base + i]) - x0;
            k += 1.0;
            let dm = d - m;
            m += dm / k;
            q += dm * (d - m);
        }
        lane_st = vec3<f32>(k, m, q);
    }
    put_gstats(seg, reduce_welford_wg(lane_st, l, lane, sg, wg), f32(p.len), x0, l, wg);
}

// Group-norm statistics (as `gn_stats`) from per-slot partials written by the conv that produced x (winograd
// `output6p` with p.stats: one slot per tile pair): parts (N S, C) of (count, mean, M2, -). Here p.len = S
// (slots per image), p.inner = C, p.segs_per_item = G, p.ch_per_seg = C / G; one work group per (n, group).
// The partials are merged with Chan et al.'s update on means shifted by x0 = the group's first partial mean,
// the value the prologue subtracts (as `gn_stats`'s first element).
@group(0) @binding(0) var<storage, read> parts: array<vec4<f32>>;

@compute @workgroup_size(256)
fn gn_stats_parts(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>, @builtin(local_invocation_id) lid: vec3<u32>,
                  @builtin(subgroup_invocation_id) lane: u32, @builtin(subgroup_size) sg: u32) {
    let seg = wid.y * nwg.x + wid.x;
    let l = lid.x;
    let n = seg / p.segs_per_item;
    let cbase = (seg % p.segs_per_item) * p.ch_per_seg;
    let pb = n * p.len * p.inner;
    let x0 = parts[pb + cbase].y;
    var a = vec3<f32>(0.0);
    let total = p.len * p.ch_per_seg;
    for (var i = l; i < total; i += 256u) {
        let b = parts[pb + (i / p.ch_per_seg) * p.inner + cbase + i % p.ch_per_seg];
        a = chan_merge(a, vec3<f32>(b.x, b.y - x0, b.z));
    }
    let st = reduce_welford(a, l, lane, sg);
    put_gstats(seg, st, st.x, x0, l, 256u);
}
