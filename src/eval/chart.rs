//! The chart scaffolding every PNG plot of the evaluations shares (plotters, with an embedded font: DejaVu
//! Sans Mono, its licence in assets/fonts/, so a plot looks the same on every machine): the bounds of the
//! finite points, the canvas, caption, axes and legend. The plots themselves (`fidelity::plot`'s line chart,
//! `trade::report`'s Pareto scatter) only draw their series.
use std::ops::Range;
use std::path::Path;
use std::sync::Once;

use anyhow::{anyhow, Result};
use plotters::coord::types::RangedCoordf64;
use plotters::prelude::*;

static FONT: Once = Once::new();

/// Registers the embedded font as "sans-serif" (once per process).
pub fn register_font() {
    FONT.call_once(|| {
        // The bytes are the vendored font file: parsing it cannot fail unless the file is replaced.
        let _ = plotters::style::register_font(
            "sans-serif",
            FontStyle::Normal,
            include_bytes!("../../assets/fonts/DejaVuSansMono.ttf"),
        );
    });
}

/// (x0, x1, y0, y1) over the points with finite coordinates; (0, 1, 0, 1) when there is none.
pub fn finite_bounds(pts: impl IntoIterator<Item = (f64, f64)>) -> (f64, f64, f64, f64) {
    let (mut x0, mut x1, mut y0, mut y1) = (f64::MAX, f64::MIN, f64::MAX, f64::MIN);
    let mut any = false;
    for (x, y) in pts {
        if x.is_finite() && y.is_finite() {
            any = true;
            x0 = x0.min(x);
            x1 = x1.max(x);
            y0 = y0.min(y);
            y1 = y1.max(y);
        }
    }
    if any {
        (x0, x1, y0, y1)
    } else {
        (0.0, 1.0, 0.0, 1.0)
    }
}

/// The sizes of a chart: image, caption font, margin, and the areas of the x and y labels (pixels).
pub struct Layout {
    pub size: (u32, u32),
    pub caption: u32,
    pub margin: u32,
    pub x_label_area: u32,
    pub y_label_area: u32,
}

/// What a chart shows around its series.
pub struct Axes<'a> {
    pub title: &'a str,
    pub x_label: &'a str,
    pub y_label: &'a str,
    pub x: Range<f64>,
    pub y: Range<f64>,
    /// Where the legend of the labelled series goes.
    pub legend: SeriesLabelPosition,
}

/// The chart handed to a plot's drawing code.
pub type Chart<'a, 'b> =
    ChartContext<'a, BitMapBackend<'b>, Cartesian2d<RangedCoordf64, RangedCoordf64>>;

/// Turns a plotters error into one naming the file.
pub type PlotError<'a> = dyn Fn(&dyn std::fmt::Display) -> anyhow::Error + 'a;

/// Writes a PNG chart to `path`: white canvas, caption, mesh with axis labels, then `series` draws into the
/// chart, then the legend (label font 13, translucent white, black border) and the file is written.
pub fn draw(
    path: &Path,
    layout: &Layout,
    axes: Axes,
    series: impl FnOnce(&mut Chart, &PlotError) -> Result<()>,
) -> Result<()> {
    register_font();
    let e = |e: &dyn std::fmt::Display| anyhow!("plot {}: {e}", path.display());
    let root = BitMapBackend::new(path, layout.size).into_drawing_area();
    root.fill(&WHITE).map_err(|x| e(&x))?;
    let mut chart = ChartBuilder::on(&root)
        .caption(axes.title, ("sans-serif", layout.caption))
        .margin(layout.margin)
        .x_label_area_size(layout.x_label_area)
        .y_label_area_size(layout.y_label_area)
        .build_cartesian_2d(axes.x, axes.y)
        .map_err(|x| e(&x))?;
    chart
        .configure_mesh()
        .x_desc(axes.x_label)
        .y_desc(axes.y_label)
        .label_style(("sans-serif", 13))
        .draw()
        .map_err(|x| e(&x))?;
    series(&mut chart, &e)?;
    chart
        .configure_series_labels()
        .label_font(("sans-serif", 13))
        .background_style(WHITE.mix(0.85))
        .border_style(BLACK)
        .position(axes.legend)
        .draw()
        .map_err(|x| e(&x))?;
    root.present().map_err(|x| e(&x))?;
    Ok(())
}
