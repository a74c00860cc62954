//! The outputs of `b2dr eval-render`: eval.json (every scored image), eval.md (the tables), the plots
//! (psnr_vs_deviation.png, psnr_vs_frame.png) and the ground truth | rendered strips (strips/).
use std::collections::BTreeMap;
use std::fmt::Write as _;
use std::path::Path;

use anyhow::{Context as _, Result};
use image::RgbImage;

use super::metrics::{psnr, ssim, IouCounts};
use super::plot::{line_chart, Series};
use super::scene::Deviation;
use super::{Results, Score};
use crate::world::palette::SemanticClass;

pub const VEHICLE: u8 = SemanticClass::Vehicle as u8;
/// Painted lane markings (dividers, edge lines, stop lines and crosswalk stripes of the synthetic world).
pub const LANE_MARKING: u8 = SemanticClass::LaneMarking as u8;

/// PSNR and SSIM of one image (the layout score is added once the classifier is fitted).
#[allow(clippy::too_many_arguments)]
pub fn score(
    scenario: &str,
    camera: &str,
    frame: usize,
    step: usize,
    deviation: Deviation,
    setting: &str,
    rgb: &[u8],
    truth: &[u8],
    size: (usize, usize),
) -> Result<Score> {
    Ok(Score {
        scenario: scenario.into(),
        camera: camera.into(),
        frame,
        step,
        deviation,
        setting: setting.into(),
        psnr: psnr(rgb, truth)?,
        ssim: ssim(rgb, truth, size.0, size.1)?,
        vehicle_iou: None,
        marking_iou: None,
        mean_iou: None,
        seg_vehicle_iou: None,
        seg_marking_iou: None,
        iou: IouCounts::default(),
        seg_iou: IouCounts::default(),
    })
}

/// The classes of the layout score: those present in the ground truth.
pub fn scored_classes(ceiling: &IouCounts) -> Vec<u8> {
    ceiling
        .counts
        .iter()
        .filter(|(_, (_, u))| *u > 0)
        .map(|(c, _)| *c)
        .collect()
}

fn class_name(c: u8) -> String {
    SemanticClass::ALL
        .get(c as usize)
        .map(|s| s.name().to_string())
        .unwrap_or_else(|| format!("class {c}"))
}

pub fn class_table(c: &IouCounts, classes: &[u8]) -> BTreeMap<String, Option<f64>> {
    let mut m: BTreeMap<String, Option<f64>> =
        classes.iter().map(|&k| (class_name(k), c.iou(k))).collect();
    m.insert("mean".into(), c.mean_iou(classes));
    m
}

/// Aggregate of a group of scored images.
struct Agg {
    n: usize,
    exact: usize,
    psnr: Option<f64>,
    ssim: f64,
    vehicle: Option<f64>,
    marking: Option<f64>,
    miou: Option<f64>,
    seg_vehicle: Option<f64>,
    seg_marking: Option<f64>,
}

fn agg<'a>(v: impl Iterator<Item = &'a Score>, classes: &[u8]) -> Option<Agg> {
    let v: Vec<&Score> = v.collect();
    if v.is_empty() {
        return None;
    }
    let finite: Vec<f64> = v.iter().filter_map(|s| s.psnr).collect();
    let (mut iou, mut seg) = (IouCounts::default(), IouCounts::default());
    for s in &v {
        iou.merge(&s.iou);
        seg.merge(&s.seg_iou);
    }
    Some(Agg {
        n: v.len(),
        exact: v.len() - finite.len(),
        psnr: (!finite.is_empty()).then(|| finite.iter().sum::<f64>() / finite.len() as f64),
        ssim: v.iter().map(|s| s.ssim).sum::<f64>() / v.len() as f64,
        vehicle: iou.iou(VEHICLE),
        marking: iou.iou(LANE_MARKING),
        miou: iou.mean_iou(classes),
        seg_vehicle: seg.iou(VEHICLE),
        seg_marking: seg.iou(LANE_MARKING),
    })
}

/// Mean PSNR change from the logged path to deviation `d` of one setting, over the cases scored (finite
/// PSNR) both displaced and on the logged path (same scenario, camera and frame), and their count.
fn falloff(r: &Results, setting: &str, d: Deviation) -> Option<(f64, usize)> {
    let drops: Vec<f64> = r
        .single
        .iter()
        .filter(|x| x.setting == setting && x.deviation == d)
        .filter_map(|x| {
            let on_log = r.single.iter().find(|y| {
                y.setting == setting
                    && y.deviation.is_none()
                    && y.scenario == x.scenario
                    && y.camera == x.camera
                    && y.frame == x.frame
            })?;
            Some(x.psnr? - on_log.psnr?)
        })
        .collect();
    (!drops.is_empty()).then(|| (drops.iter().sum::<f64>() / drops.len() as f64, drops.len()))
}

/// "Under deviation, PSNR falls off more slowly with references than without": the falloff of each setting
/// and the references' gain (falloff with references minus falloff without; > 0: the references help more
/// off the log), with the previous frame (b2dr vs no-refs) and without it (no-prev vs masks-only).
fn falloff_table(md: &mut String, r: &Results, devs: &[Deviation]) -> Result<()> {
    let pairs = [("b2dr", "no-refs"), ("no-prev", "masks-only")];
    writeln!(
        md,
        "\n## Falloff under deviation: PSNR at the deviation minus PSNR on the logged path (dB, same frames)\n\n\
         Refs gain = falloff with references - falloff without (> 0: the references slow the falloff).\n\n\
         | deviation | images | b2dr (refs + prev) | no-refs (prev) | refs gain, with prev | \
         no-prev (refs) | masks-only (neither) | refs gain, without prev |\n|---|---|---|---|---|---|---|---|"
    )?;
    for d in devs.iter().filter(|d| !d.is_none()) {
        let mut cells = vec![];
        let mut n = None;
        for (with, without) in pairs {
            let (a, b) = (falloff(r, with, *d), falloff(r, without, *d));
            n = n.or(a.map(|a| a.1));
            cells.push(f2(a.map(|a| a.0)));
            cells.push(f2(b.map(|b| b.0)));
            cells.push(f2(a.zip(b).map(|(a, b)| a.0 - b.0)));
        }
        writeln!(
            md,
            "| {} | {} | {} |",
            d.label(),
            n.map(|n| n.to_string()).unwrap_or_else(|| "-".into()),
            cells.join(" | ")
        )?;
    }
    Ok(())
}

fn f2(x: Option<f64>) -> String {
    x.map(|v| format!("{v:.2}")).unwrap_or_else(|| "-".into())
}

fn f3(x: Option<f64>) -> String {
    x.map(|v| format!("{v:.3}")).unwrap_or_else(|| "-".into())
}

fn psnr_cell(a: &Agg) -> String {
    match (a.psnr, a.exact) {
        (None, _) => "exact (= truth)".into(),
        (Some(p), 0) => format!("{p:.2}"),
        (Some(p), e) => format!("{p:.2} ({e} exact)"),
    }
}

/// Images for the strips: per deviation of the first case (label, truth per camera, per setting images);
/// per drift frame (frame, truth, rendered).
#[derive(Default)]
pub struct Strips {
    pub single: Vec<(String, Cams, Row)>,
    pub drift: Vec<(usize, Cams, Cams)>,
}

/// Interleaved RGB8 images, one per camera.
pub type Cams = Vec<Vec<u8>>;
/// (setting, its images) in the order shown.
pub type Row = Vec<(String, Cams)>;

/// Images side by side in a row, rows stacked, 4-pixel white gaps.
fn grid(rows: &[Vec<&[u8]>], size: (usize, usize)) -> RgbImage {
    let (h, w) = size;
    let gap = 4;
    let cols = rows.iter().map(|r| r.len()).max().unwrap_or(0) as u32;
    let (gw, gh) = (
        cols * (w as u32 + gap) - gap.min(cols * gap),
        rows.len() as u32 * (h as u32 + gap) - gap.min(rows.len() as u32 * gap),
    );
    let mut img = RgbImage::from_pixel(gw.max(1), gh.max(1), image::Rgb([255, 255, 255]));
    for (r, row) in rows.iter().enumerate() {
        for (c, px) in row.iter().enumerate() {
            let (x0, y0) = (c as u32 * (w as u32 + gap), r as u32 * (h as u32 + gap));
            for y in 0..h {
                for x in 0..w {
                    let p = 3 * (y * w + x);
                    img.put_pixel(
                        x0 + x as u32,
                        y0 + y as u32,
                        image::Rgb([px[p], px[p + 1], px[p + 2]]),
                    );
                }
            }
        }
    }
    img
}

fn file_label(s: &str) -> String {
    crate::scene::safe_name(&s.replace(' ', "_").replace(',', ""))
}

/// Writes eval.json, eval.md, the plots and the strips.
pub fn write(
    out: &Path,
    r: &Results,
    classes: &[u8],
    strips: &Strips,
    size: (usize, usize),
) -> Result<()> {
    std::fs::write(out.join("eval.json"), serde_json::to_string_pretty(r)?)
        .with_context(|| format!("writing {}", out.join("eval.json").display()))?;
    let mut md = String::new();
    let cfg = &r.config;
    writeln!(
        md,
        "# b2dr eval-render\n\nModel `{}`, render {} x {}, cameras {:?}, scenarios {:?}, recorded frames {:?}, \
         seed {}, {}.\n",
        r.model, r.render_size[0], r.render_size[1], cfg.cameras, cfg.scenarios, cfg.frames, cfg.seed, cfg.dtype
    )?;
    let settings: Vec<String> = {
        let mut v: Vec<String> = vec![];
        for s in &r.single {
            if !v.contains(&s.setting) {
                v.push(s.setting.clone());
            }
        }
        v
    };
    writeln!(
        md,
        "## Logged path (ego on the log, logged agents; previous frame = ground truth 0.5 s earlier)\n\n\
         Layout score two ways: the colour classifier (vehicle, lane-marking, mean IoU: colour exactness; the \
         ground truth plus 4 levels of noise takes the gate frames' vehicle IoU from 0.97 to 0.27) and the \
         layout segmenter (seg: is the class drawn there; docs/eval_render.md).\n\n\
         | setting | images | PSNR dB | SSIM | vehicle IoU | lane-marking IoU | mean IoU | vehicle IoU (seg) | \
         lane-marking IoU (seg) |\n\
         |---|---|---|---|---|---|---|---|---|"
    )?;
    for s in &settings {
        if let Some(a) = agg(
            r.single
                .iter()
                .filter(|x| &x.setting == s && x.deviation.is_none()),
            classes,
        ) {
            writeln!(
                md,
                "| {s} | {} | {} | {:.4} | {} | {} | {} | {} | {} |",
                a.n,
                psnr_cell(&a),
                a.ssim,
                f3(a.vehicle),
                f3(a.marking),
                f3(a.miou),
                f3(a.seg_vehicle),
                f3(a.seg_marking)
            )?;
        }
    }
    let devs: Vec<Deviation> = {
        let mut v: Vec<Deviation> = vec![];
        for s in &r.single {
            if !v.contains(&s.deviation) {
                v.push(s.deviation);
            }
        }
        v
    };
    let dev_settings = [
        "b2dr",
        "no-refs",
        "no-prev",
        "masks-only",
        "copy-prev",
        "copy-nearest",
    ];
    writeln!(
        md,
        "\n## Deviation sweep (references retrieved from the log at the displaced pose)\n\n\
         PSNR dB / vehicle IoU / vehicle IoU (seg) per setting.\n\n| deviation | {} |\n|---|{}",
        dev_settings.join(" | "),
        "---|".repeat(dev_settings.len())
    )?;
    let mut dev_series: Vec<(Series, Series)> = dev_settings
        .iter()
        .map(|s| {
            (
                Series {
                    name: s.to_string(),
                    points: vec![],
                },
                Series {
                    name: s.to_string(),
                    points: vec![],
                },
            )
        })
        .collect();
    for d in &devs {
        let mut cells = vec![];
        for (k, s) in dev_settings.iter().enumerate() {
            match agg(
                r.single
                    .iter()
                    .filter(|x| x.setting == *s && x.deviation == *d),
                classes,
            ) {
                Some(a) => {
                    cells.push(format!(
                        "{} / {} / {}",
                        psnr_cell(&a),
                        f3(a.vehicle),
                        f3(a.seg_vehicle)
                    ));
                    let y = a.psnr.unwrap_or(f64::NAN);
                    if d.yaw_deg == 0.0 {
                        dev_series[k].0.points.push((d.lateral_m, y));
                    }
                    if d.lateral_m == 0.0 {
                        dev_series[k].1.points.push((d.yaw_deg, y));
                    }
                }
                None => cells.push("-".into()),
            }
        }
        writeln!(md, "| {} | {} |", d.label(), cells.join(" | "))?;
    }
    falloff_table(&mut md, r, &devs)?;
    let (lat, yaw): (Vec<Series>, Vec<Series>) = dev_series.into_iter().unzip();
    line_chart(
        &out.join("psnr_vs_lateral.png"),
        "PSNR vs lateral displacement (copy-nearest at 0 m = exact)",
        "lateral displacement (m)",
        "PSNR (dB)",
        &lat,
    )?;
    line_chart(
        &out.join("psnr_vs_yaw.png"),
        "PSNR vs yaw displacement (copy-nearest at 0 deg = exact)",
        "yaw (deg)",
        "PSNR (dB)",
        &yaw,
    )?;
    if !r.drift.is_empty() {
        let d = cfg.drift_frames;
        let first = (2.min(d), 10.min(d));
        let last = ((d.saturating_sub(9)).max(1), d);
        writeln!(
            md,
            "\n## Autoregressive drift ({d} frames at 2 Hz on the logged path, frame 1 from the recorded image)\n\n\
             | setting | PSNR frames {}-{} | PSNR frames {}-{} | last - first | SSIM (all) | non-finite values |\n\
             |---|---|---|---|---|---|",
            first.0, first.1, last.0, last.1
        )?;
        let mut names: Vec<String> = vec![];
        for s in &r.drift {
            if !names.contains(&s.setting) {
                names.push(s.setting.clone());
            }
        }
        let mut series = vec![];
        for s in &names {
            let of = |a: usize, b: usize| {
                agg(
                    r.drift
                        .iter()
                        .filter(|x| &x.setting == s && x.frame >= a && x.frame <= b),
                    classes,
                )
            };
            let (fa, la, all) = (of(first.0, first.1), of(last.0, last.1), of(1, d));
            let p = |a: &Option<Agg>| a.as_ref().and_then(|a| a.psnr);
            writeln!(
                md,
                "| {s} | {} | {} | {} | {} | {} |",
                f2(p(&fa)),
                f2(p(&la)),
                f2(p(&la).zip(p(&fa)).map(|(l, f)| l - f)),
                all.map(|a| format!("{:.4}", a.ssim)).unwrap_or("-".into()),
                r.drift_nonfinite.get(s).copied().unwrap_or(0)
            )?;
            series.push(Series {
                name: s.clone(),
                points: (1..=d)
                    .filter_map(|f| of(f, f).and_then(|a| a.psnr).map(|p| (f as f64, p)))
                    .collect(),
            });
        }
        line_chart(
            &out.join("psnr_vs_frame.png"),
            "PSNR over an autoregressive rollout",
            "frame (2 Hz)",
            "PSNR (dB)",
            &series,
        )?;
    }
    writeln!(
        md,
        "\n## Layout score ceiling (the colour classifier and the segmenter on the ground truth itself)\n\n\
         | class | IoU | IoU (seg) |\n|---|---|---|"
    )?;
    for (k, v) in &r.classifier_ceiling {
        let sv = r.segmenter_ceiling.get(k).copied().flatten();
        writeln!(md, "| {k} | {} | {} |", f3(*v), f3(sv))?;
    }
    if !r.skipped.is_empty() {
        writeln!(md, "\n## Skipped cases\n")?;
        for s in &r.skipped {
            writeln!(md, "- {s}")?;
        }
    }
    // strips
    let sd = out.join("strips");
    std::fs::create_dir_all(&sd)?;
    writeln!(md, "\n## Strips (strips/)\n")?;
    for (label, truth, row) in &strips.single {
        let rows: Vec<Vec<&[u8]>> = (0..truth.len())
            .map(|k| {
                std::iter::once(&truth[k][..])
                    .chain(row.iter().map(|(_, imgs)| &imgs[k][..]))
                    .collect()
            })
            .collect();
        let name = format!("single_{}.png", file_label(label));
        grid(&rows, size).save(sd.join(&name))?;
        writeln!(
            md,
            "- `{name}`: {label}; columns: ground truth | {}; one row per camera",
            row.iter()
                .map(|(s, _)| s.as_str())
                .collect::<Vec<_>>()
                .join(" | ")
        )?;
    }
    if !strips.drift.is_empty() {
        let d = strips.drift.len();
        let pick: Vec<usize> = [1, 2, 5, 10, 20, 30, 40]
            .into_iter()
            .filter(|&f| f <= d)
            .collect();
        let rows: Vec<Vec<&[u8]>> = strips
            .drift
            .iter()
            .filter(|(f, _, _)| pick.contains(f))
            .map(|(_, t, r)| (0..t.len()).flat_map(|k| [&t[k][..], &r[k][..]]).collect())
            .collect();
        grid(&rows, size).save(sd.join("drift.png"))?;
        writeln!(
            md,
            "- `drift.png`: b2dr drift frames {pick:?} (rows); columns: ground truth | rendered per camera"
        )?;
    }
    writeln!(
        md,
        "\nPlots: psnr_vs_lateral.png, psnr_vs_yaw.png{}.",
        if r.drift.is_empty() {
            ""
        } else {
            ", psnr_vs_frame.png"
        }
    )?;
    std::fs::write(out.join("eval.md"), md)?;
    Ok(())
}
