//! matmul / linear against the CPU f64 reference: SD shapes, odd sizes, both kernels, f32 and f16, stress.
mod common;
use b2dr::ops::matmul::{self as mm, MatmulArgs, MatmulPath};
use b2dr::ops::reference::matmul as rmm;
use b2dr::tensor::{DType, Tensor};
use common::*;

/// One case: a (ba, M, K) x b (bb, K, N) or (bb, N, K); batch dims of 1 mean a 2-D operand.
struct Case {
    name: &'static str,
    ba: usize,
    bb: usize,
    m: usize,
    n: usize,
    k: usize,
    trans_b: bool,
    bias: bool,
    scale: f32,
}

const fn case(name: &'static str, m: usize, n: usize, k: usize, trans_b: bool) -> Case {
    Case {
        name,
        ba: 1,
        bb: 1,
        m,
        n,
        k,
        trans_b,
        bias: true,
        scale: 1.0,
    }
}

const CASES: &[Case] = &[
    // SD1.5 shapes: attention projections at 28x50 latents (tokens 1400, 320 ch), FF, time embedding
    case("sd_proj_1400x320x320_t", 1400, 320, 320, true),
    case("sd_ff_1400x1280x320_t", 1400, 1280, 320, true),
    case("sd_ff_out_350x640x2560_t", 350, 640, 2560, true),
    case("sd_1400x1280x320_nn", 1400, 1280, 320, false),
    case("time_emb_2x1280x320_t", 2, 1280, 320, true),
    // odd sizes
    case("one_1x1x1", 1, 1, 1, false),
    case("one_1x1x1_t", 1, 1, 1, true),
    case("odd_7x13x5", 7, 13, 5, false),
    case("odd_7x13x5_t", 7, 13, 5, true),
    case("primes_67x61x59", 67, 61, 59, false),
    case("primes_67x61x59_t", 67, 61, 59, true),
    case("k_not_tile_65x36x12", 65, 36, 12, false),
    case("k_not_tile_65x36x12_t", 65, 36, 12, true),
    case("k_tail_33x64x36_t", 33, 64, 36, true),
    Case {
        name: "batched_both_3x37x40x24",
        ba: 3,
        bb: 3,
        ..case("", 37, 40, 24, false)
    },
    Case {
        name: "batched_a_only_2x9x20x16_t",
        ba: 2,
        ..case("", 9, 20, 16, true)
    },
    Case {
        name: "batched_b_only_2x9x21x17",
        bb: 2,
        bias: false,
        ..case("", 9, 21, 17, false)
    },
    Case {
        name: "large_inputs_x1e3_t",
        scale: 1e3,
        ..case("", 70, 96, 80, true)
    },
    Case {
        name: "large_inputs_x1e3_nn",
        scale: 1e3,
        ..case("", 70, 97, 81, false)
    },
];

fn shape3(b: usize, r: usize, c: usize) -> Vec<usize> {
    if b == 1 {
        vec![r, c]
    } else {
        vec![b, r, c]
    }
}

/// Runs one case and returns its nMSE against the f64 reference (computed from the stored inputs).
fn run_case(ctx: &b2dr::vk::Context, c: &Case, dtype: DType, path: MatmulPath, seed: u64) -> f64 {
    let batch = c.ba.max(c.bb);
    // f16 stress: a x scale, b / scale (outputs must stay inside f16's range to be comparable)
    let (sa, sb) = match dtype {
        DType::F16 => (c.scale, 1.0 / c.scale),
        DType::F32 => (c.scale, c.scale),
    };
    let a = uniform(c.ba * c.m * c.k, sa, seed);
    let b = uniform(c.bb * c.k * c.n, sb, seed + 1);
    let bias = uniform(c.n, sa * sb, seed + 2);
    let bshape = if c.trans_b {
        shape3(c.bb, c.n, c.k)
    } else {
        shape3(c.bb, c.k, c.n)
    };
    let ta = upload(ctx, &shape3(c.ba, c.m, c.k), dtype, &a);
    let tb = upload(ctx, &bshape, dtype, &b);
    let tbias = upload(ctx, &[c.n], dtype, &bias);
    let oshape = if c.ba > 1 || c.bb > 1 {
        vec![batch, c.m, c.n]
    } else {
        vec![c.m, c.n]
    };
    let out = empty(ctx, &oshape, dtype);
    run(ctx, |rec| {
        mm::matmul_ex(
            rec,
            &MatmulArgs {
                bias: c.bias.then_some(&tbias),
                transpose_b: c.trans_b,
                path,
                ..MatmulArgs::new(&ta, &tb, &out)
            },
        )
    });
    let bs = stored(&bias, dtype);
    let want = rmm::matmul(
        &stored(&a, dtype),
        &stored(&b, dtype),
        c.bias.then_some(&bs[..]),
        batch,
        c.m,
        c.n,
        c.k,
        c.trans_b,
    );
    nmse(&out.to_f32(ctx).unwrap(), &want)
}

fn tol(dtype: DType) -> f64 {
    match dtype {
        DType::F32 => 1e-6,
        DType::F16 => 5e-4,
    }
}

#[test]
fn tiled_and_direct_match_reference() {
    let Some(ctx) = ctx() else { return };
    for dtype in [DType::F32, DType::F16] {
        for path in [MatmulPath::Auto, MatmulPath::Direct] {
            let mut worst = 0.0f64;
            for (i, c) in CASES.iter().enumerate() {
                let e = run_case(&ctx, c, dtype, path, 100 + i as u64);
                eprintln!("{dtype:?} {path:?} {}: nmse {e:.2e}", c.name);
                assert!(e <= tol(dtype), "{} {dtype:?} {path:?}: nmse {e:e}", c.name);
                worst = worst.max(e);
            }
            eprintln!("{dtype:?} {path:?}: worst nmse {worst:.2e}");
        }
    }
    assert_no_validation_errors();
}

/// The largest reductions the renderer runs: a truncated loop (lavapipe's 65535 back-edge budget) would drop
/// most of K and fail the threshold by orders of magnitude.
#[test]
fn long_reductions_are_not_truncated() {
    let Some(ctx) = ctx() else { return };
    for (name, k) in [("ff_k5120", 5120usize), ("unet_conv_as_gemm_k23040", 23040)] {
        let c = Case {
            name,
            ..case("", 9, 40, k, true)
        };
        for path in [MatmulPath::Auto, MatmulPath::Direct] {
            let e = run_case(&ctx, &c, DType::F32, path, 7);
            eprintln!("{name} {path:?}: nmse {e:.2e}");
            assert!(e <= 1e-6, "{name} {path:?}: nmse {e:e}");
        }
        let c = Case {
            trans_b: false,
            ..c
        };
        let e = run_case(&ctx, &c, DType::F32, MatmulPath::Auto, 8);
        assert!(e <= 1e-6, "{name} nn: nmse {e:e}");
    }
    assert_no_validation_errors();
}

#[test]
fn linear_flattens_leading_dims() {
    let Some(ctx) = ctx() else { return };
    let (bt, t, i, o) = (2usize, 77usize, 48usize, 40usize);
    let x = uniform(bt * t * i, 1.0, 1);
    let w = uniform(o * i, 1.0, 2);
    let b = uniform(o, 1.0, 3);
    let (tx, tw, tb) = (
        upload(&ctx, &[bt, t, i], DType::F32, &x),
        upload(&ctx, &[o, i], DType::F32, &w),
        upload(&ctx, &[o], DType::F32, &b),
    );
    let out = empty(&ctx, &[bt, t, o], DType::F32);
    run(&ctx, |rec| mm::linear(rec, &tx, &tw, Some(&tb), &out));
    let want = rmm::matmul(
        &stored(&x, DType::F32),
        &stored(&w, DType::F32),
        Some(&stored(&b, DType::F32)),
        1,
        bt * t,
        o,
        i,
        true,
    );
    let e = nmse(&out.to_f32(&ctx).unwrap(), &want);
    assert!(e <= 1e-6, "linear: nmse {e:e}");
    assert_no_validation_errors();
}

/// f16 policy: results past 65504 saturate (finite), and the checked mode raises the flag; in-range results
/// leave the flag clear.
#[test]
fn f16_overflow_saturates_and_is_flagged() {
    let Some(ctx) = ctx() else { return };
    let (m, n, k) = (5usize, 12usize, 64usize);
    for path in [MatmulPath::Auto, MatmulPath::Direct] {
        for (scale, overflows) in [(100.0f32, true), (1.0, false)] {
            // all-positive inputs: the sums reach k * scale^2 = 640000 > 65504 at scale 100
            let a: Vec<f32> = uniform(m * k, 1.0, 5)
                .iter()
                .map(|v| (v.abs() + 0.5) * scale)
                .collect();
            let b: Vec<f32> = uniform(k * n, 1.0, 6)
                .iter()
                .map(|v| (v.abs() + 0.5) * scale)
                .collect();
            let ta = upload(&ctx, &[m, k], DType::F16, &a);
            let tb = upload(&ctx, &[n, k], DType::F16, &b);
            let flag = Tensor::zeros(&ctx, &[1], DType::F32, "flag").unwrap();
            for checked in [false, true] {
                let out = empty(&ctx, &[m, n], DType::F16);
                run(&ctx, |rec| {
                    mm::matmul_ex(
                        rec,
                        &MatmulArgs {
                            transpose_b: true,
                            path,
                            overflow: checked.then_some(&flag),
                            ..MatmulArgs::new(&ta, &tb, &out)
                        },
                    )
                });
                let got = out.to_f32(&ctx).unwrap();
                assert!(
                    got.iter().all(|v| v.is_finite()),
                    "{path:?}: Inf/NaN in f16 output"
                );
                if overflows {
                    assert!(
                        got.iter().all(|&v| v == 65504.0),
                        "{path:?}: not saturated: {got:?}"
                    );
                } else {
                    let want = rmm::matmul(
                        &stored(&a, DType::F16),
                        &stored(&b, DType::F16),
                        None,
                        1,
                        m,
                        n,
                        k,
                        true,
                    );
                    assert!(nmse(&got, &want) <= 5e-4);
                }
            }
            let f = flag.to_f32(&ctx).unwrap()[0];
            assert_eq!(
                f,
                if overflows { 1.0 } else { 0.0 },
                "{path:?} scale {scale}: flag {f}"
            );
        }
    }
    assert_no_validation_errors();
}

#[test]
fn bad_inputs_are_errors() {
    let Some(ctx) = ctx() else { return };
    let t = |s: &[usize], d: DType| Tensor::zeros(&ctx, s, d, "t").unwrap();
    let (a, b, o) = (
        t(&[4, 8], DType::F32),
        t(&[8, 6], DType::F32),
        t(&[4, 6], DType::F32),
    );
    let mut rec = ctx.recorder().unwrap();
    let check = |r: anyhow::Result<()>, want: &str| {
        let e = format!("{:#}", r.expect_err(want));
        assert!(e.contains(want), "error {e:?} should mention {want:?}");
    };
    check(
        mm::matmul(&mut rec, &a, &t(&[7, 6], DType::F32), None, &o),
        "inner dimensions",
    );
    check(
        mm::matmul(&mut rec, &a, &b, None, &t(&[4, 5], DType::F32)),
        "out has shape",
    );
    check(
        mm::matmul(&mut rec, &a, &t(&[8, 6], DType::F16), None, &o),
        "dtype mismatch",
    );
    check(
        mm::matmul(&mut rec, &a, &b, Some(&t(&[5], DType::F32)), &o),
        "bias",
    );
    check(
        mm::matmul(
            &mut rec,
            &t(&[2, 4, 8], DType::F32),
            &t(&[3, 8, 6], DType::F32),
            None,
            &t(&[2, 4, 6], DType::F32),
        ),
        "batch sizes",
    );
    check(
        mm::matmul(&mut rec, &t(&[1, 1, 4, 8], DType::F32), &b, None, &o),
        "2-D or 3-D",
    );
    check(
        mm::linear(&mut rec, &a, &t(&[6, 7], DType::F32), None, &o),
        "linear",
    );
    check(
        mm::matmul_ex(
            &mut rec,
            &MatmulArgs {
                overflow: Some(&t(&[1], DType::F32)),
                ..MatmulArgs::new(&a, &b, &o)
            },
        ),
        "overflow flag",
    );
    assert!(
        Tensor::empty(&ctx, &[0, 3], DType::F32, "e").is_err(),
        "empty tensors are refused at creation"
    );
    drop(rec);
    assert_no_validation_errors();
}

#[test]
fn fused_residual_matches_reference() {
    let Some(ctx) = ctx() else { return };
    // out = a b^T (+ bias) + residual through every tiled B width (nt8a4: K % 8, N % 4; nt8a: N % 4 != 0;
    // nt4 / nt: K % 4, K odd), the nn kernels, the direct kernel, batched, and in place (residual = out).
    let cases: &[(&str, usize, usize, usize, usize, bool)] = &[
        ("nt8a4_2x70x32x40", 2, 70, 32, 40, true),
        ("nt8a_70x30x40", 1, 70, 30, 40, true),
        ("nt4_33x20x12", 1, 33, 20, 12, true),
        ("nt_17x9x7", 1, 17, 9, 7, true),
        ("nn4a_2x40x24x32", 2, 40, 24, 32, false),
        ("nn_13x7x5", 1, 13, 7, 5, false),
    ];
    for (i, &(name, batch, m, n, k, trans_b)) in cases.iter().enumerate() {
        for path in [MatmulPath::Tiled, MatmulPath::Direct] {
            for dtype in [DType::F32, DType::F16] {
                for in_place in [false, true] {
                    let seed = 500 + 10 * i as u64;
                    let a = uniform(batch * m * k, 1.0, seed);
                    let b = uniform(n * k, 1.0, seed + 1);
                    let bias = uniform(n, 1.0, seed + 2);
                    let r = uniform(batch * m * n, 1.0, seed + 3);
                    let ta = upload(&ctx, &[batch, m, k], dtype, &a);
                    let bshape = if trans_b { [n, k] } else { [k, n] };
                    let tb = upload(&ctx, &bshape, dtype, &b);
                    let tbias = upload(&ctx, &[n], dtype, &bias);
                    let tr = upload(&ctx, &[batch, m, n], dtype, &r);
                    let out = if in_place {
                        tr.clone()
                    } else {
                        empty(&ctx, &[batch, m, n], dtype)
                    };
                    run(&ctx, |rec| {
                        mm::matmul_ex(
                            rec,
                            &MatmulArgs {
                                bias: Some(&tbias),
                                transpose_b: trans_b,
                                path,
                                residual: Some(&tr),
                                ..MatmulArgs::new(&ta, &tb, &out)
                            },
                        )
                    });
                    // b is shared over the batch (the reference broadcasts an unbatched operand)
                    let (a64, b64, bs) =
                        (stored(&a, dtype), stored(&b, dtype), stored(&bias, dtype));
                    let mm_ = rmm::matmul(&a64, &b64, Some(&bs), batch, m, n, k, trans_b);
                    let rs = stored(&r, dtype);
                    let want: Vec<f64> = mm_.iter().zip(&rs).map(|(x, y)| x + y).collect();
                    let e = nmse(&out.to_f32(&ctx).unwrap(), &want);
                    let tol = if dtype == DType::F32 { 1e-7 } else { 5e-4 };
                    assert!(
                        e <= tol,
                        "{name} {path:?} {dtype:?} in_place {in_place}: nmse {e:e}"
                    );
                }
            }
        }
    }
    // linear_residual flattens leading dims like linear; a mis-shaped residual is an error naming it
    let x = upload(&ctx, &[2, 3, 8], DType::F32, &uniform(48, 1.0, 1));
    let w = upload(&ctx, &[4, 8], DType::F32, &uniform(32, 1.0, 2));
    let r = upload(&ctx, &[2, 3, 4], DType::F32, &uniform(24, 1.0, 3));
    let out = empty(&ctx, &[2, 3, 4], DType::F32);
    run(&ctx, |rec| {
        mm::linear_residual(rec, &x, &w, None, Some(&r), &out)
    });
    let want: Vec<f64> = rmm::matmul(
        &stored(&uniform(48, 1.0, 1), DType::F32),
        &stored(&uniform(32, 1.0, 2), DType::F32),
        None,
        1,
        6,
        4,
        8,
        true,
    )
    .iter()
    .zip(stored(&uniform(24, 1.0, 3), DType::F32))
    .map(|(a, b)| a + b)
    .collect();
    let e = nmse(&out.to_f32(&ctx).unwrap(), &want);
    assert!(e <= 1e-7, "linear_residual: nmse {e:e}");
    let bad = empty(&ctx, &[6, 4], DType::F32);
    let mut rec = ctx.recorder().unwrap();
    let err = mm::linear_residual(&mut rec, &x, &w, None, Some(&bad), &out).unwrap_err();
    assert!(format!("{err:#}").contains("residual"), "{err:#}");
    assert_no_validation_errors();
}

#[test]
fn linear_to_channels_matches_reference() {
    let Some(ctx) = ctx() else { return };
    // tokens (N, L, C) . w (O, C)^T laid out as (N, O, L) (+ bias[o]) (+ residual): L a multiple of 4 (vec4
    // stores) and not, K % 8 == 0 and not.
    for (n, l, c, o) in [
        (2usize, 72usize, 32usize, 12usize),
        (2, 35, 16, 8),
        (1, 13, 6, 5),
    ] {
        for dtype in [DType::F32, DType::F16] {
            let t = uniform(n * l * c, 1.0, 21);
            let w = uniform(o * c, 1.0, 22);
            let b = uniform(o, 1.0, 23);
            let r = uniform(n * o * l, 1.0, 24);
            let (tt, tw, tb, tr) = (
                upload(&ctx, &[n, l, c], dtype, &t),
                upload(&ctx, &[o, c], dtype, &w),
                upload(&ctx, &[o], dtype, &b),
                upload(&ctx, &[n, o, l], dtype, &r),
            );
            let out = empty(&ctx, &[n, o, l], dtype);
            run(&ctx, |rec| {
                mm::linear_to_channels(rec, &tt, &tw, Some(&tb), Some(&tr), &out)
            });
            let (t64, w64, b64, r64) = (
                stored(&t, dtype),
                stored(&w, dtype),
                stored(&b, dtype),
                stored(&r, dtype),
            );
            // w (O, C) . tokens[i]^T per image: the reference's (batch, M = O, N = L) with b = the tokens
            let prod = rmm::matmul(&w64, &t64, None, n, o, l, c, true);
            let want: Vec<f64> = prod
                .iter()
                .enumerate()
                .map(|(j, v)| v + b64[(j / l) % o] + r64[j])
                .collect();
            let e = nmse(&out.to_f32(&ctx).unwrap(), &want);
            let tol = if dtype == DType::F32 { 1e-7 } else { 5e-4 };
            assert!(e <= tol, "({n}, {l}, {c}) -> {o} {dtype:?}: nmse {e:e}");
        }
    }
    let tt = empty(&ctx, &[1, 4, 8], DType::F32);
    let tw = empty(&ctx, &[3, 8], DType::F32);
    let bad = empty(&ctx, &[1, 4, 3], DType::F32);
    let mut rec = ctx.recorder().unwrap();
    let e = mm::linear_to_channels(&mut rec, &tt, &tw, None, None, &bad).unwrap_err();
    assert!(format!("{e:#}").contains("out"), "{e:#}");
    assert_no_validation_errors();
}

#[test]
fn linear_geglu_matches_linear_then_geglu() {
    let Some(ctx) = ctx() else { return };
    let sg = ctx.info().subgroup_size as usize;
    // x (.., K) . W^T + b -> [a | g] -> a * gelu(g), W given in geglu_permutation's row order; rows not a
    // multiple of the tile, K % 32 != 0, f32 and f16, with and without bias.
    for (rows, k, d) in [
        (70usize, 32usize, 64usize),
        (13, 40, 4 * sg),
        (200, 16, 2 * sg),
    ] {
        for dtype in [DType::F32, DType::F16] {
            for with_bias in [true, false] {
                let x = uniform(rows * k, 1.0, 31);
                let w = uniform(2 * d * k, 0.5, 32);
                let b = uniform(2 * d, 0.5, 33);
                let perm = mm::geglu_permutation(2 * d, sg).expect("fusable shape");
                let wp: Vec<f32> = perm
                    .iter()
                    .flat_map(|&o| w[o * k..(o + 1) * k].to_vec())
                    .collect();
                let bp: Vec<f32> = perm.iter().map(|&o| b[o]).collect();
                let tx = upload(&ctx, &[2, rows / 2, k], dtype, &x[..2 * (rows / 2) * k]);
                let tw = upload(&ctx, &[2 * d, k], dtype, &wp);
                let tb = upload(&ctx, &[2 * d], dtype, &bp);
                let out = empty(&ctx, &[2, rows / 2, d], dtype);
                run(&ctx, |rec| {
                    mm::linear_geglu(rec, &tx, &tw, with_bias.then_some(&tb), &out)
                });
                let r = 2 * (rows / 2);
                let bs = stored(&b, dtype);
                let pre = rmm::matmul(
                    &stored(&x[..r * k], dtype),
                    &stored(&w, dtype),
                    with_bias.then_some(&bs[..]),
                    1,
                    r,
                    2 * d,
                    k,
                    true,
                );
                let want = b2dr::ops::reference::geglu(&pre, r, d);
                let e = nmse(&out.to_f32(&ctx).unwrap(), &want);
                let tol = if dtype == DType::F32 { 1e-7 } else { 5e-4 };
                assert!(
                    e <= tol,
                    "{rows}x{k} -> {d} {dtype:?} bias {with_bias}: nmse {e:e}"
                );
            }
        }
    }
    // a shape the fused kernel cannot take is an error, not garbage
    assert!(mm::geglu_permutation(2 * sg + 2, sg).is_none());
    let x = empty(&ctx, &[4, 12], DType::F32);
    let w = empty(&ctx, &[4 * sg, 12], DType::F32);
    let out = empty(&ctx, &[4, 2 * sg], DType::F32);
    let mut rec = ctx.recorder().unwrap();
    let e = mm::linear_geglu(&mut rec, &x, &w, None, &out).unwrap_err();
    assert!(format!("{e:#}").contains("K % 8"), "{e:#}");
    assert_no_validation_errors();
}

/// The tiled kernels' texel-view variants (`vk::image`: operands of 4 KiB or more read through linear
/// storage images on CPU devices) must read every operand value exactly: A . I == A and I . B == B bit for
/// bit (multiplying by 1 and adding zeros is exact in f32), with sizes that are not whole image rows (the
/// buffers are padded, lavapipe pads linear images further) and both the nn4a and the nt8a4 kernels.
#[test]
fn texel_view_operands_are_read_exactly() {
    let Some(ctx) = ctx() else { return };
    let info = ctx.info();
    let views = info.linear_images && info.is_cpu();
    if !views {
        eprintln!(
            "{} has no texel views (not a CPU device with linear storage images): plain kernels only",
            info.name
        );
    }
    // below TEXEL_MIN_BYTES: never viewed (the plain kernels run)
    const { assert!(b2dr::vk::TEXEL_MIN_BYTES > 4000) };
    assert!(!upload(&ctx, &[1000], DType::F32, &[0.5; 1000])
        .buffer()
        .has_texel_view());
    let eye = |n: usize| {
        let mut v = vec![0.0f32; n * n];
        for i in 0..n {
            v[i * n + i] = 1.0;
        }
        v
    };
    // (M, K): A of 4,608 bytes (0.28 image rows of 16 KiB), 16,896 (1.03 rows), 66,560 (4.06 rows) and
    // 307,200 (18.75 rows)
    for (m, k) in [(9usize, 128usize), (33, 128), (130, 128), (300, 256)] {
        let a = uniform(m * k, 1.0, 11);
        let ta = upload(&ctx, &[m, k], DType::F32, &a);
        let ti = upload(&ctx, &[k, k], DType::F32, &eye(k));
        assert_eq!(ta.buffer().has_texel_view(), views, "A {m}x{k}");
        for trans_b in [false, true] {
            let out = empty(&ctx, &[m, k], DType::F32);
            run(&ctx, |rec| {
                mm::matmul_ex(
                    rec,
                    &MatmulArgs {
                        transpose_b: trans_b,
                        ..MatmulArgs::new(&ta, &ti, &out)
                    },
                )
            });
            assert!(
                out.to_f32(&ctx).unwrap() == a,
                "A . I != A ({m}x{k}, transposed I: {trans_b})"
            );
        }
        // I (M x M) . B (M x K) == B: B through the view
        let tim = upload(&ctx, &[m, m], DType::F32, &eye(m));
        let out = empty(&ctx, &[m, k], DType::F32);
        run(&ctx, |rec| {
            mm::matmul_ex(rec, &MatmulArgs::new(&tim, &ta, &out))
        });
        assert!(out.to_f32(&ctx).unwrap() == a, "I . B != B ({m}x{k})");
    }
    assert_no_validation_errors();
}
