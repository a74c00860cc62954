//! Op benchmark cases shared by `b2dr bench ops` and the criterion benches: each case records its dispatch once
//! (random inputs) and is timed by replaying the recording, synchronised (fence wait) before the clock is read.
//! Case names are `<op>_<dtype>_<shape>`.
use std::time::Instant;

use anyhow::Result;
use rand::{Rng, SeedableRng};

use super::norm;
use crate::tensor::{DType, Tensor};
use crate::vk::{Context, Recording};

/// Builds a case's recording on a context.
pub type BuildFn = Box<dyn Fn(&Context) -> Result<Recording>>;

/// A benchmark case: `flops` (2 x MAC, or a nominal count for memory-bound ops) and `bytes` moved.
pub struct BenchCase {
    pub name: String,
    pub flops: f64,
    pub bytes: f64,
    pub build: BuildFn,
}

/// Timing of one case: median over the timed replays.
#[derive(Clone, Debug, serde::Serialize)]
pub struct BenchResult {
    pub name: String,
    pub ms: f64,
    pub gflops: f64,
    pub gbs: f64,
    pub iters: usize,
    /// Per-op GPU time of the last replay, summed by label, largest first (contexts created with `profile`).
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub profile: Vec<(String, f64)>,
}

pub(crate) fn random_tensor(
    ctx: &Context,
    shape: &[usize],
    dtype: DType,
    seed: u64,
) -> Result<Tensor> {
    let n: usize = shape.iter().product();
    let mut r = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
    let v: Vec<f32> = (0..n).map(|_| r.gen_range(-1.0f32..1.0)).collect();
    Tensor::from_f32(ctx, shape, dtype, &v, "bench-input")
}

/// Records `f` into a recording.
pub(crate) fn record(
    ctx: &Context,
    f: impl FnOnce(&mut crate::vk::Recorder) -> Result<()>,
) -> Result<Recording> {
    let mut rec = ctx.recorder()?;
    f(&mut rec)?;
    rec.finish()
}

fn group_norm_case(dtype: DType) -> BenchCase {
    let (c, h, w) = (320usize, 28usize, 50usize);
    let n = (c * h * w) as f64;
    BenchCase {
        name: format!("group_norm_{}_320c_28x50_g32", dtype.name()),
        // two reduction passes + normalise/affine/SiLU: about 10 flops per element
        flops: 10.0 * n,
        bytes: 2.0 * n * dtype.size() as f64,
        build: Box::new(move |ctx| {
            let x = random_tensor(ctx, &[1, c, h, w], dtype, 1)?;
            let g = random_tensor(ctx, &[c], dtype, 2)?;
            let b = random_tensor(ctx, &[c], dtype, 3)?;
            let y = Tensor::empty(ctx, &[1, c, h, w], dtype, "bench-out")?;
            record(ctx, |rec| {
                norm::group_norm(rec, &x, 32, &g, &b, 1e-5, true, &y)
            })
        }),
    }
}

/// Every op benchmark case.
pub fn cases() -> Vec<BenchCase> {
    let mut v = vec![];
    for dtype in [DType::F32, DType::F16] {
        v.push(group_norm_case(dtype));
    }
    v
}

/// Runs one case: `warmup` untimed replays, then replays until `min_time_s` has passed (at least `min_iters`).
pub fn run_case(
    ctx: &Context,
    case: &BenchCase,
    warmup: usize,
    min_iters: usize,
    min_time_s: f64,
) -> Result<BenchResult> {
    let rec = (case.build)(ctx)?;
    for _ in 0..warmup {
        rec.submit_wait()?;
    }
    let mut times = vec![];
    let start = Instant::now();
    while times.len() < min_iters || start.elapsed().as_secs_f64() < min_time_s {
        let t = Instant::now();
        rec.submit_wait()?;
        times.push(t.elapsed().as_secs_f64());
        if times.len() >= 1000 {
            break;
        }
    }
    times.sort_by(|a, b| a.total_cmp(b));
    let s = times[times.len() / 2];
    let mut by: std::collections::BTreeMap<String, f64> = Default::default();
    for t in rec.timings()? {
        *by.entry(t.label).or_default() += t.ms;
    }
    let mut profile: Vec<(String, f64)> = by.into_iter().collect();
    profile.sort_by(|a, b| b.1.total_cmp(&a.1));
    Ok(BenchResult {
        name: case.name.clone(),
        ms: s * 1e3,
        gflops: case.flops / s * 1e-9,
        gbs: case.bytes / s * 1e-9,
        iters: times.len(),
        profile,
    })
}
