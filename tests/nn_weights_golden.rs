//! Weights: the expected tensor lists against diffusers' own state_dicts (from the goldens), loading the
//! goldens' weight and case files, the shared seeded generator (fingerprints from tools/make_golden.py),
//! and every kind of loading error (missing, extra, mis-shaped, truncated, dtype).

#[path = "golden/common.rs"]
mod common;

use b2dr::nn::config::{ControlNetConfig, UNetConfig, VaeConfig};
use b2dr::nn::weights::{
    expected_controlnet, expected_unet, expected_vae, FileDType, Spec, Weights,
};
use common::*;
use serde_json::Value;
use std::collections::BTreeMap;

fn expected_for(kind: &str, cfg: &Value) -> Vec<Spec> {
    match kind {
        "unet" => expected_unet(&UNetConfig::from_json(cfg.clone()).unwrap()),
        "controlnet" => expected_controlnet(&ControlNetConfig::from_json(cfg.clone()).unwrap()),
        "vae" => expected_vae(&VaeConfig::from_json(cfg.clone()).unwrap()),
        other => panic!("unknown component {other}"),
    }
}

fn sorted(v: Vec<Spec>) -> BTreeMap<String, Vec<usize>> {
    v.into_iter().collect()
}

#[test]
fn expected_names_match_diffusers_state_dicts() {
    let g = load_json("models.json");
    for (set, e) in g["sets"].as_object().unwrap() {
        for (kind, cfg) in e["configs"].as_object().unwrap() {
            let ours = sorted(expected_for(kind, cfg));
            let theirs: BTreeMap<String, Vec<usize>> = e["state_dicts"][kind]
                .as_array()
                .unwrap()
                .iter()
                .map(|p| {
                    (
                        p[0].as_str().unwrap().to_string(),
                        p[1].as_array()
                            .unwrap()
                            .iter()
                            .map(|x| x.as_u64().unwrap() as usize)
                            .collect(),
                    )
                })
                .collect();
            for (n, s) in &theirs {
                assert_eq!(
                    ours.get(n),
                    Some(s),
                    "{set} {kind}: diffusers tensor `{n}` {s:?}; {REGENERATE}"
                );
            }
            assert_eq!(
                ours.len(),
                theirs.len(),
                "{set} {kind}: b2dr lists tensors diffusers does not have"
            );
        }
    }
}

#[test]
fn golden_weight_files_load_with_checks() {
    let g = load_json("models.json");
    let mut loaded = 0;
    for (set, e) in g["sets"].as_object().unwrap() {
        for (kind, w) in e["weights"].as_object().unwrap() {
            if let Some(f) = w["file"].as_str() {
                let exp = expected_for(kind, &e["configs"][kind]);
                let wt = Weights::load(&golden_dir().join(f), &exp)
                    .unwrap_or_else(|err| panic!("{set} {kind}: {err:#}; {REGENERATE}"));
                assert!(wt.tensors.values().all(|t| t.file_dtype == FileDType::F32));
                loaded += 1;
            }
        }
    }
    assert!(loaded >= 4);
}

#[test]
fn seeded_generator_matches_the_goldens_bit_for_bit() {
    let g = load_json("models.json");
    let e = &g["sets"]["tiny"];
    for kind in ["unet", "controlnet", "vae"] {
        let w = &e["weights"][kind];
        let seed = w["seed"].as_u64().unwrap();
        let exp = expected_for(kind, &e["configs"][kind]);
        let ours = Weights::random(&exp, seed);
        let fps = w["fingerprints"].as_object().unwrap();
        assert_eq!(fps.len(), ours.tensors.len());
        for (name, t) in &ours.tensors {
            let want: u64 = fps[name].as_str().unwrap().parse().unwrap();
            assert_eq!(
                Weights::fingerprint(t),
                want,
                "b2dr-tiny {kind} `{name}` differs from the golden; {REGENERATE}"
            );
        }
    }
}

#[test]
fn golden_weight_helper_covers_every_set() {
    let g = load_json("models.json");
    for (set, e) in g["sets"].as_object().unwrap() {
        for kind in e["configs"].as_object().unwrap().keys() {
            assert!(!golden_weights(&g, set, kind).tensors.is_empty());
        }
    }
    let c = golden_case("case_tiny_7x13.safetensors");
    let moments = c.get("out.vae_encoder.moments").unwrap();
    let mean = c.get("out.vae_encoder.mean").unwrap();
    // mean = first `latent_channels` channels of the moments, per batch item
    let (b, ch2, hw) = (
        moments.shape[0],
        moments.shape[1],
        moments.shape[2] * moments.shape[3],
    );
    for n in 0..b {
        let m = &moments.data[n * ch2 * hw..n * ch2 * hw + ch2 / 2 * hw];
        assert_eq!(m, &mean.data[n * ch2 / 2 * hw..(n + 1) * ch2 / 2 * hw]);
    }
}

#[test]
fn case_files_read_in_f16_and_f32() {
    let g = load_json("models.json");
    for case in g["cases"].as_array().unwrap() {
        let f = case["file"].as_str().unwrap();
        let bytes = std::fs::read(golden_dir().join(f)).unwrap();
        let w = Weights::from_bytes_unchecked(&bytes, f).unwrap();
        let want = if case["dtype"] == "F16" {
            FileDType::F16
        } else {
            FileDType::F32
        };
        let sample = w.get("in.sample").unwrap();
        assert_eq!(sample.file_dtype, want, "{f}");
        let hw = case["latent_hw"].as_array().unwrap();
        assert_eq!(
            sample.shape[2..],
            [
                hw[0].as_u64().unwrap() as usize,
                hw[1].as_u64().unwrap() as usize
            ]
        );
        assert!(sample.data.iter().all(|v| v.is_finite()));
    }
}

fn tiny_vae() -> (Vec<Spec>, Weights) {
    let exp = expected_vae(&VaeConfig::b2dr_tiny());
    let w = Weights::random(&exp, 9);
    (exp, w)
}

fn err_of(bytes: &[u8], exp: &[Spec]) -> String {
    format!(
        "{:#}",
        Weights::from_bytes(bytes, exp, "test.safetensors").expect_err("should fail")
    )
}

#[test]
fn save_load_round_trip_f32_and_f16() {
    let (exp, w) = tiny_vae();
    let back = Weights::from_bytes(&w.to_bytes(FileDType::F32).unwrap(), &exp, "rt").unwrap();
    assert_eq!(back.tensors, w.tensors);
    let half = Weights::from_bytes(&w.to_bytes(FileDType::F16).unwrap(), &exp, "rt16").unwrap();
    for (n, t) in &half.tensors {
        assert_eq!(t.file_dtype, FileDType::F16);
        let o = &w.tensors[n];
        assert!(
            t.data
                .iter()
                .zip(&o.data)
                .all(|(a, b)| (a - b).abs() <= 1e-3 * b.abs().max(1e-2)),
            "{n}"
        );
    }
    assert!(w.to_bytes(FileDType::Bf16).is_err());
}

#[test]
fn missing_extra_misshaped_tensors_are_named() {
    let (exp, w) = tiny_vae();
    let name = "decoder.mid_block.attentions.0.to_q.weight";
    let mut m = w.clone();
    m.tensors.remove(name);
    let e = err_of(&m.to_bytes(FileDType::F32).unwrap(), &exp);
    assert!(e.contains("missing") && e.contains(name), "{e}");

    let mut x = w.clone();
    x.tensors
        .insert("decoder.extra.weight".into(), w.tensors[name].clone());
    let e = err_of(&x.to_bytes(FileDType::F32).unwrap(), &exp);
    assert!(
        e.contains("unexpected") && e.contains("decoder.extra.weight"),
        "{e}"
    );

    let mut s = w.clone();
    let t = s.tensors.get_mut(name).unwrap();
    t.shape = vec![t.shape[0], t.shape[1], 1, 1];
    let e = err_of(&s.to_bytes(FileDType::F32).unwrap(), &exp);
    assert!(e.contains(name) && e.contains("shape"), "{e}");

    // A UNet file checked against a VAE list: first missing VAE tensor named.
    let u = Weights::random(&expected_unet(&UNetConfig::b2dr_tiny()), 1);
    let e = err_of(&u.to_bytes(FileDType::F16).unwrap(), &exp);
    assert!(e.contains("missing tensor `encoder.conv_in.weight`"), "{e}");
}

#[test]
fn truncated_and_corrupt_files_are_clear_errors() {
    let (exp, w) = tiny_vae();
    let bytes = w.to_bytes(FileDType::F32).unwrap();
    let e = err_of(&bytes[..bytes.len() - 10], &exp);
    assert!(e.contains("truncated") && e.contains('`'), "{e}");
    let e = err_of(&bytes[..100], &exp);
    assert!(e.contains("truncated"), "{e}");
    let e = err_of(&bytes[..4], &exp);
    assert!(e.contains("truncated"), "{e}");
    let mut bad = bytes.clone();
    bad[8] = b'[';
    assert!(err_of(&bad, &exp).contains("header"));
}

/// A hand-built safetensors buffer with one tensor of the given dtype and raw bytes.
fn one_tensor(name: &str, dtype: &str, shape: &[usize], raw: &[u8]) -> Vec<u8> {
    let h = serde_json::json!({ name: {"dtype": dtype, "shape": shape, "data_offsets": [0, raw.len()]} });
    let h = serde_json::to_vec(&h).unwrap();
    let mut out = (h.len() as u64).to_le_bytes().to_vec();
    out.extend_from_slice(&h);
    out.extend_from_slice(raw);
    out
}

#[test]
fn bf16_is_converted_and_other_dtypes_rejected() {
    let exp: Vec<Spec> = vec![("conv.weight".into(), vec![2])];
    let raw: Vec<u8> = [1.5f32, -2.0]
        .iter()
        .flat_map(|v| half::bf16::from_f32(*v).to_le_bytes())
        .collect();
    let w =
        Weights::from_bytes(&one_tensor("conv.weight", "BF16", &[2], &raw), &exp, "bf16").unwrap();
    assert_eq!(w.tensors["conv.weight"].data, vec![1.5, -2.0]);
    assert_eq!(w.tensors["conv.weight"].file_dtype, FileDType::Bf16);
    let e = err_of(&one_tensor("conv.weight", "I64", &[2], &[0u8; 16]), &exp);
    assert!(e.contains("conv.weight") && e.contains("I64"), "{e}");
    let e = err_of(&one_tensor("conv.weight", "F32", &[3], &[0u8; 8]), &exp);
    assert!(e.contains("conv.weight") && e.contains("bytes"), "{e}");
}

#[test]
fn legacy_vae_attention_names_are_renamed() {
    let exp: Vec<Spec> = vec![("encoder.mid_block.attentions.0.to_q.weight".into(), vec![1])];
    let raw = 0.5f32.to_le_bytes();
    let b = one_tensor(
        "encoder.mid_block.attentions.0.query.weight",
        "F32",
        &[1],
        &raw,
    );
    assert!(Weights::from_bytes(&b, &exp, "legacy").is_ok());
}

#[test]
fn random_weights_are_deterministic_and_seed_dependent() {
    let exp = expected_controlnet(&ControlNetConfig::b2dr_tiny());
    let a = Weights::random(&exp, 5);
    let b = Weights::random(&exp, 5);
    let c = Weights::random(&exp, 6);
    assert!(a.tensors.iter().all(|(n, t)| t
        .data
        .iter()
        .zip(&b.tensors[n].data)
        .all(|(x, y)| x.to_bits() == y.to_bits())));
    assert_ne!(
        a.tensors["controlnet_mid_block.weight"].data,
        c.tensors["controlnet_mid_block.weight"].data
    );
    // Zero convs are random too (documented): not all zero.
    assert!(a.tensors["controlnet_down_blocks.0.weight"]
        .data
        .iter()
        .any(|v| *v != 0.0));
    let dir = std::env::temp_dir().join(format!("b2dr_w_{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let p = dir.join("cn.safetensors");
    a.save(&p, FileDType::F32).unwrap();
    assert_eq!(Weights::load(&p, &exp).unwrap().tensors, a.tensors);
    std::fs::remove_dir_all(&dir).ok();
}

/// A safetensors header whose shape product overflows usize (issue #18) is an error naming the tensor, not an
/// arithmetic overflow.
#[test]
fn overflowing_shape_products_are_errors() {
    let exp: Vec<Spec> = vec![("conv.weight".into(), vec![2])];
    for shape in [
        vec![1usize << 40, 1 << 40],
        vec![usize::MAX, 2],
        vec![1 << 62],
    ] {
        let e = err_of(&one_tensor("conv.weight", "F32", &shape, &[0u8; 8]), &exp);
        assert!(
            e.contains("conv.weight") && e.contains("needs"),
            "{shape:?}: {e}"
        );
    }
}

/// A checked weight file holding NaN or infinity is refused naming the tensor (every image would be NaN).
#[test]
fn non_finite_weights_are_refused() {
    let exp: Vec<Spec> = vec![("conv.weight".into(), vec![2])];
    for bad in [f32::NAN, f32::INFINITY] {
        let raw: Vec<u8> = [1.0f32, bad].iter().flat_map(|v| v.to_le_bytes()).collect();
        let e = err_of(&one_tensor("conv.weight", "F32", &[2], &raw), &exp);
        assert!(
            e.contains("conv.weight") && e.contains("NaN or infinite"),
            "{bad}: {e}"
        );
    }
    // the unchecked reader (inputs, goldens) keeps them
    let raw: Vec<u8> = [1.0f32, f32::NAN]
        .iter()
        .flat_map(|v| v.to_le_bytes())
        .collect();
    let w = Weights::from_bytes_unchecked(&one_tensor("x", "F32", &[2], &raw), "in").unwrap();
    assert!(w.tensors["x"].data[1].is_nan());
}
