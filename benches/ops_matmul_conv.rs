//! matmul / conv2d throughput on the default Vulkan device (lavapipe in CI), printed as GFLOP/s.
//!
//! Cases are named `<op>_<dtype>_<shape>`; FLOP = 2 x MAC. Each sample submits a pre-recorded command buffer
//! and waits on its fence (`submit_wait`) before the clock is read, so GPU work is fully counted.
//! - `matmul_<dt>_1400x1280x320`: M x N x K = 1400 x 1280 x 320 as PyTorch Linear (x (1400, 320) times
//!   W^T, W (1280, 320), + bias): SD1.5's feed-forward up-projection at a 28x50 latent (1400 tokens).
//! - `matmul_<dt>_1400x1280x320_nn`: the same with B given as (K, N).
//! - `conv2d_<dt>_3x3_320to320_28x50`: batch 1, 320 -> 320 channels, 3x3, stride 1, pad 1, + bias.
//! - `conv2d_<dt>_1x1_320to320_28x50`: the 1x1 conv (runs as a GEMM).
//! - `conv2d_f32_3x3_64to64_28x50[_direct]`: fast path vs the direct (fallback) kernel on a smaller conv.
//!
//! lavapipe's thread count is `LP_NUM_THREADS` (default: CPU count); try `LP_NUM_THREADS=4 cargo bench ...`.
//! `B2DR_BENCH_QUICK=1` skips criterion's statistics and prints only the GFLOP/s lines.
use std::time::{Duration, Instant};

use b2dr::ops::conv2d::{self, Conv2dArgs, ConvPath};
use b2dr::ops::matmul::{self, MatmulArgs};
use b2dr::tensor::{DType, Tensor};
use b2dr::vk::{Context, ContextOptions, Recording};
use criterion::{criterion_group, criterion_main, Criterion};

fn tensor(ctx: &Context, shape: &[usize], dtype: DType) -> Tensor {
    let n: usize = shape.iter().product();
    let v: Vec<f32> = (0..n)
        .map(|i| ((i * 7919) % 1000) as f32 / 1000.0 - 0.5)
        .collect();
    Tensor::from_f32(ctx, shape, dtype, &v, "bench").expect("upload")
}

struct Bench {
    name: String,
    flop: f64,
    rec: Recording,
    _keep: Vec<Tensor>,
}

fn matmul_case(ctx: &Context, dt: DType, m: usize, n: usize, k: usize, trans: bool) -> Bench {
    let a = tensor(ctx, &[m, k], dt);
    let bshape = if trans { [n, k] } else { [k, n] };
    let b = tensor(ctx, &bshape, dt);
    let bias = tensor(ctx, &[n], dt);
    let out = tensor(ctx, &[m, n], dt);
    let mut rec = ctx.recorder().expect("recorder");
    matmul::matmul_ex(
        &mut rec,
        &MatmulArgs {
            bias: Some(&bias),
            transpose_b: trans,
            ..MatmulArgs::new(&a, &b, &out)
        },
    )
    .expect("matmul");
    Bench {
        name: format!(
            "matmul_{}_{m}x{n}x{k}{}",
            dt.name(),
            if trans { "" } else { "_nn" }
        ),
        flop: 2.0 * (m * n * k) as f64,
        rec: rec.finish().expect("finish"),
        _keep: vec![a, b, bias, out],
    }
}

fn conv_case(
    ctx: &Context,
    dt: DType,
    k: usize,
    c: usize,
    h: usize,
    w: usize,
    path: ConvPath,
) -> Bench {
    let x = tensor(ctx, &[1, c, h, w], dt);
    let wt = tensor(ctx, &[c, c, k, k], dt);
    let bias = tensor(ctx, &[c], dt);
    let p = k / 2;
    let out = tensor(ctx, &[1, c, h, w], dt);
    let mut rec = ctx.recorder().expect("recorder");
    conv2d::conv2d_ex(
        &mut rec,
        &Conv2dArgs {
            path,
            ..Conv2dArgs::new(&x, &wt, Some(&bias), &out, 1, [p; 4])
        },
    )
    .expect("conv2d");
    Bench {
        name: format!(
            "conv2d_{}_{k}x{k}_{c}to{c}_{h}x{w}{}",
            dt.name(),
            if path == ConvPath::Direct {
                "_direct"
            } else {
                ""
            }
        ),
        flop: 2.0 * (c * c * k * k * h * w) as f64,
        rec: rec.finish().expect("finish"),
        _keep: vec![x, wt, bias, out],
    }
}

fn cases(ctx: &Context) -> Vec<Bench> {
    let mut v = vec![];
    for dt in [DType::F32, DType::F16] {
        if dt == DType::F16 && !ctx.info().f16 {
            continue;
        }
        v.push(matmul_case(ctx, dt, 1400, 1280, 320, true));
        v.push(matmul_case(ctx, dt, 1400, 1280, 320, false));
        v.push(conv_case(ctx, dt, 3, 320, 28, 50, ConvPath::Auto));
        v.push(conv_case(ctx, dt, 1, 320, 28, 50, ConvPath::Auto));
    }
    v.push(conv_case(ctx, DType::F32, 3, 64, 28, 50, ConvPath::Auto));
    v.push(conv_case(ctx, DType::F32, 3, 64, 28, 50, ConvPath::Direct));
    v
}

/// CPU seconds (user + system, all threads) this process has used, from /proc (Linux; 0 elsewhere).
fn cpu_secs() -> f64 {
    let stat = std::fs::read_to_string("/proc/self/stat").unwrap_or_default();
    let rest = stat.rsplit(')').next().unwrap_or("");
    let f: Vec<f64> = rest
        .split_whitespace()
        .map(|x| x.parse().unwrap_or(0.0))
        .collect();
    // fields 14 and 15 of stat (utime, stime) are 11 and 12 after the command name; 100 ticks/s on Linux
    f.get(11)
        .zip(f.get(12))
        .map_or(0.0, |(u, s)| (u + s) / 100.0)
}

/// Median seconds of `n` synchronised runs.
fn median_secs(b: &Bench, n: usize) -> f64 {
    let mut t: Vec<f64> = (0..n)
        .map(|_| {
            let s = Instant::now();
            b.rec.submit_wait().expect("submit");
            s.elapsed().as_secs_f64()
        })
        .collect();
    t.sort_by(f64::total_cmp);
    t[n / 2]
}

fn bench(c: &mut Criterion) {
    let ctx = match Context::new(&ContextOptions::default()) {
        Ok(c) => c,
        Err(e) => {
            eprintln!("SKIP: no Vulkan device ({e:#})");
            return;
        }
    };
    let threads = std::env::var("LP_NUM_THREADS").unwrap_or_else(|_| "default".into());
    eprintln!(
        "device: {} ({}), LP_NUM_THREADS={threads}",
        ctx.info().name,
        ctx.info().kind
    );
    let filter: Vec<String> = std::env::args()
        .skip(1)
        .filter(|a| !a.starts_with('-'))
        .collect();
    let quick = std::env::var("B2DR_BENCH_QUICK").is_ok();
    for b in cases(&ctx) {
        if !filter.is_empty() && !filter.iter().any(|f| b.name.contains(f.as_str())) {
            continue;
        }
        b.rec.submit_wait().expect("warm-up");
        let c0 = cpu_secs();
        let s = median_secs(&b, 7);
        let cpu = (cpu_secs() - c0) / 7.0;
        // The machine is shared: GFLOP per CPU-second x cores estimates the uncontended figure.
        let cores = std::thread::available_parallelism().map_or(1, |n| n.get()) as f64;
        eprintln!(
            "{:<40} {:8.2} ms {:7.2} GFLOP/s (median of 7) | {:7.2} GFLOP/s per CPU-s x {cores} cores",
            b.name,
            s * 1e3,
            b.flop / s * 1e-9,
            b.flop / cpu * 1e-9 * cores
        );
        if quick {
            continue;
        }
        let flop = b.flop;
        c.bench_function(&b.name, |bn| {
            bn.iter_custom(|iters| {
                let start = Instant::now();
                for _ in 0..iters {
                    b.rec.submit_wait().expect("submit");
                }
                start.elapsed()
            })
        });
        let _ = flop;
    }
}

criterion_group! {
    name = benches;
    config = Criterion::default().sample_size(10).warm_up_time(Duration::from_secs(1)).measurement_time(Duration::from_secs(3));
    targets = bench
}
criterion_main!(benches);
