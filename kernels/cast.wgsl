enable f16;
// dtype conversion between f32 and f16 storage. x: (n) -> y: (n). f32 values beyond the f16 range become +-inf
// in f16 (IEEE conversion); the launcher documents this.

struct CastParams { n: u32 }

@group(0) @binding(0) var<storage, read> x32: array<f32>;
@group(0) @binding(1) var<storage, read_write> y16: array<f16>;
@group(0) @binding(0) var<storage, read> x16: array<f16>;
@group(0) @binding(1) var<storage, read_write> y32: array<f32>;
var<immediate> p: CastParams;

@compute @workgroup_size(256)
fn to_f16(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>, @builtin(local_invocation_id) lid: vec3<u32>) {
    let i = flat_index(wid, nwg, lid);
    if (i >= p.n) { return; }
    y16[i] = f16(x32[i]);
}

@compute @workgroup_size(256)
fn to_f32(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>, @builtin(local_invocation_id) lid: vec3<u32>) {
    let i = flat_index(wid, nwg, lid);
    if (i >= p.n) { return; }
    y32[i] = f32(x16[i]);
}

// f16_probe: does the driver round every f16 operation to f16 (IEEE half arithmetic, in hardware or emulated
// op by op), or evaluate f16 expressions in f32 and round only at the end? One invocation; x16 = (2048, 1, ...)
// from the host (not constants, so the compiler cannot fold them). y32[0] = (x0 + x1) + x1 in f16: 2048 when
// each add rounds to f16 (2049 is not a half: ties to even give 2048, twice), 2050 when the intermediate 2049
// is kept in f32. y32[1] = x0 + x1 in f16 (2048 either way: a check that the probe ran). y32[2] = f32(f16(x0 +
// 1.5)) with the sum in f32 (2049.5, not a half): 2050 when the f32 -> f16 conversion rounds to nearest even,
// 2048 when it truncates, 2049.5 when the compiler drops the f16 -> f32 round trip.
@compute @workgroup_size(1)
fn f16_probe() {
    if (p.n < 2u) { return; }
    let a = x16[0];
    let b = x16[1];
    let s = a + b;
    y32[0] = f32(s + b);
    y32[1] = f32(s);
    y32[2] = f32(f16(f32(a) + 1.5));
}
