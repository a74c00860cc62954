// ---- common.wgsl: helpers appended to every kernel by build.rs ----

// Linear invocation index of a 1D-folded grid: groups run (x, y) with x <= 65535; wg = 256 invocations.
fn flat_index(wid: vec3<u32>, nwg: vec3<u32>, lid: vec3<u32>) -> u32 {
    return (wid.y * nwg.x + wid.x) * 256u + lid.x;
}

// Texel coordinates of vec4 i of a buffer read through its texel view (src/vk/image.rs: 1024 texels a row).
fn texel_xy(i: u32) -> vec2<i32> {
    return vec2<i32>(i32(i & 1023u), i32(i >> 10u));
}

// erf(x), Abramowitz & Stegun 7.1.26 refined: max abs error 1.5e-7.
fn erf_f32(x: f32) -> f32 {
    let s = sign(x);
    let a = abs(x);
    let t = 1.0 / (1.0 + 0.3275911 * a);
    let y = 1.0 - (((((1.061405429 * t - 1.453152027) * t) + 1.421413741) * t - 0.284496736) * t + 0.254829592) * t * exp(-a * a);
    return s * y;
}

fn gelu_erf(x: f32) -> f32 {
    return 0.5 * x * (1.0 + erf_f32(x * 0.70710678118654752));
}

fn silu(x: f32) -> f32 {
    return x / (1.0 + exp(-x));
}

// Two f16 (low half first) from their packed bits, exactly (denormals included unless the device flushes them;
// Inf/NaN kept). Arithmetic instead of bitcast<vec2<f16>>(u32), which gave wrong values here (naga 30 SPIR-V
// on lavapipe 22.3; not investigated further).
fn f16x2(u: u32) -> vec2<f32> {
    let h = vec2<u32>(u & 0xffffu, u >> 16u);
    let e = h & vec2<u32>(0x7c00u);
    let mag = bitcast<vec2<f32>>((h & vec2<u32>(0x7fffu)) << vec2<u32>(13u)) * 5.192296858534828e33;
    let special = bitcast<vec2<f32>>(vec2<u32>(0x7f800000u) | ((h & vec2<u32>(0x3ffu)) << vec2<u32>(13u)));
    let v = select(mag, special, e == vec2<u32>(0x7c00u));
    return select(v, -v, (h & vec2<u32>(0x8000u)) != vec2<u32>(0u));
}
