//! variant f32: alias ST = f32;
//! variant f16: enable f16; alias ST = f16;
// Fallback multi-head attention for head dims the fast kernel does not take (d % 4 != 0, d <= 8), e.g.
// diffusers' tiny test configs (d = 1, 2). q: (B, Lq, H*d), k, v: (B, Lk, H*d) -> out: (B, Lq, H*d).
// One invocation per (b, h, query), lanes = consecutive queries: each key row is uniform across lanes.
// Online softmax in f32 (running max m, sum l, rescaled accumulator). Loop budget: Lk * (2 d + 1)
// back-edges per invocation, checked by the launcher.

struct AttnNaiveParams { b: u32, h: u32, lq: u32, lk: u32, d: u32, scale: f32 }

@group(0) @binding(0) var<storage, read> q: array<ST>;
@group(0) @binding(1) var<storage, read> k: array<ST>;
@group(0) @binding(2) var<storage, read> v: array<ST>;
@group(0) @binding(3) var<storage, read_write> out: array<ST>;
var<immediate> p: AttnNaiveParams;

@compute @workgroup_size(256)
fn main(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>, @builtin(local_invocation_id) lid: vec3<u32>) {
    let i = flat_index(wid, nwg, lid);
    if (i >= p.b * p.h * p.lq) { return; }
    let qi = i % p.lq;
    let hh = (i / p.lq) % p.h;
    let bb = i / (p.lq * p.h);
    let width = p.h * p.d;
    let qbase = (bb * p.lq + qi) * width + hh * p.d;
    var qv: array<f32, 8>;
    var acc: array<f32, 8>;
    for (var c = 0u; c < p.d; c++) { qv[c] = f32(q[qbase + c]) * p.scale; acc[c] = 0.0; }
    var m = -1e30;
    var l = 0.0;
    for (var j = 0u; j < p.lk; j++) {
        let kb = (bb * p.lk + j) * width + hh * p.d;
        var s = 0.0;
        for (var c = 0u; c < p.d; c++) { s += qv[c] * f32(k[kb + c]); }
        let mn = max(m, s);
        let corr = exp(m - mn);
        let e = exp(s - mn);
        l = l * corr + e;
        for (var c = 0u; c < p.d; c++) { acc[c] = acc[c] * corr + e * f32(v[kb + c]); }
        m = mn;
    }
    for (var c = 0u; c < p.d; c++) { out[qbase + c] = ST(acc[c] / l); }
}
