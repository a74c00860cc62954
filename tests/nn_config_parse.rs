//! diffusers config.json parsing: the built-in configs, the goldens' configs (as diffusers wrote them),
//! and one test per kind of bad config (each error must name the key).

#[path = "golden/common.rs"]
mod common;

use b2dr::nn::config::{ControlNetConfig, DownBlock, UNetConfig, UpBlock, VaeConfig};
use serde_json::{json, Value};

fn sd15_unet_json() -> Value {
    // runwayml/stable-diffusion-v1-5 unet/config.json (diffusers 0.6 era keys).
    json!({
        "_class_name": "UNet2DConditionModel", "_diffusers_version": "0.6.0", "act_fn": "silu",
        "attention_head_dim": 8, "block_out_channels": [320, 640, 1280, 1280], "center_input_sample": false,
        "cross_attention_dim": 768,
        "down_block_types": ["CrossAttnDownBlock2D", "CrossAttnDownBlock2D", "CrossAttnDownBlock2D", "DownBlock2D"],
        "downsample_padding": 1, "flip_sin_to_cos": true, "freq_shift": 0, "in_channels": 4, "layers_per_block": 2,
        "mid_block_scale_factor": 1, "norm_eps": 1e-05, "norm_num_groups": 32, "out_channels": 4, "sample_size": 64,
        "up_block_types": ["UpBlock2D", "CrossAttnUpBlock2D", "CrossAttnUpBlock2D", "CrossAttnUpBlock2D"]
    })
}

#[test]
fn sd15_unet_config_parses() {
    let c = UNetConfig::from_json(sd15_unet_json()).unwrap();
    assert_eq!(c, UNetConfig::sd15());
    assert_eq!(c.enc.num_heads, vec![8; 4]);
    assert_eq!(
        (0..4).map(|i| c.enc.head_dim(i)).collect::<Vec<_>>(),
        vec![40, 80, 160, 160]
    );
    assert_eq!(c.enc.time_embed_dim(), 1280);
    assert_eq!(c.up_blocks[0], UpBlock::Plain);
    assert_eq!(c.enc.down_blocks[3], DownBlock::Plain);
}

#[test]
fn builtins_round_trip_through_diffusers_json() {
    assert_eq!(
        UNetConfig::from_json(UNetConfig::b2dr_tiny().to_json()).unwrap(),
        UNetConfig::b2dr_tiny()
    );
    assert_eq!(
        UNetConfig::from_json(UNetConfig::sd15().to_json()).unwrap(),
        UNetConfig::sd15()
    );
    let c = ControlNetConfig::b2dr_tiny();
    assert_eq!(ControlNetConfig::from_json(c.to_json()).unwrap(), c);
    assert_eq!(
        VaeConfig::from_json(VaeConfig::sd15().to_json()).unwrap(),
        VaeConfig::sd15()
    );
    assert_eq!(
        VaeConfig::from_json(VaeConfig::b2dr_tiny().to_json()).unwrap(),
        VaeConfig::b2dr_tiny()
    );
    let t = UNetConfig::b2dr_tiny();
    assert_eq!(t.enc.block_out_channels, vec![32, 64, 128, 128]);
    assert_eq!(
        (
            t.enc.cross_attention_dim,
            t.enc.norm_num_groups,
            t.enc.num_heads[0]
        ),
        (64, 8, 4)
    );
}

/// The configs diffusers itself wrote for the goldens (every key of its `__init__`, with its defaults).
#[test]
fn golden_configs_parse_and_tiny_matches_builtin() {
    let g = common::load_json("models.json");
    for (set, e) in g["sets"].as_object().unwrap() {
        for (kind, cfg) in e["configs"].as_object().unwrap() {
            let r = match kind.as_str() {
                "unet" => UNetConfig::from_json(cfg.clone()).map(|_| ()),
                "controlnet" => ControlNetConfig::from_json(cfg.clone()).map(|_| ()),
                "vae" => VaeConfig::from_json(cfg.clone()).map(|_| ()),
                other => panic!("unknown component {other}"),
            };
            r.unwrap_or_else(|e| panic!("set {set} {kind}: {e:#}"));
        }
    }
    let tiny = &g["sets"]["tiny"]["configs"];
    assert_eq!(
        UNetConfig::from_json(tiny["unet"].clone()).unwrap(),
        UNetConfig::b2dr_tiny()
    );
    assert_eq!(
        ControlNetConfig::from_json(tiny["controlnet"].clone()).unwrap(),
        ControlNetConfig::b2dr_tiny()
    );
    assert_eq!(
        VaeConfig::from_json(tiny["vae"].clone()).unwrap(),
        VaeConfig::b2dr_tiny()
    );
}

type Edit = Box<dyn FnOnce(&mut Value)>;

fn unet_err(edit: impl FnOnce(&mut Value)) -> String {
    let mut v = sd15_unet_json();
    edit(&mut v);
    format!(
        "{:#}",
        UNetConfig::from_json(v).expect_err("config should be rejected")
    )
}

#[test]
fn bad_unet_configs_name_the_key() {
    let cases: Vec<(&str, Edit)> = vec![
        ("act_fn", Box::new(|v| v["act_fn"] = json!("gelu"))),
        (
            "down_block_types",
            Box::new(|v| v["down_block_types"][0] = json!("AttnDownBlock2D")),
        ),
        (
            "up_block_types",
            Box::new(|v| v["up_block_types"] = json!(["UpBlock2D"])),
        ),
        (
            "block_out_channels",
            Box::new(|v| v["block_out_channels"] = json!([320, 640])),
        ),
        (
            "norm_num_groups",
            Box::new(|v| v["norm_num_groups"] = json!(24)),
        ),
        (
            "attention_head_dim",
            Box::new(|v| v["attention_head_dim"] = json!(7)),
        ),
        (
            "attention_head_dim",
            Box::new(|v| v["attention_head_dim"] = json!([8, 8])),
        ),
        (
            "use_linear_projection",
            Box::new(|v| v["use_linear_projection"] = json!(true)),
        ),
        (
            "num_attention_heads",
            Box::new(|v| v["num_attention_heads"] = json!(8)),
        ),
        (
            "class_embed_type",
            Box::new(|v| v["class_embed_type"] = json!("timestep")),
        ),
        (
            "transformer_layers_per_block",
            Box::new(|v| v["transformer_layers_per_block"] = json!(2)),
        ),
        (
            "cross_attention_dim",
            Box::new(|v| v["cross_attention_dim"] = json!("768")),
        ),
        (
            "layers_per_block",
            Box::new(|v| v["layers_per_block"] = json!(0)),
        ),
        (
            "mid_block_type",
            Box::new(|v| v["mid_block_type"] = json!("UNetMidBlock2DSimpleCrossAttn")),
        ),
        (
            "resnet_time_scale_shift",
            Box::new(|v| v["resnet_time_scale_shift"] = json!("scale_shift")),
        ),
        (
            "some_future_key",
            Box::new(|v| v["some_future_key"] = json!(1)),
        ),
        (
            "_class_name",
            Box::new(|v| v["_class_name"] = json!("ControlNetModel")),
        ),
    ];
    for (key, edit) in cases {
        let msg = unet_err(edit);
        assert!(
            msg.contains(key),
            "error for bad `{key}` does not name it: {msg}"
        );
    }
    // Not an object at all.
    assert!(UNetConfig::from_json(json!([1, 2])).is_err());
}

#[test]
fn bad_controlnet_and_vae_configs_name_the_key() {
    let mut v = ControlNetConfig::b2dr_tiny().to_json();
    v["conditioning_embedding_out_channels"] = json!([]);
    let e = format!("{:#}", ControlNetConfig::from_json(v).unwrap_err());
    assert!(e.contains("conditioning_embedding_out_channels"), "{e}");
    let mut v = ControlNetConfig::b2dr_tiny().to_json();
    v["global_pool_conditions"] = json!(true);
    let e = format!("{:#}", ControlNetConfig::from_json(v).unwrap_err());
    assert!(e.contains("global_pool_conditions"), "{e}");
    let mut v = ControlNetConfig::b2dr_tiny().to_json();
    v["controlnet_conditioning_channel_order"] = json!("bgr");
    assert!(ControlNetConfig::from_json(v).unwrap().bgr_conditioning);

    for (key, val) in [
        (
            "down_block_types",
            json!(["DownEncoderBlock2D", "AttnDownEncoderBlock2D", "A", "B"]),
        ),
        ("up_block_types", json!(["UpDecoderBlock2D"])),
        ("norm_num_groups", json!(5)),
        ("latents_mean", json!([0.0, 0.0, 0.0, 0.0])),
        ("scaling_factor", json!(-1.0)),
        ("act_fn", json!("relu")),
    ] {
        let mut v = VaeConfig::sd15().to_json();
        v[key] = val;
        let e = format!("{:#}", VaeConfig::from_json(v).unwrap_err());
        assert!(
            e.contains(key),
            "error for bad `{key}` does not name it: {e}"
        );
    }
}

#[test]
fn config_files_read_from_disk() {
    let dir = std::env::temp_dir().join(format!("b2dr_cfg_{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let p = dir.join("config.json");
    std::fs::write(&p, serde_json::to_string(&sd15_unet_json()).unwrap()).unwrap();
    assert_eq!(UNetConfig::from_file(&p).unwrap(), UNetConfig::sd15());
    std::fs::write(&p, "{ not json").unwrap();
    let e = format!("{:#}", UNetConfig::from_file(&p).unwrap_err());
    assert!(e.contains("config.json"), "{e}");
    std::fs::remove_dir_all(&dir).ok();
}

/// Config integers without a bound (issue #18): a channel count of 2^40, 2^40 layers or 1000 blocks are
/// errors naming the key, not models sized from them.
#[test]
fn huge_config_integers_are_errors_naming_the_key() {
    let huge = 1u64 << 40;
    let cases: Vec<(&str, Edit)> = vec![
        (
            "block_out_channels",
            Box::new(move |v| v["block_out_channels"] = json!([huge, 640, 1280, 1280])),
        ),
        (
            "layers_per_block",
            Box::new(move |v| v["layers_per_block"] = json!(huge)),
        ),
        (
            "cross_attention_dim",
            Box::new(|v| v["cross_attention_dim"] = json!(u64::MAX)),
        ),
        (
            "attention_head_dim",
            Box::new(move |v| v["attention_head_dim"] = json!(huge)),
        ),
        (
            "in_channels",
            Box::new(|v| v["in_channels"] = json!(1u64 << 20)),
        ),
        (
            "down_block_types",
            Box::new(|v| v["down_block_types"] = json!(vec!["DownBlock2D"; 1000])),
        ),
    ];
    for (key, edit) in cases {
        let e = unet_err(edit);
        assert!(e.contains(key) && e.contains("at most"), "{key}: {e}");
    }
    let mut v = VaeConfig::sd15().to_json();
    v["block_out_channels"] = json!(vec![64; 1000]);
    let e = format!("{:#}", VaeConfig::from_json(v).unwrap_err());
    assert!(
        e.contains("block_out_channels") && e.contains("at most"),
        "{e}"
    );
    let mut v = VaeConfig::sd15().to_json();
    v["latent_channels"] = json!(huge);
    let e = format!("{:#}", VaeConfig::from_json(v).unwrap_err());
    assert!(
        e.contains("latent_channels") && e.contains("at most"),
        "{e}"
    );
}
