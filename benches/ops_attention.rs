//! Attention benchmarks: the UNet's first-level self- and cross-attention (1400 tokens, 8 heads of 40, batch 1;
//! cross-attention to the 77-token context), f32 and f16 storage, named `attention_<dtype>_<Lq>x<Lk>_h<H>_d<d>`.
//! Each iteration submits one pre-recorded dispatch and waits on its fence, so the clock is read after the device
//! finished. FLOP = 4 B H Lq Lk d (two matrix products); criterion's "elem/s" throughput is FLOP/s.
//!
//! Before criterion runs a case, the default kernel and its siblings with other query rows per lane (`_r<R>`)
//! run round-robin 7 times each and print best / median GFLOP/s: on a shared machine only runs taken side by
//! side compare. Run: `cargo bench --bench ops_attention` (lavapipe honours `LP_NUM_THREADS`).
use std::time::Instant;

use b2dr::ops::attention::{attention_with, choose, KERNELS};
use b2dr::tensor::{DType, Tensor};
use b2dr::vk::{Context, ContextOptions};
use criterion::{criterion_group, criterion_main, Criterion, Throughput};

struct Case {
    dtype: DType,
    lq: usize,
    lk: usize,
    heads: usize,
    d: usize,
}

fn bench(c: &mut Criterion) {
    let ctx = match Context::new(&ContextOptions::default()) {
        Ok(c) => c,
        Err(e) => {
            eprintln!("SKIP: no Vulkan device ({e:#})");
            return;
        }
    };
    eprintln!("device: {} ({})", ctx.info().name, ctx.info().kind);
    let cases = [
        Case {
            dtype: DType::F32,
            lq: 1400,
            lk: 1400,
            heads: 8,
            d: 40,
        },
        Case {
            dtype: DType::F32,
            lq: 1400,
            lk: 77,
            heads: 8,
            d: 40,
        },
        Case {
            dtype: DType::F16,
            lq: 1400,
            lk: 1400,
            heads: 8,
            d: 40,
        },
        Case {
            dtype: DType::F16,
            lq: 1400,
            lk: 77,
            heads: 8,
            d: 40,
        },
    ];
    let mut g = c.benchmark_group("attention");
    g.sample_size(10);
    for cs in &cases {
        let name = format!(
            "attention_{}_{}x{}_h{}_d{}",
            cs.dtype.name(),
            cs.lq,
            cs.lk,
            cs.heads,
            cs.d
        );
        let w = cs.heads * cs.d;
        let mk = |l: usize, seed: f32| {
            let data: Vec<f32> = (0..l * w)
                .map(|i| ((i as f32 * 0.618 + seed).fract() - 0.5) * 2.0)
                .collect();
            Tensor::from_f32(&ctx, &[1, l, w], cs.dtype, &data, "bench").expect("upload")
        };
        let (q, k, v) = (mk(cs.lq, 0.1), mk(cs.lk, 0.2), mk(cs.lk, 0.3));
        let out = Tensor::empty(&ctx, &[1, cs.lq, w], cs.dtype, "bench-out").expect("alloc");
        let flop = 4 * cs.heads * cs.lq * cs.lk * cs.d;
        let default = choose(cs.dtype, cs.d);
        // The default kernel under the case's name, then the other kernels holding the same head dim (query
        // rows per lane R) suffixed with `_r<R>`.
        let kernels: Vec<_> = KERNELS
            .iter()
            .filter(|k| k.dtype == cs.dtype && !k.wide && k.cols == default.cols)
            .map(|kn| {
                let label = if kn.id == default.id {
                    name.clone()
                } else {
                    format!(
                        "{name}_r{}{}",
                        kn.rows,
                        if kn.packed { "_packed" } else { "" }
                    )
                };
                let mut rec = ctx.recorder().expect("recorder");
                attention_with(&mut rec, &q, &k, &v, &out, cs.heads, None, Some(*kn))
                    .expect("record");
                let recording = rec.finish().expect("finish");
                recording.submit_wait().expect("warm-up"); // pipeline JIT happens here, outside the clock
                (label, recording)
            })
            .collect();
        // A plain timing first, so GFLOP/s lines are printed even with criterion's output filtered. The machine
        // is shared: the variants run round-robin (7 rounds) so each sees the same load, and the best and the
        // median run of each are printed.
        let mut t = vec![vec![]; kernels.len()];
        for _ in 0..7 {
            for (ti, (_, recording)) in t.iter_mut().zip(&kernels) {
                let t0 = Instant::now();
                recording.submit_wait().expect("submit");
                ti.push(t0.elapsed().as_secs_f64());
            }
        }
        let gf = |s: f64| flop as f64 / s * 1e-9;
        for (ti, (label, _)) in t.iter_mut().zip(&kernels) {
            ti.sort_by(f64::total_cmp);
            eprintln!(
                "{label}: best {:.2} ms = {:.2} GFLOP/s, median {:.2} ms = {:.2} GFLOP/s",
                ti[0] * 1e3,
                gf(ti[0]),
                ti[3] * 1e3,
                gf(ti[3])
            );
        }
        let (label, recording) = &kernels[0];
        g.throughput(Throughput::Elements(flop as u64));
        g.bench_function(label, |b| {
            b.iter(|| recording.submit_wait().expect("submit"))
        });
    }
    g.finish();
}

criterion_group!(benches, bench);
criterion_main!(benches);
