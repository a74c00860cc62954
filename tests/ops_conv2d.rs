//! conv2d against the CPU f64 reference: SD shapes, the VAE's asymmetric downsample padding, odd sizes, 1x1 as
//! GEMM, long reductions; the fast path (implicit GEMM / GEMM) and the direct kernel, f32 and f16.
mod common;
use b2dr::ops::conv2d::{self as cv, Conv2dArgs, ConvPath};
use b2dr::ops::reference::conv2d::{self as rc, ConvGeom};
use b2dr::tensor::{DType, Tensor};
use common::*;

/// x: (n, c, h, w), w: (o, c, k.0, k.1)
struct Case {
    name: &'static str,
    n: usize,
    c: usize,
    h: usize,
    w: usize,
    o: usize,
    k: (usize, usize),
    stride: usize,
    pad: [usize; 4],
    scale: f32,
    /// also run the (slow) direct kernel
    direct: bool,
}

const fn case(
    name: &'static str,
    c: usize,
    o: usize,
    h: usize,
    w: usize,
    k: usize,
    pad: usize,
) -> Case {
    Case {
        name,
        n: 1,
        c,
        h,
        w,
        o,
        k: (k, k),
        stride: 1,
        pad: [pad; 4],
        scale: 1.0,
        direct: true,
    }
}

const CASES: &[Case] = &[
    Case {
        direct: false,
        ..case("sd_3x3_320to320_28x50", 320, 320, 28, 50, 3, 1)
    },
    case("sd_like_3x3_64to48_28x50", 64, 48, 28, 50, 3, 1),
    case("conv_in_3x3_4to40_28x50", 4, 40, 28, 50, 3, 1),
    Case {
        stride: 2,
        pad: [0, 1, 0, 1],
        ..case("vae_down_s2_pad0101_24to24_56x100", 24, 24, 56, 100, 3, 0)
    },
    Case {
        n: 2,
        ..case("1x1_gemm_80to36_14x25_batch2", 80, 36, 14, 25, 1, 0)
    },
    case("one_1x1_image_1x1", 1, 1, 1, 1, 1, 0),
    case("one_3x3_pad1_on_1x1", 3, 2, 1, 1, 3, 1),
    Case {
        n: 2,
        k: (5, 3),
        stride: 3,
        pad: [2, 1, 0, 2],
        ..case("odd_7x13_k5x3_s3_pad2102", 3, 5, 7, 13, 0, 0)
    },
    case("primes_11to13_17x19", 11, 13, 17, 19, 3, 1),
    Case {
        stride: 2,
        ..case("primes_s2_13to7_23x29_k5", 13, 7, 23, 29, 5, 2)
    },
    Case {
        scale: 1e3,
        ..case("large_inputs_x1e3", 20, 24, 9, 15, 3, 1)
    },
    // few output channels (a model's last conv): vec4 window rows (W % 4 == 0, left padding 1), a partial
    // chunk of 8 input channels and a partial 8-pixel strip, asymmetric padding, batch 2
    case("conv_out_3x3_32to3_24x40", 32, 3, 24, 40, 3, 1),
    case("conv_out_3x3_20to4_13x18", 20, 4, 13, 18, 3, 1),
    Case {
        n: 2,
        pad: [2, 0, 0, 1],
        ..case(
            "conv_out_asym_pad2001_13to1_9x11_batch2",
            13,
            1,
            9,
            11,
            3,
            0,
        )
    },
];

fn run_case(ctx: &b2dr::vk::Context, c: &Case, dtype: DType, path: ConvPath, seed: u64) -> f64 {
    let g = ConvGeom {
        kh: c.k.0,
        kw: c.k.1,
        stride: c.stride,
        pad: c.pad,
    };
    // f16 stress: x * scale, w / scale keeps outputs inside f16's range
    let (sx, sw) = match dtype {
        DType::F16 => (c.scale, 1.0 / c.scale),
        DType::F32 => (c.scale, c.scale),
    };
    let x = uniform(c.n * c.c * c.h * c.w, sx, seed);
    let w = uniform(c.o * c.c * c.k.0 * c.k.1, sw, seed + 1);
    let b = uniform(c.o, sx * sw, seed + 2);
    let tx = upload(ctx, &[c.n, c.c, c.h, c.w], dtype, &x);
    let tw = upload(ctx, &[c.o, c.c, c.k.0, c.k.1], dtype, &w);
    let tb = upload(ctx, &[c.o], dtype, &b);
    let os = cv::conv2d_out_shape(tx.shape(), tw.shape(), c.stride, c.pad).unwrap();
    let out = empty(ctx, &os, dtype);
    run(ctx, |rec| {
        cv::conv2d_ex(
            rec,
            &Conv2dArgs {
                path,
                ..Conv2dArgs::new(&tx, &tw, Some(&tb), &out, c.stride, c.pad)
            },
        )
    });
    let want = rc::conv2d(
        &stored(&x, dtype),
        &stored(&w, dtype),
        Some(&stored(&b, dtype)),
        (c.n, c.c, c.h, c.w),
        c.o,
        g,
    );
    assert_eq!(g.out_hw(c.h, c.w), (os[2], os[3]));
    nmse(&out.to_f32(ctx).unwrap(), &want)
}

#[test]
fn fast_and_direct_match_reference() {
    let Some(ctx) = ctx() else { return };
    for dtype in [DType::F32, DType::F16] {
        for path in [
            ConvPath::Auto,
            ConvPath::FastHwnc,
            ConvPath::Winograd,
            ConvPath::Winograd6,
            ConvPath::Narrow,
            ConvPath::Direct,
        ] {
            let mut worst = 0.0f64;
            for (i, c) in CASES.iter().enumerate() {
                if path == ConvPath::Direct && !c.direct {
                    continue;
                }
                let wino = matches!(path, ConvPath::Winograd | ConvPath::Winograd6);
                if wino && (c.k != (3, 3) || c.stride != 1) {
                    continue;
                }
                if path == ConvPath::Narrow && (c.k != (3, 3) || c.stride != 1 || c.o > 4) {
                    continue;
                }
                let e = run_case(&ctx, c, dtype, path, 300 + i as u64);
                eprintln!("{dtype:?} {path:?} {}: nmse {e:.2e}", c.name);
                let tol = if dtype == DType::F32 { 1e-6 } else { 5e-4 };
                assert!(e <= tol, "{} {dtype:?} {path:?}: nmse {e:e}", c.name);
                worst = worst.max(e);
            }
            eprintln!("{dtype:?} {path:?}: worst nmse {worst:.2e}");
        }
    }
    assert_no_validation_errors();
}

/// The longest reductions the renderer runs (UNet up-block conv (1280 + 1280) -> 1280, 3x3: K = 23040; the
/// VAE decoder's 512-channel 3x3: K = 4608), output channels cut to keep the CPU reference fast. A loop
/// truncated by lavapipe's 65535 back-edge budget would drop most of K.
#[test]
fn long_reductions_are_not_truncated() {
    let Some(ctx) = ctx() else { return };
    let cases = [
        case("unet_up_3x3_2560to16_7x13", 2560, 16, 7, 13, 3, 1),
        // O % 4 != 0: the kernel on PyTorch-layout weights
        case("unet_up_3x3_2560to6_7x13", 2560, 6, 7, 13, 3, 1),
        case("vae_3x3_512to8_14x25", 512, 8, 14, 25, 3, 1),
    ];
    for c in &cases {
        for path in [ConvPath::Auto, ConvPath::FastHwnc, ConvPath::Direct] {
            let e = run_case(&ctx, c, DType::F32, path, 9);
            eprintln!("{} {path:?}: nmse {e:.2e}", c.name);
            assert!(e <= 1e-6, "{} {path:?}: nmse {e:e}", c.name);
        }
    }
    assert_no_validation_errors();
}

/// Winograd F(4x4, 3x3) and F(6x6, 3x3) on their edge cases: outputs that are not multiples of the tile,
/// asymmetric and zero padding, a 1x1 image, batches, several slabs of tiles (the intermediates are split at
/// 16 MiB), large inputs, and weights transformed once beforehand.
#[test]
fn winograd_edges_match_reference() {
    let Some(ctx) = ctx() else { return };
    let cases = [
        Case {
            n: 2,
            pad: [2, 0, 1, 2],
            ..case("asym_pad2012_9to12_10x7_batch2", 9, 12, 10, 7, 3, 0)
        },
        case("no_pad_8to8_6x6", 8, 8, 6, 6, 3, 0),
        case("pad1_on_1x1", 8, 8, 1, 1, 3, 1),
        case("prime_out_5to3_13x17", 5, 3, 13, 17, 3, 1),
        Case {
            n: 2,
            direct: false,
            ..case("slabs_256to8_76x76_batch2", 256, 8, 76, 76, 3, 1)
        },
        Case {
            scale: 1e3,
            ..case("large_inputs_x1e3_16to16_12x12", 16, 16, 12, 12, 3, 1)
        },
    ];
    use b2dr::ops::winograd::{transform_weight, weight_shape, Tile};
    for path in [ConvPath::Winograd, ConvPath::Winograd6] {
        for dtype in [DType::F32, DType::F16] {
            for (i, c) in cases.iter().enumerate() {
                let e = run_case(&ctx, c, dtype, path, 700 + i as u64);
                eprintln!("{dtype:?} {path:?} {}: nmse {e:.2e}", c.name);
                let tol = if dtype == DType::F32 { 1e-6 } else { 5e-4 };
                assert!(e <= tol, "{} {dtype:?} {path:?}: nmse {e:e}", c.name);
            }
        }
    }
    // transformed once, as the layers do at load
    let (x, w) = (uniform(12 * 9 * 11, 1.0, 3), uniform(16 * 12 * 9, 1.0, 4));
    let tx = upload(&ctx, &[1, 12, 9, 11], DType::F32, &x);
    let tw = upload(&ctx, &[16, 12, 3, 3], DType::F32, &w);
    let g = ConvGeom {
        kh: 3,
        kw: 3,
        stride: 1,
        pad: [1; 4],
    };
    let want = rc::conv2d(
        &stored(&x, DType::F32),
        &stored(&w, DType::F32),
        None,
        (1, 12, 9, 11),
        16,
        g,
    );
    for (tile, path) in [
        (Tile::F4, ConvPath::Winograd),
        (Tile::F6, ConvPath::Winograd6),
    ] {
        let u = empty(&ctx, &weight_shape(tw.shape(), tile), DType::F32);
        let out = empty(&ctx, &[1, 16, 9, 11], DType::F32);
        run(&ctx, |rec| {
            transform_weight(rec, &tw, &u)?;
            let (w4, w6) = if tile == Tile::F4 {
                (Some(&u), None)
            } else {
                (None, Some(&u))
            };
            cv::conv2d_ex(
                rec,
                &Conv2dArgs {
                    path,
                    wino_w: w4,
                    wino_w6: w6,
                    ..Conv2dArgs::new(&tx, &tw, None, &out, 1, [1; 4])
                },
            )
        });
        let e = nmse(&out.to_f32(&ctx).unwrap(), &want);
        assert!(e <= 1e-6, "pre-transformed {tile:?}: nmse {e:e}");
    }
    // the Winograd paths refuse other geometries
    let x5 = empty(&ctx, &[1, 4, 8, 8], DType::F32);
    let w5 = empty(&ctx, &[4, 4, 3, 3], DType::F32);
    let o5 = empty(&ctx, &[1, 4, 4, 4], DType::F32);
    for path in [ConvPath::Winograd, ConvPath::Winograd6] {
        let mut rec = ctx.recorder().unwrap();
        let r = cv::conv2d_ex(
            &mut rec,
            &Conv2dArgs {
                path,
                ..Conv2dArgs::new(&x5, &w5, None, &o5, 2, [1; 4])
            },
        );
        let msg = format!("{:#}", r.expect_err("stride 2 must be refused"));
        assert!(msg.contains("3x3 stride-1"), "{msg}");
    }
    assert_no_validation_errors();
}

/// Weights packed once by `pack_weight` (what a model does at load time) give the same result.
#[test]
fn prepacked_weights_match() {
    let Some(ctx) = ctx() else { return };
    for dtype in [DType::F32, DType::F16] {
        let (x, w) = (
            uniform(2 * 12 * 9 * 11, 1.0, 1),
            uniform(16 * 12 * 9, 1.0, 2),
        );
        let tx = upload(&ctx, &[2, 12, 9, 11], dtype, &x);
        let tw = upload(&ctx, &[16, 12, 3, 3], dtype, &w);
        let packed = empty(&ctx, &[3, 3, 12, 16], dtype);
        let out = empty(&ctx, &[2, 16, 5, 6], dtype);
        run(&ctx, |rec| {
            cv::pack_weight(rec, &tw, &packed)?;
            cv::conv2d_ex(
                rec,
                &Conv2dArgs {
                    path: ConvPath::Fast,
                    packed_w: Some(&packed),
                    ..Conv2dArgs::new(&tx, &tw, None, &out, 2, [1, 1, 1, 1])
                },
            )
        });
        let g = ConvGeom {
            kh: 3,
            kw: 3,
            stride: 2,
            pad: [1; 4],
        };
        let want = rc::conv2d(
            &stored(&x, dtype),
            &stored(&w, dtype),
            None,
            (2, 12, 9, 11),
            16,
            g,
        );
        let e = nmse(&out.to_f32(&ctx).unwrap(), &want);
        assert!(
            e <= if dtype == DType::F32 { 1e-6 } else { 5e-4 },
            "{dtype:?}: nmse {e:e}"
        );
    }
    assert_no_validation_errors();
}

#[test]
fn bad_inputs_are_errors() {
    let Some(ctx) = ctx() else { return };
    let t = |s: &[usize], d: DType| Tensor::zeros(&ctx, s, d, "t").unwrap();
    let x = t(&[1, 4, 8, 8], DType::F32);
    let w = t(&[6, 4, 3, 3], DType::F32);
    let o = t(&[1, 6, 8, 8], DType::F32);
    let mut rec = ctx.recorder().unwrap();
    let check = |r: anyhow::Result<()>, want: &str| {
        let e = format!("{:#}", r.expect_err(want));
        assert!(
            e.contains("conv2d") && e.contains(want),
            "error {e:?} should mention {want:?}"
        );
    };
    check(
        cv::conv2d(
            &mut rec,
            &x,
            &t(&[6, 5, 3, 3], DType::F32),
            None,
            1,
            [1; 4],
            &o,
        ),
        "input channels",
    );
    check(
        cv::conv2d(
            &mut rec,
            &x,
            &w,
            None,
            1,
            [1; 4],
            &t(&[1, 6, 7, 8], DType::F32),
        ),
        "out has shape",
    );
    check(
        cv::conv2d(
            &mut rec,
            &x,
            &t(&[6, 4, 3, 3], DType::F16),
            None,
            1,
            [1; 4],
            &o,
        ),
        "dtype mismatch",
    );
    check(
        cv::conv2d(&mut rec, &x, &w, None, 1, [3, 1, 1, 1], &o),
        "padding",
    );
    check(cv::conv2d(&mut rec, &x, &w, None, 0, [1; 4], &o), "stride");
    check(
        cv::conv2d(&mut rec, &x, &w, Some(&t(&[5], DType::F32)), 1, [1; 4], &o),
        "bias",
    );
    check(
        cv::conv2d(
            &mut rec,
            &t(&[1, 4, 2, 2], DType::F32),
            &t(&[6, 4, 5, 5], DType::F32),
            None,
            1,
            [0; 4],
            &o,
        ),
        "larger than the padded input",
    );
    check(
        cv::conv2d(
            &mut rec,
            &t(&[4, 8, 8], DType::F32),
            &w,
            None,
            1,
            [1; 4],
            &o,
        ),
        "(N, C, H, W)",
    );
    drop(rec);
    assert_no_validation_errors();
}

/// Several convs in one recording share its scratch buffers (per-call weight repacks, (H, W, N, C) transposes,
/// Winograd intermediates and weight transforms): each must still see its own data.
#[test]
fn convs_sharing_scratch_in_one_recording_match() {
    let Some(ctx) = ctx() else { return };
    // (c, o, h, w, path)
    let shapes = [
        (8usize, 8usize, 9usize, 11usize, ConvPath::FastHwnc),
        (12, 16, 7, 13, ConvPath::FastHwnc),
        (16, 12, 12, 12, ConvPath::Winograd),
        (8, 20, 10, 9, ConvPath::Winograd),
        (12, 8, 13, 14, ConvPath::Winograd6),
        (6, 4, 9, 8, ConvPath::Winograd6),
        (12, 8, 5, 6, ConvPath::Fast),
    ];
    let mut data = vec![];
    for (i, &(c, o, h, w, _)) in shapes.iter().enumerate() {
        let x = uniform(c * h * w, 1.0, 40 + i as u64);
        let wt = uniform(o * c * 9, 1.0, 60 + i as u64);
        let tx = upload(&ctx, &[1, c, h, w], DType::F32, &x);
        let tw = upload(&ctx, &[o, c, 3, 3], DType::F32, &wt);
        let out = empty(&ctx, &[1, o, h, w], DType::F32);
        data.push((x, wt, tx, tw, out));
    }
    run(&ctx, |rec| {
        for (&(_, _, _, _, path), (_, _, tx, tw, out)) in shapes.iter().zip(&data) {
            cv::conv2d_ex(
                rec,
                &Conv2dArgs {
                    path,
                    ..Conv2dArgs::new(tx, tw, None, out, 1, [1; 4])
                },
            )?;
        }
        Ok(())
    });
    let g = ConvGeom {
        kh: 3,
        kw: 3,
        stride: 1,
        pad: [1; 4],
    };
    for (&(c, o, h, w, path), (x, wt, _, _, out)) in shapes.iter().zip(&data) {
        let want = rc::conv2d(
            &stored(x, DType::F32),
            &stored(wt, DType::F32),
            None,
            (1, c, h, w),
            o,
            g,
        );
        let e = nmse(&out.to_f32(&ctx).unwrap(), &want);
        assert!(e <= 1e-6, "{c}->{o} {h}x{w} {path:?}: nmse {e:e}");
    }
    assert_no_validation_errors();
}

#[test]
fn fused_bias_per_image_and_residual_match_reference() {
    let Some(ctx) = ctx() else { return };
    // out = conv(x) + bias[n, o] + residual[n, o, y, x] (a ResNet block's conv1 with its time embedding and
    // conv2 with its skip), on every path: Winograd with scalar and vec4 transforms, the packed implicit GEMM
    // (fused), the O % 4 != 0 implicit GEMM and the direct kernel (separate adds), the 1x1 GEMM. Also with the
    // residual being `out` itself (in place), with a per-channel bias, and with SiLU on the result, and with
    // residuals large enough to be read through texel views.
    let cases: &[(&str, [usize; 4], usize, usize, ConvPath)] = &[
        (
            "winograd_scalar_28x50",
            [2, 8, 28, 50],
            12,
            3,
            ConvPath::Winograd,
        ),
        (
            "winograd_vec4_12x16",
            [2, 8, 12, 16],
            12,
            3,
            ConvPath::Winograd,
        ),
        (
            "winograd6_scalar_o6_13x20",
            [2, 5, 13, 20],
            6,
            3,
            ConvPath::Winograd6,
        ),
        (
            "winograd6_pairs_12x16",
            [2, 8, 12, 16],
            12,
            3,
            ConvPath::Winograd6,
        ),
        (
            "winograd6_quad_14x25",
            [2, 8, 14, 25],
            12,
            3,
            ConvPath::Winograd6,
        ),
        // outputs of 16 KiB and more (texel views from 4 KiB): on CPU devices the residual (also in place) is read through its texel
        // view (`vk::image`)
        (
            "winograd_vec4_texel_40x48",
            [1, 8, 40, 48],
            12,
            3,
            ConvPath::Winograd,
        ),
        (
            "winograd6_pairs_texel_56x100",
            [1, 8, 56, 100],
            8,
            3,
            ConvPath::Winograd6,
        ),
        ("packed_texel_14x25", [2, 32, 14, 25], 32, 3, ConvPath::Fast),
        (
            "packed_hwnc_texel_14x25",
            [2, 32, 14, 25],
            32,
            3,
            ConvPath::FastHwnc,
        ),
        ("narrow_o3_12x16", [2, 8, 12, 16], 3, 3, ConvPath::Narrow),
        ("narrow_o4_7x13", [2, 11, 7, 13], 4, 3, ConvPath::Narrow),
        ("packed_7x13", [2, 16, 7, 13], 8, 3, ConvPath::Fast),
        ("implicit_o6_7x13", [2, 5, 7, 13], 6, 3, ConvPath::Fast),
        ("direct_7x13", [2, 5, 7, 13], 8, 3, ConvPath::Direct),
        ("gemm_1x1_9x10", [2, 12, 9, 10], 8, 1, ConvPath::Fast),
    ];
    for (i, &(name, [n, c, h, w], o, k, path)) in cases.iter().enumerate() {
        for dtype in [DType::F32, DType::F16] {
            for (per_image, in_place, silu) in [
                (true, false, false),
                (false, true, true),
                (true, false, true),
            ] {
                let seed = 900 + 10 * i as u64;
                let x = uniform(n * c * h * w, 1.0, seed);
                let wt = uniform(o * c * k * k, 1.0, seed + 1);
                let nb = if per_image { n * o } else { o };
                let b = uniform(nb, 1.0, seed + 2);
                let r = uniform(n * o * h * w, 1.0, seed + 3);
                let tx = upload(&ctx, &[n, c, h, w], dtype, &x);
                let tw = upload(&ctx, &[o, c, k, k], dtype, &wt);
                let bshape: Vec<usize> = if per_image { vec![n, o] } else { vec![o] };
                let tb = upload(&ctx, &bshape, dtype, &b);
                let tr = upload(&ctx, &[n, o, h, w], dtype, &r);
                let out = if in_place {
                    tr.clone()
                } else {
                    empty(&ctx, &[n, o, h, w], dtype)
                };
                let pad = [k / 2; 4];
                run(&ctx, |rec| {
                    cv::conv2d_ex(
                        rec,
                        &Conv2dArgs {
                            path,
                            residual: Some(&tr),
                            silu,
                            ..Conv2dArgs::new(&tx, &tw, Some(&tb), &out, 1, pad)
                        },
                    )
                });
                let g = ConvGeom {
                    kh: k,
                    kw: k,
                    stride: 1,
                    pad,
                };
                let conv = rc::conv2d(
                    &stored(&x, dtype),
                    &stored(&wt, dtype),
                    None,
                    (n, c, h, w),
                    o,
                    g,
                );
                let (bs, rs) = (stored(&b, dtype), stored(&r, dtype));
                let hw = h * w;
                let want: Vec<f64> = conv
                    .iter()
                    .enumerate()
                    .map(|(j, v)| {
                        let (img, ch) = (j / (o * hw), (j / hw) % o);
                        let y = v + if per_image { bs[img * o + ch] } else { bs[ch] } + rs[j];
                        if silu {
                            b2dr::ops::reference::silu(y)
                        } else {
                            y
                        }
                    })
                    .collect();
                let e = nmse(&out.to_f32(&ctx).unwrap(), &want);
                let tol = if dtype == DType::F32 { 1e-6 } else { 5e-4 };
                assert!(
                    e <= tol,
                    "{name} {dtype:?} per_image {per_image} in_place {in_place} silu {silu}: nmse {e:e}"
                );
            }
        }
    }
    // a mis-shaped residual or bias is an error naming it
    let x = empty(&ctx, &[1, 4, 6, 6], DType::F32);
    let w = empty(&ctx, &[4, 4, 3, 3], DType::F32);
    let out = empty(&ctx, &[1, 4, 6, 6], DType::F32);
    let bad_r = empty(&ctx, &[1, 4, 6, 5], DType::F32);
    let bad_b = empty(&ctx, &[2, 4], DType::F32);
    for (bias, res, what) in [
        (None, Some(&bad_r), "residual"),
        (Some(&bad_b), None, "bias"),
    ] {
        let mut rec = ctx.recorder().unwrap();
        let e = cv::conv2d_ex(
            &mut rec,
            &Conv2dArgs {
                residual: res,
                ..Conv2dArgs::new(&x, &w, bias, &out, 1, [1; 4])
            },
        )
        .unwrap_err();
        assert!(format!("{e:#}").contains(what), "{what}: {e:#}");
    }
    assert_no_validation_errors();
}

#[test]
fn group_norm_prologue_matches_norm_then_conv() {
    let Some(ctx) = ctx() else { return };
    // conv(silu(group_norm(x))) with the norm folded into the Winograd input loads (norm::group_norm_stats +
    // Conv2dArgs::pre_gn_silu) against the f64 reference of the three steps: scalar input transform (C % 4 != 0),
    // input4s (W % 4 != 0), input4 (W % 4 == 0, left padding 1), an asymmetric padding, offset inputs (the
    // shift by each group's first element), f32 and f16, with a residual.
    // (name, x shape, O, groups, padding, input offset)
    type PrologueCase = (&'static str, [usize; 4], usize, usize, [usize; 4], f32);
    let cases: &[PrologueCase] = &[
        ("scalar_c6_9x11", [2, 6, 9, 11], 8, 3, [1; 4], 0.0),
        ("input4s_c8_7x13", [2, 8, 7, 13], 8, 4, [1; 4], 0.0),
        ("input4_c8_12x16", [1, 8, 12, 16], 12, 2, [1; 4], 0.0),
        ("asym_pad_c8_10x10", [1, 8, 10, 10], 8, 2, [0, 2, 2, 1], 0.0),
        ("offset_c8_12x16", [1, 8, 12, 16], 8, 4, [1; 4], 50.0),
    ];
    // and the few-output-channel kernel (its vec4-row and scalar loads)
    let narrow: &[PrologueCase] = &[
        ("narrow_rows4_c8_12x16", [2, 8, 12, 16], 3, 4, [1; 4], 0.0),
        ("narrow_scalar_c6_9x11", [1, 6, 9, 11], 4, 3, [1; 4], 0.0),
        (
            "narrow_offset_c12_8x20",
            [1, 12, 8, 20],
            3,
            4,
            [0, 2, 1, 1],
            50.0,
        ),
    ];
    let all = cases
        .iter()
        .flat_map(|c| [(c, ConvPath::Winograd), (c, ConvPath::Winograd6)])
        .chain(narrow.iter().map(|c| (c, ConvPath::Narrow)));
    for (i, (&(name, [n, c, h, w], o, groups, pad, offset), path)) in all.enumerate() {
        for dtype in [DType::F32, DType::F16] {
            let seed = 1200 + 10 * i as u64;
            let x: Vec<f32> = uniform(n * c * h * w, 1.0, seed)
                .iter()
                .map(|v| v + offset)
                .collect();
            let wt = uniform(o * c * 9, 1.0, seed + 1);
            let b = uniform(o, 1.0, seed + 2);
            let gamma = uniform(c, 1.0, seed + 3);
            let beta = uniform(c, 1.0, seed + 4);
            let tx = upload(&ctx, &[n, c, h, w], dtype, &x);
            let tw = upload(&ctx, &[o, c, 3, 3], dtype, &wt);
            let tb = upload(&ctx, &[o], dtype, &b);
            let tg = upload(&ctx, &[c], dtype, &gamma);
            let tbe = upload(&ctx, &[c], dtype, &beta);
            let os = cv::conv2d_out_shape(&[n, c, h, w], &[o, c, 3, 3], 1, pad).unwrap();
            let r = uniform(os.iter().product(), 1.0, seed + 5);
            let tr = upload(&ctx, &os, dtype, &r);
            let st = empty(&ctx, &[n, c, 4], DType::F32);
            let out = empty(&ctx, &os, dtype);
            run(&ctx, |rec| {
                b2dr::ops::norm::group_norm_stats(rec, &tx, groups, &tg, &tbe, 1e-5, &st)?;
                cv::conv2d_ex(
                    rec,
                    &Conv2dArgs {
                        path,
                        residual: Some(&tr),
                        pre_gn_silu: Some(&st),
                        ..Conv2dArgs::new(&tx, &tw, Some(&tb), &out, 1, pad)
                    },
                )
            });
            let hn = b2dr::ops::reference::image::group_norm(
                &stored(&x, dtype),
                n,
                c,
                h * w,
                groups,
                &stored(&gamma, dtype),
                &stored(&beta, dtype),
                1e-5,
                true,
            );
            let g = ConvGeom {
                kh: 3,
                kw: 3,
                stride: 1,
                pad,
            };
            let conv = rc::conv2d(
                &hn,
                &stored(&wt, dtype),
                Some(&stored(&b, dtype)),
                (n, c, h, w),
                o,
                g,
            );
            let rs = stored(&r, dtype);
            let want: Vec<f64> = conv.iter().zip(&rs).map(|(a, b)| a + b).collect();
            let e = nmse(&out.to_f32(&ctx).unwrap(), &want);
            let tol = if dtype == DType::F32 { 1e-6 } else { 5e-4 };
            assert!(e <= tol, "{name} {dtype:?} {path:?}: nmse {e:e}");
        }
    }
    // the prologue exists on the Winograd path only: elsewhere it is an error, not an unnormalised conv
    let x = empty(&ctx, &[1, 4, 6, 6], DType::F32);
    let w = empty(&ctx, &[4, 4, 3, 3], DType::F32);
    let st = empty(&ctx, &[1, 4, 4], DType::F32);
    let out = empty(&ctx, &[1, 4, 3, 3], DType::F32);
    let mut rec = ctx.recorder().unwrap();
    let e = cv::conv2d_ex(
        &mut rec,
        &Conv2dArgs {
            pre_gn_silu: Some(&st),
            ..Conv2dArgs::new(&x, &w, None, &out, 2, [1; 4])
        },
    )
    .unwrap_err();
    assert!(format!("{e:#}").contains("Winograd"), "{e:#}");
    assert_no_validation_errors();
}

#[test]
fn upsampled_input_matches_upsample_then_conv() {
    let Some(ctx) = ctx() else { return };
    // conv of the nearest 2x upsampling of x, read through the upsampling (Winograd: scalar input transform
    // for C % 4 != 0, input4s otherwise) or from an upsampled copy (the packed implicit GEMM, the direct
    // kernel), against the f64 reference of both steps; f32 and f16, with bias.
    let cases = [
        (
            "winograd_scalar_c6",
            [2usize, 6usize, 7usize, 9usize],
            8usize,
            ConvPath::Winograd,
        ),
        (
            "winograd_input4s_c8",
            [1, 8, 14, 25],
            12,
            ConvPath::Winograd,
        ),
        ("winograd6_scalar_c6", [2, 6, 7, 9], 8, ConvPath::Winograd6),
        (
            "winograd6_input6s_c8",
            [1, 8, 14, 25],
            12,
            ConvPath::Winograd6,
        ),
        ("narrow_c8_o3", [2, 8, 6, 10], 3, ConvPath::Narrow),
        ("packed_c8", [2, 8, 5, 7], 8, ConvPath::Fast),
        ("direct_c5", [1, 5, 4, 6], 3, ConvPath::Direct),
    ];
    // padding 1 starts every F(6x6) window at an odd upsampled coordinate; these start at even ones (and mixed)
    let pads = [("", [1; 4]), ("_pad0", [0; 4]), ("_pad2020", [2, 0, 2, 0])];
    let all = cases.iter().flat_map(|c| pads.iter().map(move |p| (c, p)));
    for (i, (&(name, [n, c, h, w], o, path), &(pname, pad))) in all.enumerate() {
        let name = format!("{name}{pname}");
        for dtype in [DType::F32, DType::F16] {
            let seed = 1500 + 10 * i as u64;
            let x = uniform(n * c * h * w, 1.0, seed);
            let wt = uniform(o * c * 9, 1.0, seed + 1);
            let b = uniform(o, 1.0, seed + 2);
            let tx = upload(&ctx, &[n, c, h, w], dtype, &x);
            let tw = upload(&ctx, &[o, c, 3, 3], dtype, &wt);
            let tb = upload(&ctx, &[o], dtype, &b);
            let os = cv::conv2d_out_shape(&[n, c, 2 * h, 2 * w], &[o, c, 3, 3], 1, pad).unwrap();
            let out = empty(&ctx, &os, dtype);
            run(&ctx, |rec| {
                cv::conv2d_ex(
                    rec,
                    &Conv2dArgs {
                        path,
                        upsample2x: true,
                        ..Conv2dArgs::new(&tx, &tw, Some(&tb), &out, 1, pad)
                    },
                )
            });
            let (h2, w2) = (2 * h, 2 * w);
            let xu = b2dr::ops::reference::image::upsample_nearest(
                &stored(&x, dtype),
                n * c,
                h,
                w,
                h2,
                w2,
            );
            let g = ConvGeom {
                kh: 3,
                kw: 3,
                stride: 1,
                pad,
            };
            let want = rc::conv2d(
                &xu,
                &stored(&wt, dtype),
                Some(&stored(&b, dtype)),
                (n, c, h2, w2),
                o,
                g,
            );
            let e = nmse(&out.to_f32(&ctx).unwrap(), &want);
            let tol = if dtype == DType::F32 { 1e-6 } else { 5e-4 };
            assert!(e <= tol, "{name} {dtype:?}: nmse {e:e}");
        }
    }
    assert_no_validation_errors();
}

/// Group-norm statistics from the F(6x6) conv's epilogue partials (`Conv2dArgs::stats_parts` +
/// `norm::group_norm_stats_parts`): the normalisation they define, applied to the conv's stored output, against
/// the f64 group norm of that output. Partial tile pairs (OH % 6, OW % 12 != 0), a batch of 2, bias and
/// residual, an output far from zero (the mean 1e3 times the spread: the shifted merge must not cancel), f32 and
/// f16 (the partials see the f16-rounded values, checked partial by partial: Mesa 25's lavapipe drops an
/// f32 -> f16 -> f32 round trip, so the kernel rounds in f32 arithmetic, `as_stored4`).
#[test]
fn group_norm_stats_from_conv_partials_match_reference() {
    let Some(ctx) = ctx() else { return };
    // (name, x shape, O, groups, residual offset)
    let cases: &[(&str, [usize; 4], usize, usize, f32)] = &[
        ("partial_pairs_14x20_batch2", [2, 8, 14, 20], 12, 3, 0.0),
        ("one_pair_6x8", [1, 4, 6, 8], 8, 8, 0.0),
        ("offset_1e3_13x28", [1, 8, 13, 28], 8, 2, 1e3),
    ];
    for (i, &(name, [n, c, h, w], o, groups, offset)) in cases.iter().enumerate() {
        for dtype in [DType::F32, DType::F16] {
            let seed = 1700 + 10 * i as u64;
            let x = uniform(n * c * h * w, 1.0, seed);
            let wt = uniform(o * c * 9, 0.3, seed + 1);
            let b = uniform(o, 1.0, seed + 2);
            let r: Vec<f32> = uniform(n * o * h * w, 1.0, seed + 3)
                .iter()
                .map(|v| v + offset)
                .collect();
            let gamma = uniform(o, 1.0, seed + 4);
            let beta = uniform(o, 1.0, seed + 5);
            let tx = upload(&ctx, &[n, c, h, w], dtype, &x);
            let tw = upload(&ctx, &[o, c, 3, 3], dtype, &wt);
            let tb = upload(&ctx, &[o], dtype, &b);
            let tr = upload(&ctx, &[n, o, h, w], dtype, &r);
            let tg = upload(&ctx, &[o], dtype, &gamma);
            let tbe = upload(&ctx, &[o], dtype, &beta);
            let out = empty(&ctx, &[n, o, h, w], dtype);
            let ps =
                cv::stats_parts_shape(ctx.info(), dtype, &[n, c, h, w], &[o, c, 3, 3], 1, [1; 4])
                    .unwrap_or([n * h.div_ceil(6) * w.div_ceil(12), o, 4]);
            let parts = empty(&ctx, &ps, DType::F32);
            let st = empty(&ctx, &[n, o, 4], DType::F32);
            run(&ctx, |rec| {
                cv::conv2d_ex(
                    rec,
                    &Conv2dArgs {
                        path: ConvPath::Winograd6,
                        residual: Some(&tr),
                        stats_parts: Some(&parts),
                        ..Conv2dArgs::new(&tx, &tw, Some(&tb), &out, 1, [1; 4])
                    },
                )?;
                b2dr::ops::norm::group_norm_stats_parts(
                    rec,
                    &parts,
                    &[n, o, h, w],
                    groups,
                    &tg,
                    &tbe,
                    1e-5,
                    &st,
                )
            });
            // the normalisation the statistics define, on the stored output, against the f64 group norm of it
            let y: Vec<f64> = out
                .to_f32(&ctx)
                .unwrap()
                .iter()
                .map(|&v| v as f64)
                .collect();
            // each partial (slot = tile pair (image, tile row, pair) of 6 rows x 12 columns): the count of the
            // pixels it covers and the mean of their values as stored (in f16: rounded, not the f32 values
            // before the store; 1e-6 is f32 precision, a partial of unrounded halves misses by ~1e-4)
            let pv = parts.to_f32(&ctx).unwrap();
            let (th, pw) = (h.div_ceil(6), w.div_ceil(12));
            for (slot, (img, ty, q)) in (0..n)
                .flat_map(|i| (0..th).flat_map(move |t| (0..pw).map(move |q| (i, t, q))))
                .enumerate()
            {
                for ch in 0..o {
                    let vals: Vec<f64> = (6 * ty..(6 * ty + 6).min(h))
                        .flat_map(|yy| (12 * q..(12 * q + 12).min(w)).map(move |xx| (yy, xx)))
                        .map(|(yy, xx)| y[((img * o + ch) * h + yy) * w + xx])
                        .collect();
                    let k = (slot * o + ch) * 4;
                    assert_eq!(
                        pv[k] as usize,
                        vals.len(),
                        "{name} {dtype:?}: slot {slot} count"
                    );
                    let mean = vals.iter().sum::<f64>() / vals.len() as f64;
                    let err = (pv[k + 1] as f64 - mean).abs();
                    assert!(
                        err <= 1e-6 * (mean.abs() + 1.0),
                        "{name} {dtype:?}: slot {slot} channel {ch}: partial mean {} vs {mean} of the stored values",
                        pv[k + 1]
                    );
                }
            }
            let s = st.to_f32(&ctx).unwrap();
            let hw = h * w;
            let got: Vec<f32> = y
                .iter()
                .enumerate()
                .map(|(j, &v)| {
                    let k = (j / hw) * 4; // (n, o) of element j
                    ((v - s[k + 2] as f64) * s[k] as f64 + s[k + 1] as f64) as f32
                })
                .collect();
            let want = b2dr::ops::reference::image::group_norm(
                &y,
                n,
                o,
                hw,
                groups,
                &stored(&gamma, dtype),
                &stored(&beta, dtype),
                1e-5,
                false,
            );
            let e = nmse(&got, &want);
            eprintln!("{name} {dtype:?}: nmse {e:.2e}");
            assert!(e <= 1e-9, "{name} {dtype:?}: nmse {e:e}");
        }
    }
    // where the path cannot write partials, asking for them is an error
    let x = empty(&ctx, &[1, 8, 6, 10], DType::F32);
    let w = empty(&ctx, &[8, 8, 3, 3], DType::F32);
    let out = empty(&ctx, &[1, 8, 6, 10], DType::F32);
    let parts = empty(&ctx, &[1, 8, 4], DType::F32);
    let mut rec = ctx.recorder().unwrap();
    let e = cv::conv2d_ex(
        &mut rec,
        &Conv2dArgs {
            path: ConvPath::Winograd,
            stats_parts: Some(&parts),
            ..Conv2dArgs::new(&x, &w, None, &out, 1, [1; 4])
        },
    )
    .unwrap_err();
    assert!(format!("{e:#}").contains("partials"), "{e:#}");
    drop(rec);
    assert_no_validation_errors();
}
