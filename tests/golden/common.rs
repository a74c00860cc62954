//! Shared helpers of the golden-file tests (included with `#[path = "golden/common.rs"] mod common;`).
//! Golden files come from `tools/make_golden.py` (diffusers on PyTorch); see tools/README.md.
#![allow(dead_code)]

use serde_json::Value;
use std::path::PathBuf;

/// The golden format version these tests read (tools/make_golden.py FORMAT_VERSION).
pub const FORMAT_VERSION: u64 = 1;

/// How to regenerate, appended to every golden mismatch message.
pub const REGENERATE: &str = "golden files are written by diffusers: regenerate with \
`python3 -m venv .venv && .venv/bin/pip install -r tools/requirements.txt && .venv/bin/python tools/make_golden.py`";

pub fn golden_dir() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("tests")
        .join("golden")
}

/// Reads and version-checks a golden JSON file.
pub fn load_json(name: &str) -> Value {
    let man: Value = serde_json::from_str(
        &std::fs::read_to_string(golden_dir().join("manifest.json"))
            .unwrap_or_else(|e| panic!("tests/golden/manifest.json: {e}; {REGENERATE}")),
    )
    .unwrap_or_else(|e| panic!("tests/golden/manifest.json: {e}; {REGENERATE}"));
    let v = man["format_version"].as_u64();
    assert_eq!(
        v,
        Some(FORMAT_VERSION),
        "golden format version {v:?}, tests expect {FORMAT_VERSION}; {REGENERATE}"
    );
    let path = golden_dir().join(name);
    let text = std::fs::read_to_string(&path)
        .unwrap_or_else(|e| panic!("{}: {e}; {REGENERATE}", path.display()));
    serde_json::from_str(&text).unwrap_or_else(|e| panic!("{}: {e}; {REGENERATE}", path.display()))
}

pub fn f32s(v: &Value) -> Vec<f32> {
    v.as_array()
        .expect("golden: array")
        .iter()
        .map(|x| x.as_f64().expect("golden: number") as f32)
        .collect()
}

pub fn f64s(v: &Value) -> Vec<f64> {
    v.as_array()
        .expect("golden: array")
        .iter()
        .map(|x| x.as_f64().expect("golden: number"))
        .collect()
}

pub fn i64s(v: &Value) -> Vec<i64> {
    v.as_array()
        .expect("golden: array")
        .iter()
        .map(|x| x.as_i64().expect("golden: integer"))
        .collect()
}

/// Normalised MSE: `sum (a - b)^2 / max(sum b^2, tiny)`.
pub fn nmse(a: &[f32], b: &[f32]) -> f64 {
    assert_eq!(a.len(), b.len(), "length mismatch");
    let num: f64 = a
        .iter()
        .zip(b)
        .map(|(x, y)| (*x as f64 - *y as f64).powi(2))
        .sum();
    let den: f64 = b.iter().map(|y| (*y as f64).powi(2)).sum();
    num / den.max(1e-30)
}

/// Asserts `nmse(got, want) <= tol` with a message naming `what` and how to regenerate.
pub fn assert_close(what: &str, got: &[f32], want: &[f32], tol: f64) {
    let e = nmse(got, want);
    assert!(
        e <= tol,
        "{what}: normalised MSE {e:.3e} > {tol:.1e} against diffusers' golden; {REGENERATE}"
    );
}

/// The weights a golden model set uses for one component (`kind`: unet, controlnet, vae): the stored F32
/// file, or b2dr's seeded generator (checked against the stored fingerprints).
pub fn golden_weights(models: &Value, set: &str, kind: &str) -> b2dr::nn::weights::Weights {
    use b2dr::nn::config::{ControlNetConfig, UNetConfig, VaeConfig};
    use b2dr::nn::weights::{expected_controlnet, expected_unet, expected_vae, Weights};
    let e = &models["sets"][set];
    let cfg = e["configs"][kind].clone();
    let exp = match kind {
        "unet" => expected_unet(&UNetConfig::from_json(cfg).expect("golden unet config")),
        "controlnet" => expected_controlnet(
            &ControlNetConfig::from_json(cfg).expect("golden controlnet config"),
        ),
        "vae" => expected_vae(&VaeConfig::from_json(cfg).expect("golden vae config")),
        other => panic!("unknown component {other}"),
    };
    let w = &e["weights"][kind];
    if let Some(f) = w["file"].as_str() {
        return Weights::load(&golden_dir().join(f), &exp)
            .unwrap_or_else(|e| panic!("{f}: {e:#}; {REGENERATE}"));
    }
    let weights = Weights::random(&exp, w["seed"].as_u64().expect("golden weights: seed"));
    for (name, t) in &weights.tensors {
        let want: u64 = w["fingerprints"][name]
            .as_str()
            .and_then(|s| s.parse().ok())
            .unwrap_or(0);
        assert_eq!(
            Weights::fingerprint(t),
            want,
            "{set} {kind} `{name}` differs from the golden; {REGENERATE}"
        );
    }
    weights
}

/// A golden case file (inputs `in.*`, diffusers outputs `out.*`) by file name, e.g. `case_tiny_28x50.safetensors`.
pub fn golden_case(file: &str) -> b2dr::nn::weights::Weights {
    let bytes = std::fs::read(golden_dir().join(file))
        .unwrap_or_else(|e| panic!("{file}: {e}; {REGENERATE}"));
    b2dr::nn::weights::Weights::from_bytes_unchecked(&bytes, file)
        .unwrap_or_else(|e| panic!("{e:#}; {REGENERATE}"))
}
