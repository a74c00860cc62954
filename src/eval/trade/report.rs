//! The outputs of `bench trade`: trade.json, trade.md (the table) and two scatter plots (time vs error against
//! the reference, time vs PSNR against the ground truth) with the Pareto front and the default marked.
use std::fmt::Write as _;
use std::path::Path;

use anyhow::{Context as _, Result};
use plotters::prelude::*;

use super::{PointResult, TradeResults};
use crate::eval::chart::{draw, finite_bounds, Axes, Layout};

/// Which of `(time, error)` points lie on the Pareto front (no other point is at most as slow and at most as
/// wrong, and strictly better in one); non-finite points never do.
pub fn pareto(pts: &[(f64, f64)]) -> Vec<bool> {
    pts.iter()
        .map(|&(t, e)| {
            t.is_finite()
                && e.is_finite()
                && !pts.iter().any(|&(t2, e2)| {
                    t2.is_finite() && e2.is_finite() && t2 <= t && e2 <= e && (t2 < t || e2 < e)
                })
        })
        .collect()
}

/// The current UTC date and time, `YYYY-MM-DD HH:MM` (civil-from-days, H. Hinnant's algorithm).
pub fn now_utc() -> String {
    let s = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map(|d| d.as_secs() as i64)
        .unwrap_or(0);
    format_utc(s)
}

fn format_utc(secs: i64) -> String {
    let days = secs.div_euclid(86_400);
    let rem = secs.rem_euclid(86_400);
    let z = days + 719_468;
    let era = z.div_euclid(146_097);
    let doe = z - era * 146_097;
    let yoe = (doe - doe / 1460 + doe / 36_524 - doe / 146_096) / 365;
    let doy = doe - (365 * yoe + yoe / 4 - yoe / 100);
    let mp = (5 * doy + 2) / 153;
    let d = doy - (153 * mp + 2) / 5 + 1;
    let m = if mp < 10 { mp + 3 } else { mp - 9 };
    let y = yoe + era * 400 + i64::from(m <= 2);
    format!(
        "{y:04}-{m:02}-{d:02} {:02}:{:02}",
        rem / 3600,
        (rem % 3600) / 60
    )
}

fn opt(v: Option<f64>, digits: usize) -> String {
    v.map(|x| format!("{x:.digits$}"))
        .unwrap_or_else(|| "-".into())
}

fn row(s: &mut String, p: &PointResult, mark: &str) {
    let q = &p.point;
    let _ = writeln!(
        s,
        "| {}{} | {} | {} {} | {}x{} | {} | {} | {:.0} | {:.0} / {:.0} / {:.0} | {:.1} | {:.3e} | {} | {} | {} | {} | {} | {} | {} |",
        q.name,
        mark,
        q.dtype,
        q.sampler,
        q.steps,
        q.size.0,
        q.size.1,
        if q.guidance == 1.0 {
            "off".to_string()
        } else {
            format!("{}", q.guidance)
        },
        q.cameras,
        p.ms_per_frame,
        p.conditioning_ms,
        p.denoise_ms,
        p.decode_ms,
        p.device_bytes as f64 / (1u64 << 20) as f64,
        p.nmse_vs_reference,
        p.psnr_vs_reference
            .map(|v| format!("{v:.2}"))
            .unwrap_or_else(|| "exact".into()),
        opt(p.psnr_vs_truth, 2),
        opt(p.vehicle_iou, 3),
        opt(p.mean_iou, 3),
        opt(p.seg_vehicle_iou, 3),
        opt(p.seg_marking_iou, 3),
        p.nonfinite
    );
}

const HEADER: &str = "| setting | dtype | sampler | size | w | cams | ms/frame | cond / denoise / decode ms | MiB | NMSE vs ref | PSNR vs ref dB | PSNR vs truth dB | vehicle IoU | mean IoU | vehicle IoU (seg) | marking IoU (seg) | non-finite |\n|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|\n";

pub fn markdown(r: &TradeResults) -> String {
    let mut s = String::new();
    let _ = writeln!(
        s,
        "# b2dr bench trade\n\nModel {} on {} ({} UTC), scenario {}, frames {:?}, cameras {:?}; seed {}; wall \
         {:.0} s.\nReference setting: f32, UniPC 50 steps, {}x{}, the model's guidance, {} camera(s). \
         Every point renders the same frames from the same initial noise; `*` marks the time / error Pareto \
         front, `(default)` the model's own setting.\n",
        r.model,
        r.device,
        r.date_utc,
        r.config.scenario,
        r.config.frames,
        r.cameras,
        r.config.seed,
        r.wall_s,
        r.render_size[0],
        r.render_size[1],
        r.cameras.len()
    );
    s.push_str(HEADER);
    for p in &r.points {
        let mut mark = String::new();
        if p.pareto {
            mark.push_str(" *");
        }
        if p.point.axis == "default" {
            mark.push_str(" (default)");
        }
        row(&mut s, p, &mark);
    }
    s.push_str("\n## Numerical extremes\n\n");
    s.push_str(HEADER);
    for p in &r.extremes {
        row(&mut s, p, "");
    }
    if !r.rollouts.is_empty() {
        s.push_str(
            "\n## Autoregressive rollouts (the model's setting, first camera; frame 1 from the recorded image)\n\n\
             | dtype | frames | non-finite values | PSNR first 10 % dB | PSNR last 10 % dB | ms/frame |\n\
             |---|---|---|---|---|---|\n",
        );
        for o in &r.rollouts {
            let _ = writeln!(
                s,
                "| {} | {} | {} | {} | {} | {:.0} |",
                o.dtype,
                o.frames,
                o.nonfinite,
                opt(o.psnr_first, 2),
                opt(o.psnr_last, 2),
                o.ms_per_frame
            );
        }
    }
    s
}

/// A scatter of (ms per frame, y) per point, the Pareto front joined, the default circled in red.
fn scatter(
    path: &Path,
    title: &str,
    y_label: &str,
    pts: &[(String, f64, f64, bool, bool)],
) -> Result<()> {
    let ok: Vec<_> = pts
        .iter()
        .filter(|p| p.1.is_finite() && p.2.is_finite())
        .collect();
    let (x0, x1, y0, y1) = finite_bounds(ok.iter().map(|p| (p.1, p.2)));
    let xpad = ((x1 - x0) * 0.08).max(1.0);
    let ypad = ((y1 - y0) * 0.1).max(0.5);
    let layout = Layout {
        size: (900, 560),
        caption: 17,
        margin: 14,
        x_label_area: 42,
        y_label_area: 60,
    };
    let axes = Axes {
        title,
        x_label: "wall time per frame, ms",
        y_label,
        x: (x0 - xpad)..(x1 + xpad * 3.0),
        y: (y0 - ypad)..(y1 + ypad),
        legend: SeriesLabelPosition::LowerRight,
    };
    draw(path, &layout, axes, |chart, e| {
        let mut front: Vec<(f64, f64)> = ok.iter().filter(|p| p.3).map(|p| (p.1, p.2)).collect();
        front.sort_by(|a, b| a.0.total_cmp(&b.0));
        chart
            .draw_series(LineSeries::new(
                front,
                RGBColor(40, 120, 40).stroke_width(2),
            ))
            .map_err(|x| e(&x))?
            .label("Pareto front")
            .legend(|(x, y)| {
                PathElement::new(
                    vec![(x, y), (x + 20, y)],
                    RGBColor(40, 120, 40).stroke_width(2),
                )
            });
        for p in &ok {
            let c = if p.3 {
                RGBColor(40, 120, 40)
            } else {
                RGBColor(60, 60, 160)
            };
            chart
                .draw_series(std::iter::once(Circle::new((p.1, p.2), 4, c.filled())))
                .map_err(|x| e(&x))?;
            if p.4 {
                chart
                    .draw_series(std::iter::once(Circle::new(
                        (p.1, p.2),
                        9,
                        RED.stroke_width(2),
                    )))
                    .map_err(|x| e(&x))?;
            }
            chart
                .draw_series(std::iter::once(Text::new(
                    p.0.clone(),
                    (p.1, p.2),
                    ("sans-serif", 12).into_font().color(&BLACK),
                )))
                .map_err(|x| e(&x))?;
        }
        Ok(())
    })
}

/// The model's name without the folder it came from (plot titles).
fn short(model: &str) -> &str {
    model.split(" (").next().unwrap_or(model)
}

pub fn write(out: &Path, r: &TradeResults) -> Result<()> {
    std::fs::create_dir_all(out).with_context(|| format!("creating {}", out.display()))?;
    std::fs::write(out.join("trade.json"), serde_json::to_string_pretty(r)?)
        .with_context(|| format!("writing {}", out.join("trade.json").display()))?;
    std::fs::write(out.join("trade.md"), markdown(r))
        .with_context(|| format!("writing {}", out.join("trade.md").display()))?;
    let refr = r.reference().map(|p| p.ms_per_frame).unwrap_or(f64::NAN);
    let pts: Vec<_> = r
        .points
        .iter()
        .filter(|p| p.point.axis != "reference")
        .map(|p| {
            (
                p.point.name.clone(),
                p.ms_per_frame,
                p.psnr_vs_reference.unwrap_or(f64::INFINITY),
                p.pareto,
                p.point.axis == "default",
            )
        })
        .collect();
    scatter(
        &out.join("trade.png"),
        &format!(
            "{}: time vs closeness to the reference (f32 UniPC 50: {refr:.0} ms, not drawn)",
            short(&r.model)
        ),
        "PSNR vs the reference setting, dB (higher = closer)",
        &pts,
    )?;
    let front = pareto(
        &r.points
            .iter()
            .map(|p| (p.ms_per_frame, -p.psnr_vs_truth.unwrap_or(f64::NAN)))
            .collect::<Vec<_>>(),
    );
    let pts: Vec<_> = r
        .points
        .iter()
        .zip(front)
        .map(|(p, f)| {
            (
                p.point.name.clone(),
                p.ms_per_frame,
                p.psnr_vs_truth.unwrap_or(f64::NAN),
                f,
                p.point.axis == "default",
            )
        })
        .collect();
    scatter(
        &out.join("trade_truth.png"),
        &format!("{}: time vs PSNR against the ground truth", short(&r.model)),
        "PSNR vs the ground truth, dB",
        &pts,
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn pareto_front_is_the_undominated_points() {
        let pts = [
            (1.0, 5.0),
            (2.0, 3.0),
            (3.0, 3.0),
            (4.0, 0.0),
            (2.0, 6.0),
            (f64::NAN, 0.0),
        ];
        assert_eq!(pareto(&pts), [true, true, false, true, false, false]);
    }

    #[test]
    fn utc_dates() {
        assert_eq!(format_utc(0), "1970-01-01 00:00");
        assert_eq!(format_utc(951_782_400), "2000-02-29 00:00");
        assert_eq!(format_utc(1_796_215_320), "2026-12-02 12:42");
    }
}
