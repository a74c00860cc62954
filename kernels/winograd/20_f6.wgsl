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
