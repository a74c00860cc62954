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
