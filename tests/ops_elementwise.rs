//! Elementwise ops against the CPU f64 reference: SD shapes, odd sizes, extremes.
mod common;
use b2dr::ops::{elementwise as ew, reference as r};
use b2dr::tensor::DType;
use common::*;

struct Case {
    name: &'static str,
    shape: &'static [usize],
    scale: f32,
}

const UNARY_CASES: &[Case] = &[
    Case {
        name: "sd_latent_320c_28x50",
        shape: &[2, 320, 28, 50],
        scale: 1.0,
    },
    Case {
        name: "odd_7x13",
        shape: &[7, 13],
        scale: 1.0,
    },
    Case {
        name: "single",
        shape: &[1],
        scale: 1.0,
    },
    Case {
        name: "prime_1009",
        shape: &[1009],
        scale: 1.0,
    },
    Case {
        name: "large_inputs_x1e3",
        shape: &[3, 257],
        scale: 1e3,
    },
];

#[test]
fn unary_ops_match_reference() {
    let Some(ctx) = ctx() else { return };
    for dtype in [DType::F32, DType::F16] {
        for c in UNARY_CASES {
            let n: usize = c.shape.iter().product();
            let x = uniform(n, c.scale, 1);
            let xs = stored(&x, dtype);
            let xt = upload(&ctx, c.shape, dtype, &x);
            for (opname, f) in [
                ("silu", r::silu as fn(f64) -> f64),
                ("gelu", r::gelu),
                ("relu", r::relu),
                ("to_unit", r::to_unit),
            ] {
                let out = empty(&ctx, c.shape, dtype);
                run(&ctx, |rec| match opname {
                    "silu" => ew::silu(rec, &xt, &out),
                    "gelu" => ew::gelu(rec, &xt, &out),
                    "relu" => ew::relu(rec, &xt, &out),
                    _ => ew::to_unit(rec, &xt, &out),
                });
                let want: Vec<f64> = xs.iter().map(|&v| f(v)).collect();
                let e = nmse(&out.to_f32(&ctx).unwrap(), &want);
                assert!(
                    e <= elementwise_tol(dtype),
                    "{opname} {} {dtype:?}: nmse {e:e}",
                    c.name
                );
            }
        }
    }
    assert_no_validation_errors();
}

#[test]
fn add_mul_broadcast_match_reference() {
    let Some(ctx) = ctx() else { return };
    // (a shape, b shape): bias per channel, time embedding per (N, C), scalars, odd sizes
    let cases: &[(&[usize], &[usize])] = &[
        (&[2, 320, 28, 50], &[1, 320, 1, 1]),
        (&[2, 320, 28, 50], &[2, 320, 1, 1]),
        (&[7, 13], &[7, 13]),
        (&[7, 13], &[13]),
        (&[3, 1, 5], &[4, 1]),
        // vec4 kernel with one operand broadcast over rows, or over the last dimension
        (&[2, 3, 8], &[8]),
        (&[4, 1], &[4, 8]),
        (&[1], &[1]),
    ];
    for dtype in [DType::F32, DType::F16] {
        for (i, (sa, sb)) in cases.iter().enumerate() {
            let a = uniform(sa.iter().product(), 1.0, 10 + i as u64);
            let b = uniform(sb.iter().product(), 1.0, 20 + i as u64);
            let (ta, tb) = (upload(&ctx, sa, dtype, &a), upload(&ctx, sb, dtype, &b));
            for op in ["add", "mul"] {
                let (want, so) =
                    r::broadcast(&stored(&a, dtype), sa, &stored(&b, dtype), sb, |x, y| {
                        if op == "add" {
                            x + y
                        } else {
                            x * y
                        }
                    });
                let out = empty(&ctx, &so, dtype);
                run(&ctx, |rec| {
                    if op == "add" {
                        ew::add(rec, &ta, &tb, &out)
                    } else {
                        ew::mul(rec, &ta, &tb, &out)
                    }
                });
                let e = nmse(&out.to_f32(&ctx).unwrap(), &want);
                assert!(
                    e <= elementwise_tol(dtype),
                    "{op} {sa:?} x {sb:?} {dtype:?}: nmse {e:e}"
                );
            }
        }
    }
    assert_no_validation_errors();
}

#[test]
fn scale_add_geglu_concat_match_reference() {
    let Some(ctx) = ctx() else { return };
    for dtype in [DType::F32, DType::F16] {
        // scale_add on a latent, with sampler-like coefficients
        let shape = [2, 4, 28, 50];
        let n = 2 * 4 * 28 * 50;
        let (x, y) = (uniform(n, 1.0, 3), uniform(n, 1.0, 4));
        let (tx, ty, out) = (
            upload(&ctx, &shape, dtype, &x),
            upload(&ctx, &shape, dtype, &y),
            empty(&ctx, &shape, dtype),
        );
        run(&ctx, |rec| ew::scale_add(rec, 0.75, &tx, -1.25, &ty, &out));
        let want: Vec<f64> = stored(&x, dtype)
            .iter()
            .zip(stored(&y, dtype))
            .map(|(a, b)| 0.75f32 as f64 * a - 1.25 * b)
            .collect();
        let e = nmse(&out.to_f32(&ctx).unwrap(), &want);
        assert!(
            e <= elementwise_tol(dtype),
            "scale_add {dtype:?}: nmse {e:e}"
        );

        // geglu: tokens x 2*inner (SD: 1400 x 2560) and an odd one
        for (rows, d) in [(1400usize, 1280usize), (7, 13)] {
            let x = uniform(rows * 2 * d, 2.0, 5);
            let tx = upload(&ctx, &[rows, 2 * d], dtype, &x);
            let out = empty(&ctx, &[rows, d], dtype);
            run(&ctx, |rec| ew::geglu(rec, &tx, &out));
            let e = nmse(
                &out.to_f32(&ctx).unwrap(),
                &r::geglu(&stored(&x, dtype), rows, d),
            );
            assert!(
                e <= elementwise_tol(dtype),
                "geglu {rows}x{d} {dtype:?}: nmse {e:e}"
            );
        }

        // concat along channels (UNet skip concat: 1280 + 640 at 14x25), odd
        for (n_, c1, c2, h, w) in [
            (2usize, 1280usize, 640usize, 14usize, 25usize),
            (1, 3, 5, 7, 13),
        ] {
            let a = uniform(n_ * c1 * h * w, 1.0, 6);
            let b = uniform(n_ * c2 * h * w, 1.0, 7);
            let (ta, tb) = (
                upload(&ctx, &[n_, c1, h, w], dtype, &a),
                upload(&ctx, &[n_, c2, h, w], dtype, &b),
            );
            let out = empty(&ctx, &[n_, c1 + c2, h, w], dtype);
            run(&ctx, |rec| ew::concat_channels(rec, &ta, &tb, &out));
            let (sa, sb) = (stored(&a, dtype), stored(&b, dtype));
            let mut want = vec![];
            for i in 0..n_ {
                want.extend_from_slice(&sa[i * c1 * h * w..(i + 1) * c1 * h * w]);
                want.extend_from_slice(&sb[i * c2 * h * w..(i + 1) * c2 * h * w]);
            }
            let got = out.to_f32(&ctx).unwrap();
            assert_eq!(
                nmse(&got, &want),
                0.0,
                "concat must be an exact copy ({dtype:?})"
            );
        }
    }
    assert_no_validation_errors();
}

#[test]
fn bad_inputs_are_errors_naming_the_op() {
    let Some(ctx) = ctx() else { return };
    let a = upload(&ctx, &[2, 3], DType::F32, &[0.0; 6]);
    let b = upload(&ctx, &[4], DType::F32, &[0.0; 4]);
    let h = upload(&ctx, &[2, 3], DType::F16, &[0.0; 6]);
    let out = empty(&ctx, &[2, 3], DType::F32);
    let mut rec = ctx.recorder().unwrap();
    let e = ew::add(&mut rec, &a, &b, &out).unwrap_err().to_string();
    assert!(
        e.contains("add") && e.contains("[2, 3]") && e.contains("[4]"),
        "{e}"
    );
    let e = ew::silu(&mut rec, &h, &out).unwrap_err().to_string();
    assert!(e.contains("silu") && e.contains("dtype"), "{e}");
    let e = ew::geglu(&mut rec, &a, &out).unwrap_err().to_string();
    assert!(e.contains("geglu"), "{e}");
    let e = b2dr::tensor::Tensor::empty(&ctx, &[0, 3], DType::F32, "x")
        .unwrap_err()
        .to_string();
    assert!(e.contains("empty shape"), "{e}");
    assert_eq!(rec.dispatch_count(), 0);
    drop(rec);
    assert_no_validation_errors();
}

#[test]
fn transpose_is_exact() {
    let Some(ctx) = ctx() else { return };
    for dtype in [DType::F32, DType::F16] {
        for (b, rr, c) in [(2usize, 320usize, 1400usize), (1, 7, 13), (3, 1, 5)] {
            let x = uniform(b * rr * c, 1.0, 8);
            let tx = upload(&ctx, &[b, rr, c], dtype, &x);
            let out = empty(&ctx, &[b, c, rr], dtype);
            run(&ctx, |rec| ew::transpose(rec, &tx, &out));
            let xs = stored(&x, dtype);
            let mut want = vec![0.0; xs.len()];
            for n in 0..b {
                for i in 0..rr {
                    for j in 0..c {
                        want[(n * c + j) * rr + i] = xs[(n * rr + i) * c + j];
                    }
                }
            }
            assert_eq!(
                nmse(&out.to_f32(&ctx).unwrap(), &want),
                0.0,
                "transpose {b}x{rr}x{c} {dtype:?}"
            );
        }
    }
    assert_no_validation_errors();
}
