//! The guided sampling loop golden (b2dr-tiny UNet + ControlNet, UniPC 5 steps, guidance 7.5, latent 7 x 13):
//! the host sampler plan with classifier-free guidance folded in, fed with diffusers' own per-step model
//! outputs, reproduces diffusers' latents; and the golden EXR holds the decoded image.

#[path = "golden/common.rs"]
mod common;

use b2dr::nn::weights::Weights;
use b2dr::sampling::cpu::CpuSampler;
use b2dr::sampling::unipc::{self, UniPcConfig};
use b2dr::sampling::{Buf, NoiseSchedule};
use common::*;

fn loop_file() -> (serde_json::Value, Weights) {
    let g = load_json("models.json");
    let f = g["loop"]["file"].as_str().unwrap().to_string();
    let bytes =
        std::fs::read(golden_dir().join(&f)).unwrap_or_else(|e| panic!("{f}: {e}; {REGENERATE}"));
    (g, Weights::from_bytes_unchecked(&bytes, &f).unwrap())
}

#[test]
fn guided_unipc_loop_matches_diffusers() {
    let (g, w) = loop_file();
    let l = &g["loop"];
    let steps = l["steps"].as_u64().unwrap() as usize;
    let scale = l["guidance_scale"].as_f64().unwrap();
    let plan = unipc::plan(&NoiseSchedule::sd15(), &UniPcConfig::default(), steps).unwrap();
    assert_eq!(plan.timesteps, i64s(&l["timesteps"]), "{REGENERATE}");
    let plan = plan.with_guidance(scale);
    let mut s = CpuSampler::new(w.get("in.x_T").unwrap().data.clone());
    let mut worst: f64 = 0.0;
    for (i, step) in plan.steps.iter().enumerate() {
        s.set(
            Buf::EpsUncond,
            w.get(&format!("out.eps_uncond_{i}")).unwrap().data.clone(),
        )
        .unwrap();
        s.set(
            Buf::EpsCond,
            w.get(&format!("out.eps_cond_{i}")).unwrap().data.clone(),
        )
        .unwrap();
        s.apply(step).unwrap();
        let want = &w.get(&format!("out.latent_{i}")).unwrap().data;
        worst = worst.max(nmse(s.sample(), want));
        assert_close(
            &format!("guided loop latent after step {i}"),
            s.sample(),
            want,
            1e-5,
        );
    }
    println!("guided UniPC loop: worst per-step nMSE {worst:.3e}");
}

#[test]
fn golden_exr_holds_the_decoded_image() {
    let (g, w) = loop_file();
    let Some(exr_name) = g["loop"]["exr"].as_str() else {
        println!("skipped: the golden generator had no OpenEXR package");
        return;
    };
    let img = w.get("out.image").unwrap(); // (1, 3, H, W) in [0, 1]
    let (h, wd) = (img.shape[2], img.shape[3]);
    let path = golden_dir().join(exr_name);
    let read = exr::prelude::read_first_rgba_layer_from_file(
        &path,
        |res, _| vec![[0f32; 3]; res.width() * res.height()],
        move |px: &mut Vec<[f32; 3]>, pos, (r, g, b, _a): (f32, f32, f32, f32)| {
            px[pos.y() * wd + pos.x()] = [r, g, b];
        },
    )
    .unwrap_or_else(|e| panic!("{}: {e}; {REGENERATE}", path.display()));
    let size = read.layer_data.size;
    assert_eq!((size.height(), size.width()), (h, wd));
    let px = &read.layer_data.channel_data.pixels;
    let mut max_err: f32 = 0.0;
    for (i, p) in px.iter().enumerate() {
        for (c, got) in p.iter().enumerate() {
            let want = img.data[c * h * wd + i];
            max_err = max_err.max((got - want).abs());
        }
    }
    assert!(
        max_err <= 1e-6,
        "EXR differs from the stored image by {max_err}; {REGENERATE}"
    );
}
