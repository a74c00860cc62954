// ---- F(4x4, 3x3): transforms, scalar entries, vec4 forms (the matrices: 00_common.wgsl's header).

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
