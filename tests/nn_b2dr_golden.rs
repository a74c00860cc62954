//! The Bench2Drive-R ControlNet and frame against the PyTorch reference modules (python/b2dr_ref) on the same
//! weights and inputs (tests/golden/b2dr_*, written by tools/make_golden_b2dr.py).
//! Thresholds (normalised MSE, the acceptance): 1e-5 in f32, 1e-3 in f16.
mod common;
#[path = "golden/common.rs"]
mod golden;

use b2dr::nn::b2dr::{B2drControlNet, FrameTensors, RefRows};
use b2dr::nn::b2dr_config::B2drConfig;
use b2dr::nn::config::{UNetConfig, VaeConfig};
use b2dr::nn::device::{DeviceWeights, Fwd, Workspace};
use b2dr::nn::unet::UNet;
use b2dr::nn::vae::{VaeDecoder, VaeEncoder};
use b2dr::nn::weights::{expected_unet, expected_vae, HostTensor, Weights};
use b2dr::ops::reference::image as ref_image;
use b2dr::ops::warp;
use b2dr::render::frame::{B2drModel, FrameInputs, FrameRenderer, FrameShape, Prev, RefInputs};
use b2dr::sampling::{unipc, NoiseSchedule};
use b2dr::tensor::{DType, Tensor};
use b2dr::vk::Context;
use serde_json::Value;

const CASES: [(&str, usize, (usize, usize)); 2] = [
    ("b2dr_case_n1_7x13.safetensors", 1, (7, 13)),
    ("b2dr_case_n6_4x6.safetensors", 6, (4, 6)),
];

struct Golden {
    unet: Weights,
    control: Weights,
    vae: Weights,
    ucfg: UNetConfig,
    ccfg: B2drConfig,
    vcfg: VaeConfig,
}

fn golden() -> Golden {
    golden_with("b2dr_")
}

/// `prefix`: "b2dr_" (SD1.5's 4 latent channels) or "b2dr_z8_" (the design variant with 8).
fn golden_with(prefix: &str) -> Golden {
    let models: Value = golden::load_json(&format!("{prefix}models.json"));
    let ucfg = UNetConfig::from_json(models["configs"]["unet"].clone()).expect("unet config");
    let ccfg = B2drConfig::from_json(models["configs"]["controlnet"].clone()).expect("controlnet");
    let vcfg = VaeConfig::from_json(models["configs"]["vae"].clone()).expect("vae config");
    let load = |f: &str, exp: &[b2dr::nn::weights::Spec]| {
        Weights::load(&golden::golden_dir().join(f), exp)
            .unwrap_or_else(|e| panic!("{f}: {e:#}; {}", golden::REGENERATE))
    };
    Golden {
        unet: load(
            &format!("{prefix}weights_unet.safetensors"),
            &expected_unet(&ucfg),
        ),
        control: load(
            &format!("{prefix}weights_controlnet.safetensors"),
            &b2dr::nn::b2dr::expected_b2dr(&ccfg),
        ),
        vae: load(
            &format!("{prefix}weights_vae.safetensors"),
            &expected_vae(&vcfg),
        ),
        ucfg,
        ccfg,
        vcfg,
    }
}

struct Case(Weights);

impl Case {
    fn get(&self, n: &str) -> &HostTensor {
        self.0
            .get(n)
            .unwrap_or_else(|e| panic!("{e:#}; {}", golden::REGENERATE))
    }
    /// Uploads with `shape` (the golden's (N, 2, ...) tensors as (2N, ...)).
    fn up(&self, ctx: &Context, n: &str, dt: DType, shape: Option<&[usize]>) -> Tensor {
        let h = self.get(n);
        let s = shape.unwrap_or(&h.shape);
        Tensor::from_f32(ctx, s, dt, &h.data, n).unwrap()
    }
    /// (N, 2, rest...) -> (2N, rest...)
    fn pair_shape(&self, n: &str) -> Vec<usize> {
        let s = &self.get(n).shape;
        let mut v = vec![s[0] * s[1]];
        v.extend_from_slice(&s[2..]);
        v
    }
    fn context(&self, cams: usize) -> Vec<f32> {
        let c = self.get("in.context");
        if c.shape.len() == 2 {
            c.data.repeat(cams)
        } else {
            c.data.clone()
        }
    }
}

fn check(what: &str, got: &[f32], want: &HostTensor, tol: f64) -> f64 {
    let e = golden::nmse(got, &want.data);
    eprintln!("  {what}: nmse {e:.3e} (tol {tol:e})");
    assert!(
        e <= tol,
        "{what}: nmse {e:e} > {tol:e} against the PyTorch reference; {}",
        golden::REGENERATE
    );
    e
}

fn record<T>(
    ctx: &Context,
    ws: &mut Workspace,
    f: impl FnOnce(&mut Fwd) -> anyhow::Result<T>,
) -> T {
    let mut rec = ctx.recorder().unwrap();
    let out = f(&mut Fwd { rec: &mut rec, ws }).unwrap();
    rec.finish().unwrap().submit_wait().unwrap();
    out
}

fn tol(dt: DType) -> f64 {
    match dt {
        DType::F32 => 1e-5,
        DType::F16 => 1e-3,
    }
}

#[test]
fn b2dr_components_match_reference() {
    let Some(ctx) = common::ctx() else { return };
    let g = golden();
    for dt in [DType::F32, DType::F16] {
        let cdw = DeviceWeights::upload(&ctx, &g.control, "", dt).unwrap();
        let cn = B2drControlNet::load(&cdw, &g.ccfg).unwrap();
        for (file, n, _) in CASES {
            eprintln!("{file} {dt:?}");
            let c = Case(golden::golden_case(file));
            let mut ws = Workspace::new(&ctx, dt);
            let t = |c: &Case, name: &str| c.up(&ctx, name, dt, None);
            let locs = g.ccfg.ref_attn.len();
            // noise-level embedding (the golden's temb adds the time embedding of in.timestep)
            // (the golden gives the level per camera, all equal; the engine takes one per frame)
            let nls = &c.get("in.noise_level").data;
            assert!(
                nls.iter().all(|v| *v == nls[0]),
                "one noise level per frame"
            );
            let nl = Tensor::from_f32(&ctx, &[1], DType::F32, &nls[..1], "n").unwrap();
            let e = record(&ctx, &mut ws, |f| cn.noise_embedding(f, &nl));
            let want = c.get("out.noise_embedding.emb");
            check(
                "noise_embedding",
                &e.to_f32(&ctx).unwrap(),
                &HostTensor {
                    data: want.data[..e.numel()].to_vec(),
                    ..want.clone()
                },
                tol(dt),
            );
            // reference encoder, per Ref-Attn location
            let lat = c.up(
                &ctx,
                "out.ref_latents",
                dt,
                Some(&c.pair_shape("out.ref_latents")),
            );
            let feats = record(&ctx, &mut ws, |f| cn.ref_encoder().forward(f, &lat));
            for (j, at) in g.ccfg.ref_attn.iter().enumerate() {
                let fi = match at {
                    b2dr::nn::b2dr_config::RefAttnAt::Down(i) => &feats[*i],
                    b2dr::nn::b2dr_config::RefAttnAt::Mid => feats.last().unwrap(),
                };
                let name = format!("out.ref_encoder.features.{j}");
                assert_eq!(fi.shape(), &c.pair_shape(&name)[..], "{name}");
                check(&name, &fi.to_f32(&ctx).unwrap(), c.get(&name), tol(dt));
            }
            // PE MLP and one Ref-Attn per location (inputs from the golden)
            for j in 0..locs {
                let pe = cn.pos_embed(j).unwrap();
                let pcur_in = t(&c, &format!("in.pe_cur.{j}"));
                let pref_in = c.up(
                    &ctx,
                    &format!("in.pe_ref.{j}"),
                    dt,
                    Some(&c.pair_shape(&format!("in.pe_ref.{j}"))),
                );
                let pc = record(&ctx, &mut ws, |f| pe.forward(f, &pcur_in));
                let pr = record(&ctx, &mut ws, |f| pe.forward(f, &pref_in));
                check(
                    &format!("pos_embed.{j}.cur"),
                    &pc.to_f32(&ctx).unwrap(),
                    c.get(&format!("out.pos_embed.{j}.cur")),
                    tol(dt),
                );
                check(
                    &format!("pos_embed.{j}.ref"),
                    &pr.to_f32(&ctx).unwrap(),
                    c.get(&format!("out.pos_embed.{j}.ref")),
                    tol(dt),
                );
                let fname = format!("out.ref_encoder.features.{j}");
                let feat = c.up(&ctx, &fname, dt, Some(&c.pair_shape(&fname)));
                let ra = cn.ref_attn(j).unwrap();
                let h = t(&c, &format!("in.ref_attn.{j}.hidden"));
                let y = record(&ctx, &mut ws, |f| {
                    let kv = ra.prepare(f, &feat, &pr, &pc)?;
                    ra.forward(f, &h, &kv)
                });
                check(
                    &format!("ref_attn.{j}"),
                    &y.to_f32(&ctx).unwrap(),
                    c.get(&format!("out.ref_attn.{j}.hidden")),
                    tol(dt),
                );
            }
            // the whole ControlNet, with and without references, and the guided [no-ref; ref] batch
            let masks = t(&c, "in.masks");
            let pe_cur: Vec<Tensor> = (0..locs)
                .map(|j| t(&c, &format!("in.pe_cur.{j}")))
                .collect();
            let pe_ref: Vec<Tensor> = (0..locs)
                .map(|j| {
                    let nm = format!("in.pe_ref.{j}");
                    c.up(&ctx, &nm, dt, Some(&c.pair_shape(&nm)))
                })
                .collect();
            let x = t(&c, "in.x_t");
            let z = t(&c, "out.prev.z");
            let s = x.shape().to_vec();
            let x8 = Tensor::empty(&ctx, &[s[0], 8, s[2], s[3]], dt, "x8").unwrap();
            let ts = c.get("in.timestep").data[0];
            let tt = Tensor::from_f32(&ctx, &[n], DType::F32, &vec![ts; n], "t").unwrap();
            let cx = Tensor::from_f32(&ctx, &[n, 77, 32], dt, &c.context(n), "context").unwrap();
            let frame = record(&ctx, &mut ws, |f| {
                b2dr::ops::elementwise::concat_channels(f.rec, &x, &z, &x8)?;
                cn.prepare(
                    f,
                    &FrameTensors {
                        masks: &masks,
                        noise_level: &nl,
                        refs: Some((&lat, &pe_cur, &pe_ref)),
                    },
                )
            });
            let mut outs = vec![];
            for (rows, key) in [
                (RefRows::All, "controlnet_ref"),
                (RefRows::None, "controlnet_noref"),
            ] {
                let o = record(&ctx, &mut ws, |f| {
                    cn.forward(f, &x8, &tt, &cx, &frame, rows, 1.0)
                });
                for (k, d) in o.down.iter().enumerate() {
                    check(
                        &format!("{key}.down.{k}"),
                        &d.to_f32(&ctx).unwrap(),
                        c.get(&format!("out.{key}.down.{k}")),
                        tol(dt),
                    );
                }
                check(
                    &format!("{key}.mid"),
                    &o.mid.to_f32(&ctx).unwrap(),
                    c.get(&format!("out.{key}.mid")),
                    tol(dt),
                );
                outs.push(o);
            }
            // guided batch: the second half is the reference model, the first exactly the no-reference one
            // run in the same batch
            let x16 = Tensor::empty(&ctx, &[2 * n, 8, s[2], s[3]], dt, "x16").unwrap();
            let t2 = Tensor::from_f32(&ctx, &[2 * n], DType::F32, &vec![ts; 2 * n], "t2").unwrap();
            let cx2 = Tensor::from_f32(&ctx, &[2 * n, 77, 32], dt, &c.context(n).repeat(2), "cx2")
                .unwrap();
            record(&ctx, &mut ws, |f| {
                b2dr::ops::elementwise::concat_channels(
                    f.rec,
                    &x8.reshape(&[1, n * 8 * s[2] * s[3], 1, 1])?,
                    &x8.reshape(&[1, n * 8 * s[2] * s[3], 1, 1])?,
                    &x16.reshape(&[1, 2 * n * 8 * s[2] * s[3], 1, 1])?,
                )
            });
            let og = record(&ctx, &mut ws, |f| {
                cn.forward(f, &x16, &t2, &cx2, &frame, RefRows::SecondHalf, 1.0)
            });
            let on = record(&ctx, &mut ws, |f| {
                cn.forward(f, &x16, &t2, &cx2, &frame, RefRows::None, 1.0)
            });
            for k in 0..og.down.len() {
                let (a, b) = (
                    og.down[k].to_f32(&ctx).unwrap(),
                    on.down[k].to_f32(&ctx).unwrap(),
                );
                let half = a.len() / 2;
                assert_eq!(
                    a[..half],
                    b[..half],
                    "guided batch: the no-ref half of down.{k} differs from the no-ref model"
                );
                let r = outs[0].down[k].to_f32(&ctx).unwrap();
                let e = golden::nmse(&a[half..], &r);
                assert!(
                    e <= 1e-10,
                    "guided batch: the ref half of down.{k} differs from the ref model: {e:e}"
                );
            }
            let d = golden::nmse(
                &outs[0].mid.to_f32(&ctx).unwrap(),
                &outs[1].mid.to_f32(&ctx).unwrap(),
            );
            assert!(
                d > 1e-6,
                "references change nothing (mid nmse {d:e}): the test would not see them"
            );
        }
    }
    common::assert_no_validation_errors();
}

struct Dev {
    unet: UNet,
    cn: B2drControlNet,
    enc: VaeEncoder,
    dec: VaeDecoder,
    _w: Vec<DeviceWeights>,
}

fn device_model(ctx: &Context, g: &Golden, dt: DType) -> Dev {
    let u = DeviceWeights::upload(ctx, &g.unet, "", dt).unwrap();
    let c = DeviceWeights::upload(ctx, &g.control, "", dt).unwrap();
    let v = DeviceWeights::upload(ctx, &g.vae, "", DType::F32).unwrap();
    Dev {
        unet: UNet::load(&u, &g.ucfg).unwrap(),
        cn: B2drControlNet::load(&c, &g.ccfg).unwrap(),
        enc: VaeEncoder::load(&v, &g.vcfg).unwrap(),
        dec: VaeDecoder::load(&v, &g.vcfg).unwrap(),
        _w: vec![u, c, v],
    }
}

#[allow(clippy::too_many_arguments)]
fn renderer(
    ctx: &Context,
    g: &Golden,
    d: &Dev,
    c: &Case,
    n: usize,
    w: f64,
    dt: DType,
    x0_base_prev: bool,
) -> FrameRenderer {
    let img = &c.get("in.masks").shape;
    let m = B2drModel {
        unet: &d.unet,
        control: &d.cn,
        vae_encoder: &d.enc,
        vae_decoder: &d.dec,
        scaling_factor: g.vcfg.scaling_factor,
        dtype: dt,
        x0_base_prev,
    };
    let plan = unipc::plan(&NoiseSchedule::sd15(), &Default::default(), 3).unwrap();
    FrameRenderer::new(
        ctx,
        &m,
        FrameShape {
            cameras: n,
            size: (img[2], img[3]),
            refs: true,
            ref_guidance: w,
            out_size: None,
            prev_noise_level: None,
            prev_blur_sigma: None,
        },
        &c.context(n),
        plan,
    )
    .unwrap()
}

fn inputs<'a>(c: &'a Case, locs: usize) -> FrameInputs<'a> {
    FrameInputs {
        masks: &c.get("in.masks").data,
        prev: Prev::Image(&c.get("in.prev_image").data),
        refs: Some(RefInputs {
            images: &c.get("in.ref_images").data,
            pe_cur: (0..locs)
                .map(|j| &c.get(&format!("in.pe_cur.{j}")).data[..])
                .collect(),
            pe_ref: (0..locs)
                .map(|j| &c.get(&format!("in.pe_ref.{j}")).data[..])
                .collect(),
        }),
        x_t: &c.get("in.x_T").data,
        eps_prev: &c.get("in.eps_prev").data,
        prev_warp: None,
    }
}

#[test]
fn b2dr_frame_matches_reference() {
    frame_matches(&golden(), &CASES);
}

/// The design variant whose VAE has 8 latent channels (UNet in / out 8, ControlNet in_channels 16): the whole
/// frame (prev chain, reference encoder, guided sampling, decode) against the PyTorch modules.
#[test]
fn b2dr_frame_with_8_latent_channels_matches_reference() {
    let g = golden_with("b2dr_z8_");
    assert_eq!(g.vcfg.latent_channels, 8);
    assert_eq!(g.ccfg.latent_channels(), 8);
    frame_matches(&g, &[("b2dr_z8_case_n1_7x13.safetensors", 1, (7, 13))]);
}

fn frame_matches(g: &Golden, cases: &[(&str, usize, (usize, usize))]) {
    let Some(ctx) = common::ctx() else { return };
    let locs = g.ccfg.ref_attn.len();
    for dt in [DType::F32, DType::F16] {
        let d = device_model(&ctx, g, dt);
        for &(file, n, _) in cases {
            eprintln!("{file} {dt:?}");
            let c = Case(golden::golden_case(file));
            let mut ws = [2.0, 1.0].to_vec();
            if c.0.get("out.frame_w1.image").is_err() {
                ws.truncate(1);
            }
            for w in ws {
                let key = if w == 2.0 { "frame_w2" } else { "frame_w1" };
                let r = renderer(&ctx, g, &d, &c, n, w, dt, false);
                r.render(&inputs(&c, locs)).unwrap();
                // the previous-frame chain: blur -> encode -> noise
                check(
                    &format!("{key} prev z"),
                    &r.prev_latent().unwrap(),
                    c.get("out.prev.z"),
                    tol(dt),
                );
                let img = r.image().unwrap();
                check(
                    &format!("{key} image"),
                    &img,
                    c.get(&format!("out.{key}.image")),
                    tol(dt),
                );
                check(
                    &format!("{key} latent"),
                    &r.latent().unwrap(),
                    c.get(&format!("out.{key}.latent.2")),
                    tol(dt),
                );
                // the same inputs again: bit-identical
                r.render(&inputs(&c, locs)).unwrap();
                assert_eq!(r.image().unwrap(), img, "{key}: a rerun differs");
            }
        }
    }
    common::assert_no_validation_errors();
}

/// b2dr.json x0_base "prev": the same sampling loop as the reference (the sampled latent is the golden one),
/// the base is the previous frame's clean latent (the golden noised latent with its noise taken out), and the
/// frame is the VAE decode of latent + base; "no previous frame" zeroes the base.
#[test]
fn x0_base_prev_decodes_the_sampled_residual_plus_the_previous_latent() {
    let Some(ctx) = common::ctx() else { return };
    let g = golden();
    let locs = g.ccfg.ref_attn.len();
    let (file, n, _) = CASES[0];
    let c = Case(golden::golden_case(file));
    let d = device_model(&ctx, &g, DType::F32);
    let r = renderer(&ctx, &g, &d, &c, n, 2.0, DType::F32, true);
    r.render(&inputs(&c, locs)).unwrap();
    check(
        "x0 base: sampled latent",
        &r.latent().unwrap(),
        c.get("out.frame_w2.latent.2"),
        tol(DType::F32),
    );
    // z_clean = (z_noised - sqrt(1 - abar) eps_prev) / sqrt(abar)
    let a = r.prev_alpha_bar();
    let eps = &c.get("in.eps_prev").data;
    let want: Vec<f32> = c
        .get("out.prev.z")
        .data
        .iter()
        .zip(eps)
        .map(|(z, e)| ((*z as f64 - (1.0 - a).sqrt() * *e as f64) / a.sqrt()) as f32)
        .collect();
    let base = r.base_latent().unwrap().expect("a base");
    let e = golden::nmse(&base, &want);
    assert!(e <= 1e-6, "base latent nmse {e:e}");
    assert!(
        base.iter().any(|v| v.abs() > 1e-3),
        "a zero base would test nothing"
    );
    // the decode of latent + base, written out
    let lat = r.latent().unwrap();
    let (lc, h, w) = r.latent_size();
    let s = g.vcfg.scaling_factor;
    let z: Vec<f32> = lat
        .iter()
        .zip(&base)
        .map(|(x, b)| ((*x as f64 + *b as f64) / s) as f32)
        .collect();
    let zt = Tensor::from_f32(&ctx, &[n, lc, h, w], DType::F32, &z, "z").unwrap();
    let mut ws = Workspace::new(&ctx, DType::F32);
    let dec = record(&ctx, &mut ws, |f| d.dec.forward(f, &zt));
    let want_img: Vec<f32> = dec
        .to_f32(&ctx)
        .unwrap()
        .iter()
        .map(|v| (v / 2.0 + 0.5).clamp(0.0, 1.0))
        .collect();
    let img = r.image().unwrap();
    let e = golden::nmse(&img, &want_img);
    assert!(e <= 1e-10, "image vs decode(latent + base): nmse {e:e}");
    // (the golden's random VAE maps most latents near one colour: the base moves the image little, but far
    // more than the tolerance above)
    let plain = golden::nmse(&img, &c.get("out.frame_w2.image").data);
    assert!(
        plain > 1e3 * e.max(1e-12),
        "the base changed nothing (nmse {plain:e} to the plain frame, {e:e} to decode(latent + base))"
    );
    // no previous frame: the base is zero
    let mut x = inputs(&c, locs);
    x.prev = Prev::None;
    r.render(&x).unwrap();
    assert!(r.base_latent().unwrap().unwrap().iter().all(|v| *v == 0.0));
    common::assert_no_validation_errors();
}

/// A B2D-R ControlNet whose new outputs are zero (conv_in's previous-latent channels, the noise-level
/// embedding's last layer, every Ref-Attn output projection) equals the plain ControlNet on the shared weights,
/// with references and any previous latent.
#[test]
fn fresh_b2dr_equals_plain_controlnet() {
    use b2dr::nn::config::ControlNetConfig;
    use b2dr::nn::controlnet::ControlNet;
    let Some(ctx) = common::ctx() else { return };
    let g = golden();
    let mut b = g.control.clone();
    let ci = b.tensors.get_mut("conv_in.weight").unwrap();
    let (o, i) = (ci.shape[0], ci.shape[1]);
    assert_eq!(i, 8);
    let mut plain_conv_in = vec![];
    for oc in 0..o {
        for ic in 0..8 {
            let k = &mut ci.data[(oc * 8 + ic) * 9..(oc * 8 + ic + 1) * 9];
            if ic < 4 {
                plain_conv_in.extend_from_slice(k);
            } else {
                k.fill(0.0);
            }
        }
    }
    for (name, t) in b.tensors.iter_mut() {
        if name.starts_with("noise_embedding.linear_2")
            || (name.starts_with("ref_attn.") && name.contains("to_out"))
        {
            t.data.fill(0.0);
        }
    }
    let mut pcfg: ControlNetConfig = g.ccfg.base.clone();
    pcfg.enc.in_channels = 4;
    let mut plain = Weights::default();
    for (name, spec) in b2dr::nn::weights::expected_controlnet(&pcfg) {
        let mut t = b.get(&name).unwrap().clone();
        if name == "conv_in.weight" {
            t.shape = spec.clone();
            t.data = plain_conv_in.clone();
        }
        plain.tensors.insert(name, t);
    }
    let c = Case(golden::golden_case(CASES[0].0));
    let dt = DType::F32;
    let bdw = DeviceWeights::upload(&ctx, &b, "", dt).unwrap();
    let pdw = DeviceWeights::upload(&ctx, &plain, "", dt).unwrap();
    let bn = B2drControlNet::load(&bdw, &g.ccfg).unwrap();
    let pn = ControlNet::load(&pdw, &pcfg).unwrap();
    let mut ws = Workspace::new(&ctx, dt);
    let t = |name: &str| c.up(&ctx, name, dt, None);
    let (x, z, masks) = (t("in.x_t"), t("out.prev.z"), t("in.masks"));
    let s = x.shape().to_vec();
    let x8 = Tensor::empty(&ctx, &[1, 8, s[2], s[3]], dt, "x8").unwrap();
    let tt = Tensor::from_f32(&ctx, &[1], DType::F32, &c.get("in.timestep").data, "t").unwrap();
    let cx = Tensor::from_f32(&ctx, &[1, 77, 32], dt, &c.context(1), "cx").unwrap();
    let nl = Tensor::from_f32(&ctx, &[1], DType::F32, &[200.0], "n").unwrap();
    let locs = g.ccfg.ref_attn.len();
    let lat = c.up(
        &ctx,
        "out.ref_latents",
        dt,
        Some(&c.pair_shape("out.ref_latents")),
    );
    let pe_cur: Vec<Tensor> = (0..locs).map(|j| t(&format!("in.pe_cur.{j}"))).collect();
    let pe_ref: Vec<Tensor> = (0..locs)
        .map(|j| {
            let nm = format!("in.pe_ref.{j}");
            c.up(&ctx, &nm, dt, Some(&c.pair_shape(&nm)))
        })
        .collect();
    let ob = record(&ctx, &mut ws, |f| {
        b2dr::ops::elementwise::concat_channels(f.rec, &x, &z, &x8)?;
        let fr = bn.prepare(
            f,
            &FrameTensors {
                masks: &masks,
                noise_level: &nl,
                refs: Some((&lat, &pe_cur, &pe_ref)),
            },
        )?;
        bn.forward(f, &x8, &tt, &cx, &fr, RefRows::All, 0.7)
    });
    let op = record(&ctx, &mut ws, |f| pn.forward(f, &x, &tt, &cx, &masks, 0.7));
    for (k, (a, p)) in ob.down.iter().zip(&op.down).enumerate() {
        let (a, p) = (a.to_f32(&ctx).unwrap(), p.to_f32(&ctx).unwrap());
        let e = golden::nmse(&a, &p);
        assert!(
            e <= 1e-12,
            "down.{k}: the fresh B2D-R ControlNet differs from the plain one: {e:e}"
        );
    }
    let e = golden::nmse(&ob.mid.to_f32(&ctx).unwrap(), &op.mid.to_f32(&ctx).unwrap());
    assert!(e <= 1e-12, "mid: {e:e}");
    common::assert_no_validation_errors();
}

/// The PETR geometry of src/projection/pe.rs (through render::inputs::geometry) equals the golden's
/// position-encoding inputs, which python/b2dr_ref/pe.py computed from the same camera matrices.
#[test]
fn position_encodings_match_python_port() {
    use b2dr::projection::geometry::{mat3_from_rows, mat4_from_rows};
    use b2dr::scene::camera::Camera;
    let g = golden();
    for (file, n, (h, w)) in CASES {
        let c = Case(golden::golden_case(file));
        let m4 = |d: &[f32]| {
            let mut r = [[0.0f64; 4]; 4];
            for (i, v) in d.iter().enumerate() {
                r[i / 4][i % 4] = *v as f64;
            }
            mat4_from_rows(&r)
        };
        let cur = m4(&c.get("in.geom.cur_ego2global").data);
        let mut per_cam = vec![];
        for k in 0..n {
            let kd = &c.get("in.geom.k_render").data[k * 9..(k + 1) * 9];
            let mut r = [[0.0f64; 3]; 3];
            for (i, v) in kd.iter().enumerate() {
                r[i / 3][i % 3] = *v as f64;
            }
            let cam = Camera {
                name: format!("cam{k}"),
                intrinsic: mat3_from_rows(&r),
                cam2ego: m4(&c.get("in.geom.cam2ego").data[k * 16..(k + 1) * 16]),
                width: (8 * w) as u32,
                height: (8 * h) as u32,
                distortion: [0.0; 5],
            };
            let rd = &c.get("in.geom.ref_ego2global").data;
            let (a, b) = (
                m4(&rd[k * 32..k * 32 + 16]),
                m4(&rd[k * 32 + 16..k * 32 + 32]),
            );
            per_cam.push(
                b2dr::render::inputs::geometry(&g.ccfg, &cam, (8 * h, 8 * w), &cur, [&a, &b])
                    .unwrap(),
            );
        }
        let geo = b2dr::render::inputs::stack(&per_cam);
        for j in 0..g.ccfg.ref_attn.len() {
            check(
                &format!("{file} pe_cur.{j}"),
                &geo.pe_cur[j],
                c.get(&format!("in.pe_cur.{j}")),
                1e-10,
            );
            check(
                &format!("{file} pe_ref.{j}"),
                &geo.pe_ref[j],
                c.get(&format!("in.pe_ref.{j}")),
                1e-10,
            );
        }
    }
}

/// A model that warps its previous frame (b2dr.json prev_warp_max_depth > 0): the frame's previous-frame chain
/// encodes the previous image sampled at the given grid (against the f64 reference warp of the image fed to the
/// plain model), and without a grid keeps the image as given (the plain model's chain, bit for bit).
#[test]
fn warped_previous_frame_is_the_reference_warp_of_the_image() {
    let Some(ctx) = common::ctx() else { return };
    let g = golden();
    let locs = g.ccfg.ref_attn.len();
    let (file, n, _) = CASES[0];
    let c = Case(golden::golden_case(file));
    let (ih, iw) = {
        let s = &c.get("in.masks").shape;
        (s[2], s[3])
    };
    let plain = device_model(&ctx, &g, DType::F32);
    let mut wcfg = g.ccfg.clone();
    wcfg.prev_warp_max_depth = 30.0;
    let cw = DeviceWeights::upload(&ctx, &g.control, "", DType::F32).unwrap();
    let warping = Dev {
        unet: UNet::load(&plain._w[0], &g.ucfg).unwrap(),
        cn: B2drControlNet::load(&cw, &wcfg).unwrap(),
        enc: VaeEncoder::load(&plain._w[2], &g.vcfg).unwrap(),
        dec: VaeDecoder::load(&plain._w[2], &g.vcfg).unwrap(),
        _w: vec![cw],
    };
    let rp = renderer(&ctx, &g, &plain, &c, n, 2.0, DType::F32, false);
    let rw = renderer(&ctx, &g, &warping, &c, n, 2.0, DType::F32, false);
    // no grid: the image as given
    rp.render(&inputs(&c, locs)).unwrap();
    rw.render(&inputs(&c, locs)).unwrap();
    assert_eq!(rw.prev_latent().unwrap(), rp.prev_latent().unwrap());
    // a grid: sub-pixel shifts, one point on the border, one outside (keeps its pixel)
    let mut grid = vec![];
    for y in 0..ih {
        for x in 0..iw {
            let (gx, gy) = match (y * iw + x) % 5 {
                3 => (-0.5, y as f32),
                4 => (warp::NO_SOURCE, warp::NO_SOURCE),
                _ => (x as f32 * 0.83 + 0.61, y as f32 * 0.9 + 0.37),
            };
            grid.extend([gx, gy]);
        }
    }
    let grid: Vec<f32> = grid.repeat(n);
    let prev = &c.get("in.prev_image").data;
    let wanted = ref_image::warp_bilinear(
        &prev.iter().map(|v| *v as f64).collect::<Vec<_>>(),
        &grid.iter().map(|v| *v as f64).collect::<Vec<_>>(),
        n,
        3,
        ih,
        iw,
    );
    assert!(
        golden::nmse(&wanted.iter().map(|v| *v as f32).collect::<Vec<_>>(), prev) > 1e-3,
        "the grid must move the image for the check to mean anything"
    );
    let mut x = inputs(&c, locs);
    x.prev_warp = Some(&grid);
    rw.render(&x).unwrap();
    let moved: Vec<f32> = wanted.iter().map(|v| *v as f32).collect();
    let mut y = inputs(&c, locs);
    y.prev = Prev::Image(&moved);
    rp.render(&y).unwrap();
    let e = golden::nmse(&rw.prev_latent().unwrap(), &rp.prev_latent().unwrap());
    assert!(
        e <= 1e-10,
        "warped chain vs the reference warp fed as given: nmse {e:e}"
    );
    // a grid for a model that does not warp is an error, not ignored
    let err = rp.render(&x).unwrap_err();
    assert!(format!("{err:#}").contains("does not warp"), "{err:#}");
    common::assert_no_validation_errors();
}
