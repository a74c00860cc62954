//! The small-head-dim attention fallback against a plain f64 reference.
mod common;
use b2dr::ops::attention_naive::attention_naive;
use b2dr::tensor::DType;
use common::*;

/// q: (B, Lq, H*d), k, v: (B, Lk, H*d) -> (B, Lq, H*d), softmax(q k^T / sqrt(d)) v per head.
#[allow(clippy::too_many_arguments)]
fn reference(
    q: &[f64],
    k: &[f64],
    v: &[f64],
    b: usize,
    lq: usize,
    lk: usize,
    h: usize,
    d: usize,
) -> Vec<f64> {
    let w = h * d;
    let mut out = vec![0.0; b * lq * w];
    for bb in 0..b {
        for hh in 0..h {
            for i in 0..lq {
                let s: Vec<f64> = (0..lk)
                    .map(|j| {
                        (0..d)
                            .map(|c| {
                                q[(bb * lq + i) * w + hh * d + c]
                                    * k[(bb * lk + j) * w + hh * d + c]
                            })
                            .sum::<f64>()
                            / (d as f64).sqrt()
                    })
                    .collect();
                let m = s.iter().cloned().fold(f64::MIN, f64::max);
                let e: Vec<f64> = s.iter().map(|x| (x - m).exp()).collect();
                let z: f64 = e.iter().sum();
                for c in 0..d {
                    out[(bb * lq + i) * w + hh * d + c] = (0..lk)
                        .map(|j| e[j] / z * v[(bb * lk + j) * w + hh * d + c])
                        .sum();
                }
            }
        }
    }
    out
}

#[test]
fn small_head_dims_match_reference() {
    let Some(ctx) = ctx() else { return };
    for dtype in [DType::F32, DType::F16] {
        for (b, lq, lk, h, d, scale) in [
            (2usize, 91usize, 77usize, 8usize, 1usize, 1.0f32),
            (1, 28, 28, 2, 2, 1.0),
            (1, 7, 13, 3, 3, 1.0),
            (1, 13, 1400, 1, 5, 1.0),
            (1, 5, 9, 2, 2, 300.0),
        ] {
            let (q, k, v) = (
                uniform(b * lq * h * d, scale, 1),
                uniform(b * lk * h * d, scale, 2),
                uniform(b * lk * h * d, 1.0, 3),
            );
            let (tq, tk, tv) = (
                upload(&ctx, &[b, lq, h * d], dtype, &q),
                upload(&ctx, &[b, lk, h * d], dtype, &k),
                upload(&ctx, &[b, lk, h * d], dtype, &v),
            );
            let out = empty(&ctx, &[b, lq, h * d], dtype);
            run(&ctx, |rec| {
                attention_naive(rec, &tq, &tk, &tv, &out, h, None)
            });
            let want = reference(
                &stored(&q, dtype),
                &stored(&k, dtype),
                &stored(&v, dtype),
                b,
                lq,
                lk,
                h,
                d,
            );
            let e = nmse(&out.to_f32(&ctx).unwrap(), &want);
            let tol = if dtype == DType::F32 { 1e-7 } else { 5e-4 };
            assert!(
                e <= tol,
                "attention_naive b{b} {lq}x{lk} h{h} d{d} x{scale} {dtype:?}: nmse {e:e}"
            );
        }
    }
    assert_no_validation_errors();
}

#[test]
fn loop_budget_and_shapes_are_checked() {
    let Some(ctx) = ctx() else { return };
    let q = empty(&ctx, &[1, 4, 6], DType::F32);
    let k = empty(&ctx, &[1, 20000, 6], DType::F32);
    let mut rec = ctx.recorder().unwrap();
    let e = attention_naive(&mut rec, &q, &k, &k, &q, 2, None)
        .unwrap_err()
        .to_string();
    assert!(e.contains("budget"), "{e}");
    let e = attention_naive(&mut rec, &q, &k, &k, &q, 4, None)
        .unwrap_err()
        .to_string();
    assert!(e.contains("heads"), "{e}");
}
