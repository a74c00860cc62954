//! variant f32: alias ST = f32;
//! variant f16: enable f16; alias ST = f16;
// Elementwise ops. Storage type ST, arithmetic in f32. One element per invocation: addresses are contiguous
// across neighbouring invocations, which llvmpipe turns into vector loads.

struct UnaryParams { n: u32, op: u32 }
struct BinaryParams {
    op: u32,
    n: u32,
    // output shape (d0, d1, d2, d3), right-aligned; element strides of a and b (0 where broadcast)
    d1: u32, d2: u32, d3: u32,
    sa0: u32, sa1: u32, sa2: u32, sa3: u32,
    sb0: u32, sb1: u32, sb2: u32, sb3: u32,
}
struct ScaleAddParams { n: u32, alpha: f32, beta: f32 }
struct GegluParams { rows: u32, d: u32 }
struct ConcatParams { n: u32, c1: u32, c2: u32, hw: u32 }
struct TransposeParams { n: u32, r: u32, c: u32 }
struct LinCombParams { n: u32, terms: u32, o_out: u32, o0: u32, o1: u32, o2: u32, o3: u32, c0: f32, c1: f32, c2: f32, c3: f32 }

@group(0) @binding(0) var<storage, read> a: array<ST>;
@group(0) @binding(1) var<storage, read> b: array<ST>;
@group(0) @binding(2) var<storage, read_write> out: array<ST>;
@group(0) @binding(1) var<storage, read_write> out1: array<ST>;
@group(0) @binding(2) var<storage, read> t2: array<ST>;
@group(0) @binding(3) var<storage, read> t3: array<ST>;
@group(0) @binding(4) var<storage, read_write> out4: array<ST>;
// vec4 views for the `*4` kernels: on lavapipe each storage access is a per-lane loop whatever its width, so
// 4 elements per access is ~4x fewer loops
@group(0) @binding(0) var<storage, read> av4: array<vec4<ST>>;
@group(0) @binding(1) var<storage, read> bv4: array<vec4<ST>>;
@group(0) @binding(2) var<storage, read_write> ov4: array<vec4<ST>>;
@group(0) @binding(1) var<storage, read_write> o1v4: array<vec4<ST>>;

var<immediate> up: UnaryParams;
var<immediate> bp: BinaryParams;
var<immediate> sp: ScaleAddParams;
var<immediate> gp: GegluParams;
var<immediate> cp: ConcatParams;
var<immediate> tp: TransposeParams;
var<immediate> lp: LinCombParams;

// x: (n) -> out1: (n); op 0 = silu, 1 = gelu(erf), 2 = relu, 3 = clamp(x / 2 + 0.5, 0, 1) (decoded image -> [0, 1])
@compute @workgroup_size(256)
fn unary(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>, @builtin(local_invocation_id) lid: vec3<u32>) {
    let i = flat_index(wid, nwg, lid);
    if (i >= up.n) { return; }
    let x = f32(a[i]);
    var y: f32;
    if (up.op == 0u) { y = silu(x); } else if (up.op == 1u) { y = gelu_erf(x); } else if (up.op == 2u) { y = max(x, 0.0); } else { y = clamp(x * 0.5 + 0.5, 0.0, 1.0); }
    out1[i] = ST(y);
}

// `unary` on vec4s: x: (n), n % 4 == 0; up.n counts vec4s
@compute @workgroup_size(256)
fn unary4(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>, @builtin(local_invocation_id) lid: vec3<u32>) {
    let i = flat_index(wid, nwg, lid);
    if (i >= up.n) { return; }
    let x = vec4<f32>(av4[i]);
    var y: vec4<f32>;
    if (up.op == 0u) { y = x / (1.0 + exp(-x)); } else if (up.op == 1u) { y = vec4<f32>(gelu_erf(x.x), gelu_erf(x.y), gelu_erf(x.z), gelu_erf(x.w)); } else if (up.op == 2u) { y = max(x, vec4<f32>(0.0)); } else { y = clamp(x * 0.5 + 0.5, vec4<f32>(0.0), vec4<f32>(1.0)); }
    o1v4[i] = vec4<ST>(y);
}

// Element offsets in a and b of output element i of (d0, d1, d2, d3) (broadcast strides from the launcher).
fn operand_offsets(i: u32) -> vec2<u32> {
    let i3 = i % bp.d3;
    let r3 = i / bp.d3;
    let i2 = r3 % bp.d2;
    let r2 = r3 / bp.d2;
    let i1 = r2 % bp.d1;
    let i0 = r2 / bp.d1;
    return vec2<u32>(i0 * bp.sa0 + i1 * bp.sa1 + i2 * bp.sa2 + i3 * bp.sa3,
                     i0 * bp.sb0 + i1 * bp.sb1 + i2 * bp.sb2 + i3 * bp.sb3);
}

// `binary` on 4 consecutive elements of the last dimension (d3 % 4 == 0); bp.n counts vec4s. An operand with
// stride 1 on d3 (its other strides multiples of 4) loads a vec4, one with stride 0 the vec4 holding its
// element (buffers are allocated in whole 16-byte units, so that vec4 is inside the allocation).
@compute @workgroup_size(256)
fn binary4(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>, @builtin(local_invocation_id) lid: vec3<u32>) {
    let q = flat_index(wid, nwg, lid);
    if (q >= bp.n) { return; }
    let o = operand_offsets(4u * q);
    let ia = o.x;
    let ib = o.y;
    var x: vec4<f32>;
    if (bp.sa3 == 1u) { x = vec4<f32>(av4[ia / 4u]); } else { x = vec4<f32>(f32(av4[ia / 4u][ia % 4u])); }
    var y: vec4<f32>;
    if (bp.sb3 == 1u) { y = vec4<f32>(bv4[ib / 4u]); } else { y = vec4<f32>(f32(bv4[ib / 4u][ib % 4u])); }
    var z: vec4<f32>;
    if (bp.op == 0u) { z = x + y; } else { z = x * y; }
    ov4[q] = vec4<ST>(z);
}

// a: broadcast to out shape, b: broadcast to out shape -> out: (d0, d1, d2, d3); op 0 = add, 1 = mul
@compute @workgroup_size(256)
fn binary(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>, @builtin(local_invocation_id) lid: vec3<u32>) {
    let i = flat_index(wid, nwg, lid);
    if (i >= bp.n) { return; }
    let o = operand_offsets(i);
    let x = f32(a[o.x]);
    let y = f32(b[o.y]);
    var z: f32;
    if (bp.op == 0u) { z = x + y; } else { z = x * y; }
    out[i] = ST(z);
}

// out = alpha * a + beta * b, all (n)
@compute @workgroup_size(256)
fn scale_add(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>, @builtin(local_invocation_id) lid: vec3<u32>) {
    let i = flat_index(wid, nwg, lid);
    if (i >= sp.n) { return; }
    out[i] = ST(sp.alpha * f32(a[i]) + sp.beta * f32(b[i]));
}

// a: (rows, 2d) = [value | gate] -> out1: (rows, d) = value * gelu(gate)   (diffusers GEGLU)
@compute @workgroup_size(256)
fn geglu(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>, @builtin(local_invocation_id) lid: vec3<u32>) {
    let i = flat_index(wid, nwg, lid);
    if (i >= gp.rows * gp.d) { return; }
    let r = i / gp.d;
    let c = i % gp.d;
    let v = f32(a[r * 2u * gp.d + c]);
    let g = f32(a[r * 2u * gp.d + gp.d + c]);
    out1[i] = ST(v * gelu_erf(g));
}

// `geglu` on vec4s (d % 4 == 0): invocation i -> row i / (d / 4), chunk i % (d / 4)
@compute @workgroup_size(256)
fn geglu4(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>, @builtin(local_invocation_id) lid: vec3<u32>) {
    let i = flat_index(wid, nwg, lid);
    let d4 = gp.d / 4u;
    if (i >= gp.rows * d4) { return; }
    let r = i / d4;
    let c = i % d4;
    let v = vec4<f32>(av4[r * 2u * d4 + c]);
    let g = vec4<f32>(av4[r * 2u * d4 + d4 + c]);
    o1v4[i] = vec4<ST>(v * vec4<f32>(gelu_erf(g.x), gelu_erf(g.y), gelu_erf(g.z), gelu_erf(g.w)));
}

// a: (N, c1, hw), b: (N, c2, hw) -> out: (N, c1 + c2, hw)
@compute @workgroup_size(256)
fn concat(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>, @builtin(local_invocation_id) lid: vec3<u32>) {
    let i = flat_index(wid, nwg, lid);
    if (i >= cp.n) { return; }
    let c = cp.c1 + cp.c2;
    let p = i % cp.hw;
    let ch = (i / cp.hw) % c;
    let nb = i / (cp.hw * c);
    if (ch < cp.c1) {
        out[i] = a[(nb * cp.c1 + ch) * cp.hw + p];
    } else {
        out[i] = b[(nb * cp.c2 + ch - cp.c1) * cp.hw + p];
    }
}

// a: (B, R, C) -> out1: (B, C, R). One output element per invocation: writes contiguous, reads strided.
@compute @workgroup_size(256)
fn transpose(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>, @builtin(local_invocation_id) lid: vec3<u32>) {
    let i = flat_index(wid, nwg, lid);
    if (i >= tp.n) { return; }
    let r = i % tp.r;
    let c = (i / tp.r) % tp.c;
    let b = i / (tp.r * tp.c);
    out1[i] = a[(b * tp.r + r) * tp.c + c];
}

// out4[o_out + i] = sum_{k < terms} c_k * t_k[o_k + i], i < n, with t0 = a, t1 = b (the sampler's linear
// combinations; element offsets select the uncond / cond halves of a guided batch). Unused terms must still
// be bound (any buffer) and have c = 0. out may alias an input element-for-element.
@compute @workgroup_size(256)
fn lincomb(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>, @builtin(local_invocation_id) lid: vec3<u32>) {
    let i = flat_index(wid, nwg, lid);
    if (i >= lp.n) { return; }
    var acc = lp.c0 * f32(a[lp.o0 + i]);
    if (lp.terms > 1u) { acc += lp.c1 * f32(b[lp.o1 + i]); }
    if (lp.terms > 2u) { acc += lp.c2 * f32(t2[lp.o2 + i]); }
    if (lp.terms > 3u) { acc += lp.c3 * f32(t3[lp.o3 + i]); }
    out4[lp.o_out + i] = ST(acc);
}
