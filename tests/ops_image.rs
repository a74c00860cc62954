//! Nearest upsample, bicubic resize, Gaussian blur, timestep embedding against f64 references.
mod common;
use b2dr::ops::reference::image as r;
use b2dr::ops::{blur, embedding, resample, warp};
use b2dr::tensor::DType;
use common::*;

#[test]
fn upsample_nearest_matches_pytorch_rule() {
    let Some(ctx) = ctx() else { return };
    // UNet decoder sizes (not powers of two: 4x7 -> 7x13 -> 14x25 -> 28x50) and plain doubling.
    for dtype in [DType::F32, DType::F16] {
        for (c, h, w, oh, ow) in [
            (8usize, 4usize, 7usize, 7usize, 13usize),
            (4, 7, 13, 14, 25),
            (3, 14, 25, 28, 50),
            (2, 5, 5, 10, 10),
            (1, 1, 1, 3, 2),
        ] {
            let x = uniform(2 * c * h * w, 1.0, 1);
            let tx = upload(&ctx, &[2, c, h, w], dtype, &x);
            let out = empty(&ctx, &[2, c, oh, ow], dtype);
            run(&ctx, |rec| {
                resample::upsample_nearest(rec, &tx, &out, (oh, ow))
            });
            let want = r::upsample_nearest(&stored(&x, dtype), 2 * c, h, w, oh, ow);
            assert_eq!(
                nmse(&out.to_f32(&ctx).unwrap(), &want),
                0.0,
                "nearest {h}x{w}->{oh}x{ow} must copy exactly"
            );
        }
    }
    assert_no_validation_errors();
}

#[test]
fn bicubic_matches_pytorch_semantics() {
    let Some(ctx) = ctx() else { return };
    // render 224x400 -> native 900x1600 (the renderer's output path), a downscale and odd sizes
    for dtype in [DType::F32, DType::F16] {
        for (h, w, oh, ow) in [
            (224usize, 400usize, 900usize, 1600usize),
            (900, 1600, 224, 400),
            (7, 13, 11, 5),
            (1, 1, 3, 3),
        ] {
            let x = uniform(3 * h * w, 1.0, 2);
            let tx = upload(&ctx, &[1, 3, h, w], dtype, &x);
            let out = empty(&ctx, &[1, 3, oh, ow], dtype);
            run(&ctx, |rec| {
                resample::resize_bicubic(rec, &tx, &out, (oh, ow))
            });
            let want = r::resize_bicubic(&stored(&x, dtype), 3, h, w, oh, ow);
            let e = nmse(&out.to_f32(&ctx).unwrap(), &want);
            assert!(
                e <= elementwise_tol(dtype),
                "bicubic {h}x{w}->{oh}x{ow} {dtype:?}: nmse {e:e}"
            );
        }
    }
    assert_no_validation_errors();
}

#[test]
fn bicubic_known_values() {
    let Some(ctx) = ctx() else { return };
    // Upscaling a linear ramp by 2 with align_corners=False: interior samples of a cubic-convolution kernel
    // reproduce linear functions exactly; x = 0..3 -> samples at -0.25, 0.25, 0.75, ..., with clamped borders.
    let x = [0.0f32, 1.0, 2.0, 3.0];
    let tx = upload(&ctx, &[1, 1, 1, 4], DType::F32, &x);
    let out = empty(&ctx, &[1, 1, 1, 8], DType::F32);
    run(&ctx, |rec| resample::resize_bicubic(rec, &tx, &out, (1, 8)));
    let got = out.to_f32(&ctx).unwrap();
    // Values printed by PyTorch 2.x: F.interpolate(tensor([[[[0., 1., 2., 3.]]]]), size=(1, 8), mode="bicubic",
    // align_corners=False). Note A = -0.75 does not reproduce linear data exactly (only A = -0.5 does), and
    // border taps are clamped: e.g. out[2] = 1 * w(0.25) + 2 * w(1.25) = 0.87890625 - 0.2109375.
    let want = [
        -0.10546875f64,
        0.19140625,
        0.66796875,
        1.296875,
        1.703125,
        2.33203125,
        2.80859375,
        3.10546875,
    ];
    for (i, want) in want.into_iter().enumerate() {
        assert!(
            (got[i] as f64 - want).abs() < 1e-6,
            "out[{i}] = {} != {want}",
            got[i]
        );
    }
}

#[test]
fn gaussian_blur_matches_reference() {
    let Some(ctx) = ctx() else { return };
    for dtype in [DType::F32, DType::F16] {
        for (h, w, sigma) in [
            (224usize, 400usize, 1.0f32),
            (7, 13, 1.0),
            (32, 32, 2.0),
            (9, 9, 0.5),
        ] {
            let x = uniform(3 * h * w, 1.0, 3);
            let shape = [1, 3, h, w];
            let (tx, tmp, out) = (
                upload(&ctx, &shape, dtype, &x),
                empty(&ctx, &shape, dtype),
                empty(&ctx, &shape, dtype),
            );
            run(&ctx, |rec| blur::gaussian_blur(rec, &tx, sigma, &tmp, &out));
            let want = r::gaussian_blur(&stored(&x, dtype), 3, h, w, sigma as f64);
            let e = nmse(&out.to_f32(&ctx).unwrap(), &want);
            // f16 rounds twice (after each pass)
            let tol = if dtype == DType::F32 {
                1e-7
            } else {
                2.0 * elementwise_tol(dtype)
            };
            assert!(e <= tol, "blur {h}x{w} sigma {sigma} {dtype:?}: nmse {e:e}");
        }
    }
    assert_no_validation_errors();
}

#[test]
fn timestep_embedding_matches_diffusers_formula() {
    let Some(ctx) = ctx() else { return };
    let ts = [999.0f32, 949.0, 500.0, 1.0, 0.0];
    let t = upload(&ctx, &[5], DType::F32, &ts);
    let t64: Vec<f64> = ts.iter().map(|&v| v as f64).collect();
    for (dim, flip, shift) in [
        (320usize, true, 0.0f32),
        (64, true, 0.0),
        (33, false, 1.0),
        (4, true, 0.0),
    ] {
        let out = empty(&ctx, &[5, dim], DType::F32);
        let opts = embedding::TimestepEmbedding {
            flip_sin_to_cos: flip,
            downscale_freq_shift: shift,
            ..Default::default()
        };
        run(&ctx, |rec| {
            embedding::timestep_embedding(rec, &t, opts, &out)
        });
        let want = r::timestep_embedding(&t64, dim, flip, shift as f64, 10000.0, 1.0);
        let e = nmse(&out.to_f32(&ctx).unwrap(), &want);
        assert!(e <= 1e-7, "timestep embedding dim {dim}: nmse {e:e}");
    }
    assert_no_validation_errors();
}

#[test]
fn image_op_bad_inputs_are_errors() {
    let Some(ctx) = ctx() else { return };
    let x = upload(&ctx, &[1, 1, 4, 4], DType::F32, &[0.0; 16]);
    let o = empty(&ctx, &[1, 1, 4, 4], DType::F32);
    let mut rec = ctx.recorder().unwrap();
    let e = resample::upsample_nearest(&mut rec, &x, &o, (8, 8))
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("upsample_nearest") && e.contains("[1, 1, 4, 4]"),
        "{e}"
    );
    let e = blur::gaussian_blur(&mut rec, &x, 5.0, &o, &o)
        .unwrap_err()
        .to_string();
    assert!(e.contains("gaussian_blur") && e.contains("radius"), "{e}");
    let e = blur::gaussian_blur(&mut rec, &x, f32::NAN, &o, &o)
        .unwrap_err()
        .to_string();
    assert!(e.contains("sigma"), "{e}");
    let t16 = upload(&ctx, &[2], DType::F16, &[1.0, 2.0]);
    let e = embedding::timestep_embedding(&mut rec, &t16, Default::default(), &o)
        .unwrap_err()
        .to_string();
    assert!(e.contains("timestep_embedding"), "{e}");
    assert_eq!(rec.dispatch_count(), 0);
}

#[test]
fn warp_bilinear_matches_reference() {
    let Some(ctx) = ctx() else { return };
    // the render size, odd sizes, one row / one column
    for (n, c, h, w) in [
        (2usize, 3usize, 112usize, 200usize),
        (1, 3, 7, 13),
        (3, 2, 1, 9),
        (1, 1, 5, 1),
    ] {
        let x = uniform(n * c * h * w, 1.0, 5);
        // sources across the image and beyond: interior, the half-pixel borders, outside, and NO_SOURCE
        let g = uniform(n * h * w * 2, 1.0, 6);
        let mut grid = Vec::with_capacity(g.len());
        for (i, p) in g.chunks(2).enumerate() {
            let (sx, sy) = match i % 7 {
                0 => (-0.5, h as f32 - 0.5),
                1 => (w as f32 - 0.5, -0.5),
                2 => (-0.6, 0.0),
                3 => (warp::NO_SOURCE, warp::NO_SOURCE),
                _ => (
                    (p[0] + 1.0) / 2.0 * w as f32 - 0.5,
                    (p[1] + 1.0) / 2.0 * h as f32 - 0.5,
                ),
            };
            grid.extend([sx, sy]);
        }
        let (tx, tg, out) = (
            upload(&ctx, &[n, c, h, w], DType::F32, &x),
            upload(&ctx, &[n, h, w, 2], DType::F32, &grid),
            empty(&ctx, &[n, c, h, w], DType::F32),
        );
        run(&ctx, |rec| warp::warp_bilinear(rec, &tx, &tg, &out));
        let want = r::warp_bilinear(
            &stored(&x, DType::F32),
            &stored(&grid, DType::F32),
            n,
            c,
            h,
            w,
        );
        let e = nmse(&out.to_f32(&ctx).unwrap(), &want);
        assert!(e <= 1e-10, "warp {n}x{c}x{h}x{w}: nmse {e:e}");
    }
    // a grid of the wrong shape and f16 images are errors
    let x = upload(&ctx, &[1, 3, 4, 4], DType::F32, &[0.5; 48]);
    let bad = empty(&ctx, &[1, 4, 3, 2], DType::F32);
    let out = empty(&ctx, &[1, 3, 4, 4], DType::F32);
    let mut rec = ctx.recorder().unwrap();
    assert!(warp::warp_bilinear(&mut rec, &x, &bad, &out).is_err());
    let x16 = upload(&ctx, &[1, 3, 4, 4], DType::F16, &[0.5; 48]);
    let g = empty(&ctx, &[1, 4, 4, 2], DType::F32);
    assert!(warp::warp_bilinear(&mut rec, &x16, &g, &out).is_err());
    drop(rec);
    assert_no_validation_errors();
}
