//! Softmax against the CPU f64 reference: SD shapes (attention rows of 1400 and 77), odd sizes, long rows
//! (a truncated loop would show), extremes (values 1e4 apart, constant rows, inputs x1e3).
mod common;
use b2dr::ops::{reference::attention as r, softmax::softmax};
use b2dr::tensor::DType;
use common::*;

const TOL: f64 = 1e-6;

/// `v` as a tensor of `dtype` would hold it.
fn stored_f32(v: &[f64], dtype: DType) -> Vec<f32> {
    let f: Vec<f32> = v.iter().map(|&x| x as f32).collect();
    stored(&f, dtype).iter().map(|&x| x as f32).collect()
}

/// x: (rows, n) with values from `gen`.
struct Case {
    name: &'static str,
    rows: usize,
    n: usize,
    gen: fn(usize, u64) -> Vec<f32>,
}

fn unit(n: usize, seed: u64) -> Vec<f32> {
    uniform(n, 4.0, seed)
}
fn x1e3(n: usize, seed: u64) -> Vec<f32> {
    uniform(n, 1e3, seed)
}
/// Values in {-1e4, 0, 1e4} plus small noise: rows dominated by a few huge entries.
fn spread_1e4(n: usize, seed: u64) -> Vec<f32> {
    uniform(n, 1.5, seed)
        .iter()
        .map(|v| v.round() * 1e4 + v.fract())
        .collect()
}
fn constant(n: usize, _seed: u64) -> Vec<f32> {
    vec![7.25; n]
}

const CASES: &[Case] = &[
    Case {
        name: "sd_self_rows_1400",
        rows: 512,
        n: 1400,
        gen: unit,
    },
    Case {
        name: "sd_cross_rows_77",
        rows: 1400,
        n: 77,
        gen: unit,
    },
    Case {
        name: "odd_7x13",
        rows: 7,
        n: 13,
        gen: unit,
    },
    Case {
        name: "single_1x1",
        rows: 1,
        n: 1,
        gen: unit,
    },
    Case {
        name: "prime_3x1009",
        rows: 3,
        n: 1009,
        gen: unit,
    },
    Case {
        name: "n_below_lanes_5x3",
        rows: 5,
        n: 3,
        gen: unit,
    },
    Case {
        name: "long_rows_2x262144",
        rows: 2,
        n: 262_144,
        gen: unit,
    },
    Case {
        name: "inputs_x1e3",
        rows: 33,
        n: 77,
        gen: x1e3,
    },
    Case {
        name: "values_1e4_apart",
        rows: 31,
        n: 1400,
        gen: spread_1e4,
    },
    Case {
        name: "constant_rows",
        rows: 9,
        n: 77,
        gen: constant,
    },
];

#[test]
fn softmax_matches_reference() {
    let Some(ctx) = ctx() else { return };
    for dtype in [DType::F32, DType::F16] {
        for (ci, c) in CASES.iter().enumerate() {
            // f16 cannot hold 1e4-apart values exactly but does store them; the reference uses the stored values.
            let x = (c.gen)(c.rows * c.n, 100 + ci as u64);
            let xt = upload(&ctx, &[c.rows, c.n], dtype, &x);
            let out = empty(&ctx, &[c.rows, c.n], dtype);
            run(&ctx, |rec| softmax(rec, &xt, &out));
            let want = r::softmax(&stored(&x, dtype), c.rows, c.n);
            let got = out.to_f32(&ctx).unwrap();
            let e = nmse(&got, &want);
            // f16 storage floor: the reference itself rounded to f16. It is ~4e-8 for normal outputs but rows
            // of 262144 put probabilities (~4e-6) in f16's subnormal range, where rounding alone costs ~5e-6.
            let floor = nmse(&stored_f32(&want, dtype), &want);
            eprintln!(
                "softmax {:<22} {dtype:?}: nmse {e:.3e} (storage floor {floor:.1e})",
                c.name
            );
            assert!(
                e <= TOL + 2.0 * floor,
                "softmax {} {dtype:?}: nmse {e:e}",
                c.name
            );
        }
    }
    assert_no_validation_errors();
}

#[test]
fn softmax_bad_inputs_are_errors() {
    let Some(ctx) = ctx() else { return };
    let a = upload(&ctx, &[2, 3], DType::F32, &[0.0; 6]);
    let h = empty(&ctx, &[2, 3], DType::F16);
    let wrong = empty(&ctx, &[3, 2], DType::F32);
    let mut rec = ctx.recorder().unwrap();
    let e = softmax(&mut rec, &a, &h).unwrap_err().to_string();
    assert!(e.contains("softmax") && e.contains("dtype"), "{e}");
    let e = softmax(&mut rec, &a, &wrong).unwrap_err().to_string();
    assert!(
        e.contains("softmax") && e.contains("[3, 2]") && e.contains("[2, 3]"),
        "{e}"
    );
    let long = empty(&ctx, &[1, 300_000], DType::F32);
    let e = softmax(&mut rec, &long, &long).unwrap_err().to_string();
    assert!(e.contains("softmax") && e.contains("300000"), "{e}");
    assert_eq!(rec.dispatch_count(), 0);
    drop(rec);
    assert_no_validation_errors();
}
