//! Op benchmark cases shared by `b2dr bench ops` and the criterion benches: each case records its dispatch once
//! (random inputs) and is timed by replaying the recording, synchronised (fence wait) before the clock is read.
//! Case names are `<op>_<dtype>_<shape>`.
use std::time::Instant;

use anyhow::Result;
use rand::{Rng, SeedableRng};

use super::{attention, conv2d, matmul, norm, winograd};
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
    /// Fastest replay (on a noisy machine the more stable figure for A/B comparisons).
    pub min_ms: f64,
    pub gflops: f64,
    pub gbs: f64,
    pub iters: usize,
    /// Per-op GPU time of the last replay, summed by label, with the dispatch count, largest first (contexts
    /// created with `profile`).
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub profile: Vec<(String, f64, usize)>,
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

/// matmul MxNxK = 1400 x 1280 x 320 as a Linear layer: x (1400, 320) * W^T, W (1280, 320), + bias.
fn matmul_case(dtype: DType) -> BenchCase {
    let (m, n, k) = (1400usize, 1280usize, 320usize);
    BenchCase {
        name: format!("matmul_{}_{m}x{n}x{k}", dtype.name()),
        flops: 2.0 * (m * n * k) as f64,
        bytes: ((m * k + n * k + m * n) * dtype.size()) as f64,
        build: Box::new(move |ctx| {
            let x = random_tensor(ctx, &[m, k], dtype, 1)?;
            let w = random_tensor(ctx, &[n, k], dtype, 2)?;
            let b = random_tensor(ctx, &[n], dtype, 3)?;
            let y = Tensor::empty(ctx, &[m, n], dtype, "bench-out")?;
            record(ctx, |rec| matmul::linear(rec, &x, &w, Some(&b), &y))
        }),
    }
}

/// conv 3x3, c -> c channels at h x w, pad 1, bias, batch 1; weights packed (and Winograd-transformed for both
/// tile sizes) once beforehand, as the models do at load time. 320 channels at 28 x 50 with `path` Auto is the
/// required case; the implicit-GEMM case (`_implicit`) shows what Winograd gains, `_f4` / `_f6` the two
/// Winograd tile sizes. FLOP counts are the direct conv's in all.
fn conv_case(dtype: DType, path: conv2d::ConvPath, (c, h, w): (usize, usize, usize)) -> BenchCase {
    use conv2d::ConvPath as P;
    let suffix = match path {
        P::Fast => "_implicit",
        P::Winograd => "_f4",
        P::Winograd6 => "_f6",
        _ => "",
    };
    BenchCase {
        name: format!("conv2d_{}_3x3_{c}to{c}_{h}x{w}{suffix}", dtype.name()),
        flops: 2.0 * (c * c * 9 * h * w) as f64,
        bytes: ((2 * c * h * w + c * c * 9) * dtype.size()) as f64,
        build: Box::new(move |ctx| {
            let x = random_tensor(ctx, &[1, c, h, w], dtype, 1)?;
            let wt = random_tensor(ctx, &[c, c, 3, 3], dtype, 2)?;
            let b = random_tensor(ctx, &[c], dtype, 3)?;
            let packed = Tensor::empty(ctx, &[3, 3, c, c], dtype, "packed-w")?;
            record(ctx, |rec| conv2d::pack_weight(rec, &wt, &packed))?.submit_wait()?;
            let wino = |t| {
                Tensor::empty(
                    ctx,
                    &winograd::weight_shape(wt.shape(), t),
                    DType::F32,
                    "wino-w",
                )
            };
            let (wino4, wino6) = (wino(winograd::Tile::F4)?, wino(winograd::Tile::F6)?);
            record(ctx, |rec| {
                winograd::transform_weight(rec, &wt, &wino4)?;
                winograd::transform_weight(rec, &wt, &wino6)
            })?
            .submit_wait()?;
            let y = Tensor::empty(ctx, &[1, c, h, w], dtype, "bench-out")?;
            record(ctx, |rec| {
                conv2d::conv2d_ex(
                    rec,
                    &conv2d::Conv2dArgs {
                        path,
                        packed_w: Some(&packed),
                        wino_w: Some(&wino4),
                        wino_w6: Some(&wino6),
                        ..conv2d::Conv2dArgs::new(&x, &wt, Some(&b), &y, 1, [1; 4])
                    },
                )
            })
        }),
    }
}

/// attention: 1400 queries, `lk` keys, 8 heads of dim 40, batch 1; FLOP = 4 B H Lq Lk d.
fn attention_case(dtype: DType, lk: usize) -> BenchCase {
    let (lq, h, d) = (1400usize, 8usize, 40usize);
    BenchCase {
        name: format!("attention_{}_{lq}x{lk}_h{h}_d{d}", dtype.name()),
        flops: 4.0 * (h * lq * lk * d) as f64,
        bytes: ((2 * lq * h * d + 2 * lk * h * d) * dtype.size()) as f64,
        build: Box::new(move |ctx| {
            let q = random_tensor(ctx, &[1, lq, h * d], dtype, 1)?;
            let k = random_tensor(ctx, &[1, lk, h * d], dtype, 2)?;
            let v = random_tensor(ctx, &[1, lk, h * d], dtype, 3)?;
            let o = Tensor::empty(ctx, &[1, lq, h * d], dtype, "bench-out")?;
            record(ctx, |rec| {
                attention::attention(rec, &q, &k, &v, &o, h, None)
            })
        }),
    }
}

/// Every op benchmark case.
pub fn cases() -> Vec<BenchCase> {
    let mut v = vec![];
    for dtype in [DType::F32, DType::F16] {
        v.push(matmul_case(dtype));
        let sd = (320, 28, 50);
        v.push(conv_case(dtype, conv2d::ConvPath::Auto, sd));
        v.push(conv_case(dtype, conv2d::ConvPath::Fast, sd));
        // the VAE decoder's full-resolution conv, with each Winograd tile size
        for path in [conv2d::ConvPath::Winograd, conv2d::ConvPath::Winograd6] {
            v.push(conv_case(dtype, path, (32, 224, 400)));
        }
        v.push(attention_case(dtype, 1400));
        v.push(attention_case(dtype, 77));
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
    let mut by: std::collections::BTreeMap<String, (f64, usize)> = Default::default();
    for t in rec.timings()? {
        let e = by.entry(t.label).or_default();
        e.0 += t.ms;
        e.1 += 1;
    }
    let mut profile: Vec<(String, f64, usize)> =
        by.into_iter().map(|(l, (ms, n))| (l, ms, n)).collect();
    profile.sort_by(|a, b| b.1.total_cmp(&a.1));
    Ok(BenchResult {
        name: case.name.clone(),
        ms: s * 1e3,
        min_ms: times[0] * 1e3,
        gflops: case.flops / s * 1e-9,
        gbs: case.bytes / s * 1e-9,
        iters: times.len(),
        profile,
    })
}
