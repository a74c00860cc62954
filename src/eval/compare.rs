//! The paper's closed-loop comparison (Bench2Drive-R Table 3, plus the ground-truth row the synthetic world
//! allows): the same planner under several renderer modes on the same scenarios, one table of scores per
//! metric and renderer, and the front camera of every mode side by side at a few planner steps.
//!
//!   <out>/<renderer>/...        each mode's own run (eval::run layout)
//!   <out>/comparison.md, .json  CLS and per-metric means per renderer
//!   <out>/side_by_side_<scenario>_<step>.png   one row per renderer
//!   <out>/diverged/<scenario>_<step>.png        where the renderer changed the outcome (scores differ): each
//!                                               renderer's mosaic (the cameras the planner saw + the BEV) at
//!                                               four planner steps, one row per renderer in table order
use std::path::Path;

use anyhow::{Context as _, Result};
use serde_json::{json, Value};

use super::batch::METRICS;
use super::run::{folder_name, run, RendererMode, RunConfig};
use crate::vk::Context;

/// Runs `base` under every mode of `modes` into `out/<mode>` and writes the comparison.
pub fn compare(
    ctx: Option<&Context>,
    base: &RunConfig,
    modes: &[RendererMode],
    out: &Path,
    resume: bool,
) -> Result<Value> {
    // comparison.json lands in `out` itself: the scenario folder must not be it (nor hold it)
    super::batch::check_out_outside_scenarios(
        out,
        &crate::scene::import::resolve(&base.scenario)?,
    )?;
    let mut rows = vec![];
    for &m in modes {
        let mut c = base.clone();
        c.renderer = m;
        eprintln!("renderer {}:", m.name());
        let s = run(ctx, &c, &out.join(m.name()), resume)?;
        rows.push((m, s));
    }
    let mut table = String::from("| renderer | CLS |");
    for m in &METRICS {
        table.push_str(&format!(" {m} |"));
    }
    table.push_str(" failures |\n|---|---|");
    table.push_str(&"---|".repeat(METRICS.len() + 1)); // the metrics and "failures"
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
        for k in &METRICS {
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
    let diverged = diverged(&rows, out)?;
    let mut md = format!(
        "# Closed-loop comparison\n\nPlanner `{}`, agents `{:?}` ({kind}), scenarios `{}` ({} scenarios), {} steps.\n\n{table}",
        base.planner,
        base.agents,
        base.scenario,
        rows.first()
            .and_then(|(_, s)| s["scenarios"].as_array().map(|v| v.len()))
            .unwrap_or(0),
        base.steps
    );
    if !diverged.is_empty() {
        md.push_str(&format!(
            "\nScenarios where the renderer changed the score (per renderer, in table order; mosaics in `diverged/`):\n\n| scenario | {} |\n|---|{}\n",
            rows.iter().map(|(m, _)| m.name()).collect::<Vec<_>>().join(" | "),
            "---|".repeat(rows.len())
        ));
        for (name, scores) in &diverged {
            let cells: Vec<String> = scores.iter().map(|v| format!("{v:.3}")).collect();
            md.push_str(&format!("| {name} | {} |\n", cells.join(" | ")));
        }
    }
    std::fs::write(out.join("comparison.md"), &md)
        .with_context(|| format!("writing {}", out.join("comparison.md").display()))?;
    let div: Vec<Value> = diverged
        .iter()
        .map(|(n, v)| json!({"scenario": n, "scores": v}))
        .collect();
    let summary = json!({"planner": base.planner, "scenario": base.scenario, "cls_kind": kind, "rows": js,
        "diverged": div});
    std::fs::write(
        out.join("comparison.json"),
        serde_json::to_string_pretty(&summary)?,
    )?;
    side_by_side(base, modes, out)?;
    println!("{md}");
    let all_failed = |s: &Value| super::batch::ensure_not_all_failed(s, out).is_err();
    if let Some((m, s)) = rows
        .first()
        .filter(|_| rows.iter().all(|(_, s)| all_failed(s)))
    {
        // no scenario of any renderer ran: the table is empty of results, a non-zero exit status says so
        super::batch::ensure_not_all_failed(s, &out.join(m.name()))?;
    }
    Ok(summary)
}

/// The scenarios whose score differs between modes (name, score per mode), and for each the modes' mosaics
/// stacked at four planner steps spread over the run.
fn diverged(rows: &[(RendererMode, Value)], out: &Path) -> Result<Vec<(String, Vec<f64>)>> {
    let per_mode: Vec<Vec<(String, f64)>> = rows
        .iter()
        .map(|(_, s)| {
            s["scenarios"]
                .as_array()
                .map(|v| {
                    v.iter()
                        .map(|x| {
                            (
                                x["scenario"].as_str().unwrap_or("").to_string(),
                                x["score"].as_f64().unwrap_or(0.0),
                            )
                        })
                        .collect()
                })
                .unwrap_or_default()
        })
        .collect();
    let Some(first) = per_mode.first() else {
        return Ok(vec![]);
    };
    let mut found = vec![];
    for (name, _) in first {
        let scores: Vec<f64> = per_mode
            .iter()
            .map(|m| m.iter().find(|(n, _)| n == name).map_or(0.0, |x| x.1))
            .collect();
        if scores.iter().all(|&v| (v - scores[0]).abs() < 1e-9) {
            continue;
        }
        let steps = rows[0].1["scenarios"]
            .as_array()
            .and_then(|v| v.iter().find(|x| x["scenario"] == name.as_str()))
            .and_then(|x| x["steps"].as_u64())
            .unwrap_or(150)
            .min(1 << 32) as usize; // read back from a file: no overflow below
        let dir = out.join("diverged");
        std::fs::create_dir_all(&dir).with_context(|| format!("creating {}", dir.display()))?;
        // the scenario name comes from the data: its folder name (as the run wrote it) cannot leave `out`
        let folder = folder_name(name);
        for q in 0..4 {
            // planner steps (multiples of 5) at 0, 1/4, 1/2, 3/4 of the run
            let step = steps * q / 4 / 5 * 5;
            let mosaics = rows.iter().map(|(m, _)| {
                out.join(m.name())
                    .join(&folder)
                    .join("mosaic")
                    .join(format!("{step:04}.png"))
            });
            save_stack(mosaics, &dir.join(format!("{folder}_{step:04}.png")))?;
        }
        found.push((name.clone(), scores));
    }
    Ok(found)
}

/// The images at `paths` that exist, stacked vertically (left-aligned, black where narrower) into `to`;
/// nothing is written when none exists.
fn save_stack(paths: impl Iterator<Item = std::path::PathBuf>, to: &Path) -> Result<()> {
    let rows: Vec<image::RgbImage> = paths
        .filter_map(|p| image::open(p).ok().map(|i| i.to_rgb8()))
        .collect();
    if rows.is_empty() {
        return Ok(());
    }
    let w = rows.iter().map(|r| r.width()).max().unwrap_or(1);
    let h: u32 = rows.iter().map(|r| r.height()).sum();
    let mut canvas = image::RgbImage::new(w, h);
    let mut y = 0;
    for r in &rows {
        image::imageops::replace(&mut canvas, r, 0, y as i64);
        y += r.height();
    }
    canvas
        .save(to)
        .with_context(|| format!("writing {}", to.display()))
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
        let frames = modes.iter().map(|m| {
            out.join(m.name())
                .join(&scen)
                .join("frames")
                .join(format!("{step:04}_{}.png", folder_name(&cam)))
        });
        save_stack(
            frames,
            &out.join(format!("side_by_side_{scen}_{step:04}.png")),
        )?;
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn diverged_lists_only_scenarios_whose_score_differs_and_stacks_their_mosaics() {
        let out = std::env::temp_dir().join(format!("b2dr-compare-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&out);
        let modes = [RendererMode::Groundtruth, RendererMode::LogReplay];
        for (k, m) in modes.iter().enumerate() {
            for sc in ["same", "differs"] {
                let d = out.join(m.name()).join(sc).join("mosaic");
                std::fs::create_dir_all(&d).unwrap();
                for step in [0, 5, 10, 15] {
                    image::RgbImage::from_pixel(4 + k as u32, 3, image::Rgb([k as u8 * 200, 0, 0]))
                        .save(d.join(format!("{step:04}.png")))
                        .unwrap();
                }
            }
        }
        let summary = |differs: f64| {
            json!({"scenarios": [
                {"scenario": "same", "score": 0.5, "steps": 20},
                {"scenario": "differs", "score": differs, "steps": 20},
            ]})
        };
        let rows = vec![(modes[0], summary(1.0)), (modes[1], summary(0.0))];
        let d = diverged(&rows, &out).unwrap();
        assert_eq!(d, vec![("differs".to_string(), vec![1.0, 0.0])]);
        let img = image::open(out.join("diverged/differs_0005.png"))
            .unwrap()
            .to_rgb8();
        // one row per mode, in order, as wide as the widest
        assert_eq!((img.width(), img.height()), (5, 6));
        assert_eq!(img.get_pixel(0, 0)[0], 0);
        assert_eq!(img.get_pixel(0, 5)[0], 200);
        assert!(!out.join("diverged/same_0000.png").exists());
        std::fs::remove_dir_all(&out).unwrap();
    }

    /// Scenario names from the data ("../../x", "a/b") become folder names: the diverged mosaics are read from
    /// the folders the run wrote and written inside `diverged/`, never outside `out` (issue #18).
    #[test]
    fn diverged_names_from_data_stay_inside_out() {
        let root = std::env::temp_dir().join(format!("b2dr-compare-names-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&root);
        let out = root.join("a").join("out");
        let modes = [RendererMode::Groundtruth, RendererMode::LogReplay];
        let names = ["../../escape", "x/y"];
        for m in &modes {
            for sc in names {
                let d = out.join(m.name()).join(folder_name(sc)).join("mosaic");
                std::fs::create_dir_all(&d).unwrap();
                image::RgbImage::new(2, 2).save(d.join("0000.png")).unwrap();
            }
        }
        let summary = |score: f64| {
            json!({"scenarios": names.iter().map(|n| json!({"scenario": n, "score": score, "steps": 4}))
                .collect::<Vec<_>>()})
        };
        let rows = vec![(modes[0], summary(1.0)), (modes[1], summary(0.0))];
        assert_eq!(diverged(&rows, &out).unwrap().len(), 2);
        for sc in names {
            let f = out
                .join("diverged")
                .join(format!("{}_0000.png", folder_name(sc)));
            assert!(f.is_file(), "{}", f.display());
        }
        assert!(!root.join("a/escape_0000.png").exists());
        assert!(!out.join("diverged/x").exists());
        std::fs::remove_dir_all(&root).ok();
    }
}
