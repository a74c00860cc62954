//! variant f32: alias ST = f32;
//! variant f16: enable f16; alias ST = f16;
// Softmax of scale * x over the last dimension. Storage type ST, all arithmetic in f32.
//
// One work group of 8 invocations (one lavapipe subgroup) per row; lane l owns columns l, l + 8, l + 16, ...
// so the 8 lanes read 8 contiguous values per step. Pass 1 keeps a per-lane online (max, sum) pair, rescaling the
// sum whenever the max grows; the lanes are then combined with subgroupMax / subgroupAdd. Pass 2 writes
// exp(x - max) / sum. Loop budget (lavapipe: 65535 back-edges per invocation): 2 * ceil(n / 8) iterations,
// the launcher caps n accordingly.
//
// On devices whose subgroups are wider than 8 the work group of 8 is still one subgroup (lanes 0..7).

struct SoftmaxParams { rows: u32, n: u32, scale: f32 }

@group(0) @binding(0) var<storage, read> x: array<ST>;
@group(0) @binding(1) var<storage, read_write> y: array<ST>;

var<immediate> p: SoftmaxParams;

const NEG_BIG: f32 = -3.0e38;

// x: (rows, n) -> y: (rows, n); grid: rows work groups folded into (x, y) with x <= 65535
@compute @workgroup_size(8)
fn main(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
        @builtin(subgroup_invocation_id) lane: u32) {
    let row = wid.y * nwg.x + wid.x;
    if (row >= p.rows) { return; }
    let base = row * p.n;
    var m = NEG_BIG;
    var s = 0.0;
    // Two columns per iteration halves the loop count; the second is masked by a select, not a branch.
    var j = lane;
    loop {
        if (j >= p.n) { break; }
        let a = p.scale * f32(x[base + j]);
        let j2 = j + 8u;
        let has2 = j2 < p.n;
        let b = select(NEG_BIG, p.scale * f32(x[base + min(j2, p.n - 1u)]), has2);
        let mn = max(m, max(a, b));
        s = s * exp(m - mn) + exp(a - mn) + select(0.0, exp(b - mn), has2);
        m = mn;
        j += 16u;
    }
    let mx = subgroupMax(m);
    let total = subgroupAdd(s * exp(m - mx));
    let inv = 1.0 / total;
    j = lane;
    loop {
        if (j >= p.n) { break; }
        y[base + j] = ST(exp(p.scale * f32(x[base + j]) - mx) * inv);
        j += 8u;
    }
}
