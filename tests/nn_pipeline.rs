//! The planned sampling pipeline against diffusers' own guided loop (b2dr-tiny, UniPC 5 steps, guidance 7.5,
//! ControlNet, VAE decode), plus determinism, long f16 rollouts with strong guidance, and 1-step schedules.
mod common;
#[path = "golden/common.rs"]
mod golden;

use b2dr::nn::config::{ControlNetConfig, UNetConfig, VaeConfig};
use b2dr::nn::controlnet::ControlNet;
use b2dr::nn::device::DeviceWeights;
use b2dr::nn::pipeline::{Pipeline, PipelineShape};
use b2dr::nn::unet::UNet;
use b2dr::nn::vae::VaeDecoder;
use b2dr::nn::weights::{self, Weights};
use b2dr::sampling::{unipc, NoiseSchedule};
use b2dr::tensor::DType;
use b2dr::vk::Context;

struct Tiny {
    unet: UNet,
    control: ControlNet,
    vae: VaeDecoder,
    scaling: f64,
    _w: Vec<DeviceWeights>,
}

fn tiny(ctx: &Context, dtype: DType) -> Tiny {
    let (uc, cc, vc) = (
        UNetConfig::b2dr_tiny(),
        ControlNetConfig::b2dr_tiny(),
        VaeConfig::b2dr_tiny(),
    );
    // Same seeds as the goldens' "tiny" set (models.json): unet 1, controlnet 2, vae 3.
    let m = golden::load_json("models.json");
    let seed = |k: &str| m["sets"]["tiny"]["weights"][k]["seed"].as_u64().unwrap();
    let uw = DeviceWeights::upload(
        ctx,
        &Weights::random(&weights::expected_unet(&uc), seed("unet")),
        "",
        dtype,
    )
    .unwrap();
    let cw = DeviceWeights::upload(
        ctx,
        &Weights::random(&weights::expected_controlnet(&cc), seed("controlnet")),
        "",
        dtype,
    )
    .unwrap();
    let vw = DeviceWeights::upload(
        ctx,
        &Weights::random(&weights::expected_vae(&vc), seed("vae")),
        "",
        DType::F32,
    )
    .unwrap();
    Tiny {
        unet: UNet::load(&uw, &uc).unwrap(),
        control: ControlNet::load(&cw, &cc).unwrap(),
        vae: VaeDecoder::load(&vw, &vc).unwrap(),
        scaling: vc.scaling_factor,
        _w: vec![uw, cw, vw],
    }
}

#[test]
fn guided_unipc_loop_matches_diffusers() {
    let Some(ctx) = common::ctx() else { return };
    let m = golden::load_json("models.json");
    let lp = &m["loop"];
    let bytes = std::fs::read(golden::golden_dir().join(lp["file"].as_str().unwrap())).unwrap();
    let io = Weights::from_bytes_unchecked(&bytes, "loop")
        .unwrap()
        .tensors;
    let steps = lp["steps"].as_u64().unwrap() as usize;
    let plan = unipc::plan(&NoiseSchedule::sd15(), &Default::default(), steps).unwrap();
    let want_ts: Vec<i64> = golden::i64s(&lp["timesteps"]);
    assert_eq!(plan.timesteps, want_ts);
    let t = tiny(&ctx, DType::F32);
    let shape = PipelineShape {
        batch: 1,
        latent: (7, 13),
        context: (77, 64),
        guidance: Some(lp["guidance_scale"].as_f64().unwrap()),
        conditioning_scale: lp["conditioning_scale"].as_f64().unwrap() as f32,
    };
    let p = Pipeline::new(
        &ctx,
        &t.unet,
        Some(&t.control),
        Some((&t.vae, t.scaling)),
        DType::F32,
        shape,
        plan,
    )
    .unwrap();
    let out = p
        .run(
            &io["in.x_T"].data,
            &io["in.context_uncond"].data,
            &io["in.context_cond"].data,
            Some(&io["in.cond_image"].data),
            true,
            None,
        )
        .unwrap();
    for (i, l) in out.latents.iter().enumerate() {
        golden::assert_close(
            &format!("latent after step {i}"),
            l,
            &io[&format!("out.latent_{i}")].data,
            1e-5,
        );
    }
    golden::assert_close("decoded image", &out.image, &io["out.image"].data, 1e-5);
    // per-pixel bound on the decoded image
    let maxd = out
        .image
        .iter()
        .zip(&io["out.image"].data)
        .map(|(a, b)| (a - b).abs())
        .fold(0.0f32, f32::max);
    assert!(
        maxd < 1e-3,
        "decoded image: max per-pixel difference {maxd}"
    );
    common::assert_no_validation_errors();
}

#[test]
fn same_seed_same_device_is_bitwise_identical_and_extremes_stay_finite() {
    let Some(ctx) = common::ctx() else { return };
    let t = tiny(&ctx, DType::F16);
    let shape = |g| PipelineShape {
        batch: 1,
        latent: (4, 7),
        context: (77, 64),
        guidance: g,
        conditioning_scale: 1.0,
    };
    let x = common::uniform(4 * 4 * 7, 1.5, 1);
    let c = common::uniform(77 * 64, 1.0, 2);
    let u = common::uniform(77 * 64, 1.0, 3);
    let img = common::uniform(3 * 32 * 56, 1.0, 4);
    // 100 steps, f16 model, guidance 30: no NaN/Inf.
    let plan = unipc::plan(&NoiseSchedule::sd15(), &Default::default(), 100).unwrap();
    let p = Pipeline::new(
        &ctx,
        &t.unet,
        Some(&t.control),
        Some((&t.vae, t.scaling)),
        DType::F16,
        shape(Some(30.0)),
        plan,
    )
    .unwrap();
    let a = p.run(&x, &u, &c, Some(&img), false, None).unwrap();
    assert!(
        a.latents[0].iter().chain(&a.image).all(|v| v.is_finite()),
        "NaN/Inf after 100 f16 steps at guidance 30"
    );
    // Replaying the same plan gives bit-identical results.
    let b = p.run(&x, &u, &c, Some(&img), false, None).unwrap();
    assert_eq!(
        a.latents[0].iter().map(|v| v.to_bits()).collect::<Vec<_>>(),
        b.latents[0].iter().map(|v| v.to_bits()).collect::<Vec<_>>()
    );
    assert_eq!(
        a.image.iter().map(|v| v.to_bits()).collect::<Vec<_>>(),
        b.image.iter().map(|v| v.to_bits()).collect::<Vec<_>>()
    );
    // 1-step schedule without guidance.
    let plan1 = unipc::plan(&NoiseSchedule::sd15(), &Default::default(), 1).unwrap();
    let p1 = Pipeline::new(
        &ctx,
        &t.unet,
        Some(&t.control),
        None,
        DType::F16,
        shape(None),
        plan1,
    )
    .unwrap();
    let o = p1.run(&x, &[], &c, Some(&img), false, None).unwrap();
    assert!(o.latents[0].iter().all(|v| v.is_finite()));
    common::assert_no_validation_errors();
}
