//! The paper's closed-loop comparison (Bench2Drive-R Table 3, plus the ground-truth row the synthetic world
//! allows): the same planner under several renderer modes on the same scenarios, one table of scores per
//! metric and renderer, and the front camera of every mode side by side at a few planner steps.
//!
//!   <out>/<renderer>/...        each mode's own run (eval::run layout)
//!   <out>/comparison.md, .json  CLS and per-metric means per renderer
//!   <out>/side_by_side_<scenario>_<step>.png   one row per renderer
use std::path::Path;

use anyhow::{Context as _, Result};
use serde_json::{json, Value};

use super::run::{folder_name, run, RendererMode, RunConfig};
use crate::vk::Context;

const METRICS: [&str; 9] = [
    "no_ego_at_fault_collisions",
    "drivable_area_compliance",
    "driving_direction_compliance",
    "ego_is_making_progress",
    "time_to_collision_within_bound",
    "speed_limit_compliance",
    "ego_progress_along_expert_route",
    "ego_is_comfortable",
    "score",
];

/// Runs `base` under every mode of `modes` into `out/<mode>` and writes the comparison.
pub fn compare(
    ctx: Option<&Context>,
    base: &RunConfig,
    modes: &[RendererMode],
    out: &Path,
    resume: bool,
) -> Result<Value> {
    let mut rows = vec![];
    for &m in modes {
        let mut c = base.clone();
        c.renderer = m;
        eprintln!("renderer {}:", m.name());
        let s = run(ctx, &c, &out.join(m.name()), resume)?;
        rows.push((m, s));
    }
    let mut table = String::from("| renderer | CLS |");
    for m in &METRICS[..8] {
        table.push_str(&format!(" {m} |"));
    }
    table.push_str(" failures |\n|---|---|");
    table.push_str(&"---|".repeat(METRICS.len()));
    table.push('\n');
    let mut js = vec![];
    for (m, s) in &rows {
        let sc = s["scenarios"].as_array().cloned().unwrap_or_default();
        let n = sc.len().max(1) as f64;
        let mean = |k: &str| -> f64 {
            sc.iter()
                .map(|v| v["metrics"][k].as_f64().unwrap_or(0.0))
                .sum::<f64>()
                / n
        };
        let fails = sc.iter().filter(|v| !v["failure"].is_null()).count();
        table.push_str(&format!(
            "| {} | {:.4} |",
            m.name(),
            s["cls"].as_f64().unwrap_or(0.0)
        ));
        let mut per = serde_json::Map::new();
        for k in &METRICS[..8] {
            let v = mean(k);
            table.push_str(&format!(" {v:.3} |"));
            per.insert(k.to_string(), json!(v));
        }
        table.push_str(&format!(" {fails} |\n"));
        js.push(
            json!({"renderer": m.name(), "cls": s["cls"], "cls_kind": s["cls_kind"], "metrics": per,
            "failures": fails, "timing_ms": s["timing_ms"]}),
        );
    }
    let kind = rows
        .first()
        .and_then(|(_, s)| s["cls_kind"].as_str())
        .unwrap_or("CLS")
        .to_string();
    let md = format!(
        "# Closed-loop comparison\n\nPlanner `{}`, agents `{:?}` ({kind}), scenarios `{}`, {} steps.\n\n{table}",
        base.planner, base.agents, base.scenario, base.steps
    );
    std::fs::write(out.join("comparison.md"), &md)
        .with_context(|| format!("writing {}", out.join("comparison.md").display()))?;
    let summary =
        json!({"planner": base.planner, "scenario": base.scenario, "cls_kind": kind, "rows": js});
    std::fs::write(
        out.join("comparison.json"),
        serde_json::to_string_pretty(&summary)?,
    )?;
    side_by_side(base, modes, out)?;
    println!("{md}");
    Ok(summary)
}

/// The front camera (or the first camera) of every mode at up to four planner steps, one row per mode.
fn side_by_side(base: &RunConfig, modes: &[RendererMode], out: &Path) -> Result<()> {
    let first = out.join(modes[0].name());
    let Some(scen) = std::fs::read_dir(&first).ok().and_then(|d| {
        d.filter_map(|e| e.ok())
            .find(|e| e.path().join("frames").is_dir())
    }) else {
        return Ok(());
    };
    let scen = scen.file_name().to_string_lossy().to_string();
    let cam = base
        .cameras
        .iter()
        .find(|c| c.contains("FRONT") && !c.contains("LEFT") && !c.contains("RIGHT"))
        .cloned()
        .unwrap_or_else(|| "CAM_FRONT".into());
    for step in [0usize, 20, 40, 60] {
        let mut rows: Vec<image::RgbImage> = vec![];
        for m in modes {
            let p = out
                .join(m.name())
                .join(&scen)
                .join("frames")
                .join(format!("{step:04}_{}.png", folder_name(&cam)));
            if let Ok(img) = image::open(&p) {
                rows.push(img.to_rgb8());
            }
        }
        if rows.is_empty() {
            continue;
        }
        let w = rows.iter().map(|r| r.width()).max().unwrap_or(1);
        let h: u32 = rows.iter().map(|r| r.height()).sum();
        let mut canvas = image::RgbImage::new(w, h);
        let mut y = 0;
        for r in &rows {
            image::imageops::replace(&mut canvas, r, 0, y as i64);
            y += r.height();
        }
        let p = out.join(format!("side_by_side_{scen}_{step:04}.png"));
        canvas
            .save(&p)
            .with_context(|| format!("writing {}", p.display()))?;
    }
    Ok(())
}
