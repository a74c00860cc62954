//! The Savitzky-Golay port against scipy's own output (golden file from tools/metrics_savgol_golden.py;
//! regenerate with `python3 tools/metrics_savgol_golden.py > tests/fixtures/nuplan/savgol_golden.json`).
use b2dr::metrics::savgol::savgol_filter;
use serde::Deserialize;

#[derive(Deserialize)]
struct Case {
    window: usize,
    poly: usize,
    deriv: usize,
    delta: f64,
    y: Vec<f64>,
}

#[derive(Deserialize)]
struct Golden {
    x: Vec<f64>,
    cases: Vec<Case>,
}

#[test]
fn savgol_matches_scipy() {
    let g: Golden =
        serde_json::from_str(include_str!("fixtures/nuplan/savgol_golden.json")).unwrap();
    for c in &g.cases {
        let y = savgol_filter(&g.x, c.window, c.poly, c.deriv, c.delta).unwrap();
        let scale = c.y.iter().fold(1.0f64, |m, v| m.max(v.abs()));
        for (i, (a, b)) in y.iter().zip(&c.y).enumerate() {
            // Relative to the signal's scale: LAPACK's lstsq and our QR differ by a few ulps.
            assert!(
                (a - b).abs() <= 1e-12 * scale,
                "window {} poly {} deriv {} i {i}: {a} vs scipy {b}",
                c.window,
                c.poly,
                c.deriv
            );
        }
    }
}
