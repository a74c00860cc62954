// Sinusoidal timestep embedding (diffusers get_timestep_embedding), always f32.
// t: (B) -> out: (B, dim); half = dim / 2; freq_j = exp(-ln(max_period) * j / (half - shift));
// arg = scale * t * freq_j; out = [sin | cos] or, with flip (SD: flip_sin_to_cos = true), [cos | sin];
// an odd dim gets a trailing zero column.

struct EmbParams { b: u32, dim: u32, flip: u32, shift: f32, max_period: f32, scale: f32 }

@group(0) @binding(0) var<storage, read> t: array<f32>;
@group(0) @binding(1) var<storage, read_write> out: array<f32>;
var<immediate> p: EmbParams;

@compute @workgroup_size(256)
fn timestep(@builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>, @builtin(local_invocation_id) lid: vec3<u32>) {
    let i = flat_index(wid, nwg, lid);
    if (i >= p.b * p.dim) { return; }
    let n = i / p.dim;
    let c = i % p.dim;
    let half_ = p.dim / 2u;
    if (c >= 2u * half_) { out[i] = 0.0; return; }
    let j = c % half_;
    let freq = exp(-log(p.max_period) * f32(j) / (f32(half_) - p.shift));
    let arg = p.scale * t[n] * freq;
    // Cody-Waite reduction of arg to [-pi, pi] so large timesteps (up to 999) keep sin/cos accurate.
    let k = round(arg * 0.15915494309189535);
    let r = (arg - k * 6.28125) - k * 0.0019353071795864769;
    let first_is_sin = p.flip == 0u;
    if ((c < half_) == first_is_sin) { out[i] = sin(r); } else { out[i] = cos(r); }
}
