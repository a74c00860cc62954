//! variant f32: alias ST = f32; const IS_F16: bool = false; fn note_overflow() {}
//! variant f16: enable f16; alias ST = f16; const IS_F16: bool = true; fn note_overflow() {}
//! variant f16chk: enable f16; alias ST = f16; const IS_F16: bool = true; @group(0) @binding(5) var<storage, read_write> flag: array<u32>; fn note_overflow() { flag[0] = 0x3f800000u; }
// Direct batched matmul: one output per invocation, plain k loop. The fallback for devices without the
// lane-shuffle operations the tiled kernel (matmul.wgsl) needs, and the oracle the tests compare it with.
// Loop budget (lavapipe: 65535 back-edges per invocation): the k loop is unrolled by 4 (K = 23040 -> 5760).
// Same parameters, bindings and f16 overflow policy as matmul.wgsl.

struct MatmulParams { m: u32, n: u32, k: u32, sa: u32, sb: u32, bias_mode: u32, batch: u32, res: u32 }

@group(0) @binding(0) var<storage, read> a: array<ST>;
@group(0) @binding(1) var<storage, read> b: array<ST>;
@group(0) @binding(2) var<storage, read> bias: array<ST>;
@group(0) @binding(3) var<storage, read_write> c: array<ST>;
@group(0) @binding(4) var<storage, read> res: array<ST>;
var<immediate> p: MatmulParams;

const F16_MAX: f32 = 65504.0;

fn out_val(x: f32) -> ST {
    if (IS_F16 && abs(x) > F16_MAX) {
        note_overflow();
        return ST(clamp(x, -F16_MAX, F16_MAX));
    }
    return ST(x);
}

fn finish(i: u32, m: u32, n: u32, s: f32) {
    var v = s;
    if (p.bias_mode == 1u) { v += f32(bias[n]); }
    if (p.bias_mode == 2u) { v += f32(bias[m]); }
    if (p.res == 1u) { v += f32(res[i]); }
    c[i] = out_val(v);
}

// A: (B?, M, K), B: (B?, K, N) -> C: (B, M, N); flat grid over B M N.
@compute @workgroup_size(256)
fn nn(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>, @builtin(local_invocation_id) lid: vec3<u32>) {
    let i = flat_index(wid, nwg, lid);
    let mn = p.m * p.n;
    let bt = i / mn;
    let m = (i % mn) / p.n;
    let n = i % p.n;
    if (bt >= p.batch) { return; }
    let ao = bt * p.sa + m * p.k;
    let bo = bt * p.sb + n;
    var s = 0.0;
    var k = 0u;
    for (; k + 4u <= p.k; k += 4u) {
        s += f32(a[ao + k]) * f32(b[bo + k * p.n]) + f32(a[ao + k + 1u]) * f32(b[bo + (k + 1u) * p.n])
           + f32(a[ao + k + 2u]) * f32(b[bo + (k + 2u) * p.n]) + f32(a[ao + k + 3u]) * f32(b[bo + (k + 3u) * p.n]);
    }
    for (; k < p.k; k++) { s += f32(a[ao + k]) * f32(b[bo + k * p.n]); }
    finish(i, m, n, s);
}

// A: (B?, M, K), W: (B?, N, K) -> C = A W^T: (B, M, N); flat grid over B M N.
@compute @workgroup_size(256)
fn nt(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>, @builtin(local_invocation_id) lid: vec3<u32>) {
    let i = flat_index(wid, nwg, lid);
    let mn = p.m * p.n;
    let bt = i / mn;
    let m = (i % mn) / p.n;
    let n = i % p.n;
    if (bt >= p.batch) { return; }
    let ao = bt * p.sa + m * p.k;
    let bo = bt * p.sb + n * p.k;
    var s = 0.0;
    var k = 0u;
    for (; k + 4u <= p.k; k += 4u) {
        s += f32(a[ao + k]) * f32(b[bo + k]) + f32(a[ao + k + 1u]) * f32(b[bo + k + 1u])
           + f32(a[ao + k + 2u]) * f32(b[bo + k + 2u]) + f32(a[ao + k + 3u]) * f32(b[bo + k + 3u]);
    }
    for (; k < p.k; k++) { s += f32(a[ao + k]) * f32(b[bo + k]); }
    finish(i, m, n, s);
}
