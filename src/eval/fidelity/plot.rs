//! Line charts (PNG) of `b2dr eval-render` on the shared scaffolding of [`crate::eval::chart`].
use std::path::Path;

use anyhow::Result;
use plotters::prelude::*;

use crate::eval::chart::{draw, finite_bounds, Axes, Layout};

/// One line of a chart: (x, y) points in order; points with a non-finite y are left out.
pub struct Series {
    pub name: String,
    pub points: Vec<(f64, f64)>,
}

/// A line chart of `series` written to `path` (800 x 480 PNG).
pub fn line_chart(
    path: &Path,
    title: &str,
    x_label: &str,
    y_label: &str,
    series: &[Series],
) -> Result<()> {
    let (x0, x1, y0, y1) = finite_bounds(series.iter().flat_map(|s| s.points.iter().copied()));
    let pad = ((y1 - y0) * 0.08).max(0.5);
    let (y0, y1) = (y0 - pad, y1 + pad);
    let x1 = if x1 > x0 { x1 } else { x0 + 1.0 };
    let layout = Layout {
        size: (800, 480),
        caption: 18,
        margin: 12,
        x_label_area: 40,
        y_label_area: 55,
    };
    let axes = Axes {
        title,
        x_label,
        y_label,
        x: x0..x1,
        y: y0..y1,
        legend: SeriesLabelPosition::LowerLeft,
    };
    draw(path, &layout, axes, |chart, e| {
        for (i, s) in series.iter().enumerate() {
            let c = Palette99::pick(i).to_rgba();
            let p: Vec<(f64, f64)> = s
                .points
                .iter()
                .copied()
                .filter(|p| p.1.is_finite())
                .collect();
            chart
                .draw_series(LineSeries::new(p.clone(), c.stroke_width(2)))
                .map_err(|x| e(&x))?
                .label(s.name.clone())
                .legend(move |(x, y)| {
                    PathElement::new(vec![(x, y), (x + 20, y)], c.stroke_width(2))
                });
            chart
                .draw_series(p.into_iter().map(|q| Circle::new(q, 3, c.filled())))
                .map_err(|x| e(&x))?;
        }
        Ok(())
    })
}
