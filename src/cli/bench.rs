//! `b2dr bench ops [--json] [--filter S] [--profile]`: times every op case on the chosen device.
use std::collections::BTreeMap;

use anyhow::{bail, Result};
use b2dr::ops::bench;
use b2dr::vk::{Context, ContextOptions};

pub fn run_ops(
    device: Option<String>,
    json: bool,
    filter: Option<String>,
    min_time_s: f64,
    profile: bool,
) -> Result<()> {
    run_cases(device, bench::cases(), json, filter, min_time_s, profile)
}

/// `b2dr bench model`: the model-level cases of `b2dr::nn::bench`.
pub fn run_model(
    device: Option<String>,
    json: bool,
    filter: Option<String>,
    min_time_s: f64,
    profile: bool,
) -> Result<()> {
    run_cases(
        device,
        b2dr::nn::bench::cases(),
        json,
        filter,
        min_time_s,
        profile,
    )
}

fn run_cases(
    device: Option<String>,
    all: Vec<bench::BenchCase>,
    json: bool,
    filter: Option<String>,
    min_time_s: f64,
    profile: bool,
) -> Result<()> {
    let ctx = Context::new(&ContextOptions {
        device,
        profile,
        ..Default::default()
    })?;
    let cases: Vec<_> = all
        .into_iter()
        .filter(|c| filter.as_deref().is_none_or(|f| c.name.contains(f)))
        .collect();
    if cases.is_empty() {
        bail!("no benchmark case matches {:?}", filter.unwrap_or_default());
    }
    if !json {
        eprintln!("device: {} ({})", ctx.info().name, ctx.info().kind);
        println!(
            "{:<40} {:>10} {:>10} {:>10} {:>9} {:>6}",
            "case", "ms", "min ms", "GFLOP/s", "GB/s", "iters"
        );
    }
    let mut out = BTreeMap::new();
    for c in &cases {
        if !json {
            eprint!("  running {} ...\r", c.name);
        }
        let r = bench::run_case(&ctx, c, 2, 3, min_time_s)?;
        if json {
            out.insert(
                r.name.clone(),
                serde_json::json!({"ms": r.ms, "min_ms": r.min_ms, "gflops": r.gflops, "gbs": r.gbs, "iters": r.iters}),
            );
        } else {
            println!(
                "{:<40} {:>10.3} {:>10.3} {:>10.2} {:>9.2} {:>6}",
                r.name, r.ms, r.min_ms, r.gflops, r.gbs, r.iters
            );
            let top = std::env::var("B2DR_PROFILE_TOP")
                .ok()
                .and_then(|v| v.parse().ok())
                .unwrap_or(15);
            for (label, ms, n) in r.profile.iter().take(top) {
                println!("    {label:<36} {ms:>10.3} ms {n:>5}x");
            }
            if !r.profile.is_empty() {
                let total: f64 = r.profile.iter().map(|p| p.1).sum();
                let n: usize = r.profile.iter().map(|p| p.2).sum();
                println!("    {:<36} {total:>10.3} ms {n:>5}x", "(all dispatches)");
            }
        }
    }
    if json {
        println!("{}", serde_json::to_string_pretty(&out)?);
    }
    Ok(())
}
