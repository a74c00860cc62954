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
                    let c0 = out4(v0);
                    let c1 = out4(v1);
                    let c2 = out4(v2);
                    let c3 = out4(v3);
                    y4[e] = vec4<ST>(c0);
                    y4[e + ps] = vec4<ST>(c1);
                    y4[e + 2u * ps] = vec4<ST>(c2);
                    y4[e + 3u * ps] = vec4<ST>(c3);
                    if (p.stats == 1u) {
                        // the values as stored (`as_stored4`), shifted by each channel's first value
                        let f0 = as_stored4(c0);
                        let f1 = as_stored4(c1);
                        let f2 = as_stored4(c2);
                        let f3 = as_stored4(c3);
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

// The f32 value that storing v (|v| <= 65504, as `out4` leaves it) as ST keeps: v itself in f32; in f16 v rounded
// to the nearest half (ties to even, subnormal halves included), computed with f32 operations that are exact
// (scalings by powers of two, roundEven). Not vec4<f32>(vec4<f16>(v)): Mesa 25's lavapipe drops that round trip
// (f32(f16(x)) = x: `b2dr info`'s f16 probe, kernels/cast.wgsl), and statistics of the unrounded values miss
// the stored tensor's mean by ~ulp / sqrt(count) (group norm NMSE 1e-9 instead of 1e-15 on one-channel groups).
fn as_stored4(v: vec4<f32>) -> vec4<f32> {
    if (!IS_F16) { return v; }
    // binary exponent of |v| (v in [2^ex, 2^(ex + 1))); the half's spacing there is 2^(ex - 10), at least 2^-24
    let ex = vec4<i32>((bitcast<vec4<u32>>(v) >> vec4<u32>(23u)) & vec4<u32>(0xffu)) - vec4<i32>(127);
    let k = max(ex - vec4<i32>(10), vec4<i32>(-24));
    // 2^-k and 2^k built from their exponent bits (k in [-24, 118]: both normal f32)
    let down = bitcast<vec4<f32>>(vec4<u32>(vec4<i32>(127) - k) << vec4<u32>(23u));
    let up = bitcast<vec4<f32>>(vec4<u32>(vec4<i32>(127) + k) << vec4<u32>(23u));
    return round(v * down) * up;
}
