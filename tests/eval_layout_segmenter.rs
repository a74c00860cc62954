//! The two layout scores of eval-render on ground-truth frames of a held-out dense scenario
//! (`builtin:town:100:60`, recorded frames 8, 16, 24, CAM_FRONT, 112 x 200; the segmenter trained on seeds
//! 1000-1011): the
//! colour classifier is exact on the ground truth but collapses under an invisible change; the segmenter keeps its
//! score under it and still falls when the image is too blurred to show the objects.
use b2dr::eval::fidelity::metrics::{IouCounts, PaletteClassifier};
use b2dr::eval::fidelity::segmenter::LayoutSegmenter;
use b2dr::eval::fidelity::{LANE_MARKING, VEHICLE};
use b2dr::world::{load_all, World};

const H: usize = 112;
const W: usize = 200;

/// (RGB8, class ids) of CAM_FRONT at recorded frames 8, 16, 24.
fn truth() -> Vec<(Vec<u8>, Vec<u8>)> {
    let sc = load_all("builtin:town:100:60").unwrap().remove(0);
    let cam = sc.rig.camera("CAM_FRONT").unwrap();
    let world = World::new(&sc);
    [8usize, 16, 24]
        .iter()
        .map(|&fi| {
            let f = &sc.rig.frames[fi];
            let step = b2dr::world::export::plan::frame_step(&sc, f);
            let mut r = world
                .render_step(std::slice::from_ref(cam), &f.ego2global, step, W, H, 1)
                .unwrap();
            let c = r.remove(0);
            (c.rgb, c.class)
        })
        .collect()
}

/// i.i.d. noise, uniform in [-a, a] levels (a deterministic hash per byte), clamped.
fn noised(rgb: &[u8], a: i32, seed: u64) -> Vec<u8> {
    rgb.iter()
        .enumerate()
        .map(|(i, &v)| {
            let h = b2dr::world::palette::mix64(i as u64 ^ seed.wrapping_mul(0x9e37_79b9));
            let n = (h % (2 * a as u64 + 1)) as i32 - a;
            (v as i32 + n).clamp(0, 255) as u8
        })
        .collect()
}

/// A box blur of radius r (per channel, the window clipped at the borders).
fn box_blur(rgb: &[u8], r: usize) -> Vec<u8> {
    let mut out = vec![0u8; rgb.len()];
    for y in 0..H {
        for x in 0..W {
            for c in 0..3 {
                let (mut s, mut n) = (0u32, 0u32);
                for yy in y.saturating_sub(r)..(y + r + 1).min(H) {
                    for xx in x.saturating_sub(r)..(x + r + 1).min(W) {
                        s += rgb[(yy * W + xx) * 3 + c] as u32;
                        n += 1;
                    }
                }
                out[(y * W + x) * 3 + c] = ((s + n / 2) / n) as u8;
            }
        }
    }
    out
}

fn scores(
    classify: &dyn Fn(&[u8]) -> Vec<u8>,
    imgs: &[Vec<u8>],
    t: &[(Vec<u8>, Vec<u8>)],
) -> (f64, f64) {
    let mut c = IouCounts::default();
    for (img, (_, cls)) in imgs.iter().zip(t) {
        c.add(&classify(img), cls);
    }
    (c.iou(VEHICLE).unwrap(), c.iou(LANE_MARKING).unwrap())
}

#[test]
fn the_segmenter_scores_what_is_drawn_and_the_colour_classifier_colour_exactness() {
    let t = truth();
    let pairs: Vec<(&[u8], &[u8])> = t.iter().map(|(r, c)| (&r[..], &c[..])).collect();
    let clf = PaletteClassifier::fit(&pairs).unwrap();
    let seg = LayoutSegmenter::builtin().unwrap();
    let colour = |img: &[u8]| clf.classify(img);
    let segment = |img: &[u8]| seg.classify(img, H, W).unwrap();
    let clean: Vec<Vec<u8>> = t.iter().map(|(r, _)| r.clone()).collect();
    let noisy: Vec<Vec<u8>> = clean
        .iter()
        .enumerate()
        .map(|(k, r)| noised(r, 7, k as u64))
        .collect();
    let blurred: Vec<Vec<u8>> = clean.iter().map(|r| box_blur(r, 4)).collect();
    let (cv, cm) = scores(&colour, &clean, &t);
    let (cnv, cnm) = scores(&colour, &noisy, &t);
    let (sv, sm) = scores(&segment, &clean, &t);
    let (snv, snm) = scores(&segment, &noisy, &t);
    let (sbv, sbm) = scores(&segment, &blurred, &t);
    eprintln!(
        "colour: clean {cv:.3} / {cm:.3}, noise {cnv:.3} / {cnm:.3}; segmenter: clean {sv:.3} / {sm:.3}, \
         noise {snv:.3} / {snm:.3}, blur 9 px {sbv:.3} / {sbm:.3} (vehicle / lane marking IoU)"
    );
    // the colour classifier: near its ceiling on the ground truth it was fitted on (vehicle colours overlap
    // the buildings' there), below half of it under +-7 levels of noise
    assert!(cv > 0.7 && cnv < 0.5 * cv, "colour vehicle {cv} -> {cnv}");
    // the segmenter: a useful ceiling on unseen ground truth, unmoved by the noise, and not fooled by a blur
    // that erases the cars' and markings' shapes
    assert!(
        sv >= SEG_VEHICLE_MIN && sm >= SEG_MARKING_MIN,
        "segmenter ceiling {sv} / {sm}"
    );
    assert!(
        (snv - sv).abs() < 0.05 && (snm - sm).abs() < 0.05,
        "noise moved the segmenter: {sv} -> {snv}, {sm} -> {snm}"
    );
    assert!(
        sbv < 0.7 * sv && sbm < 0.5 * sm,
        "a 9-px blur keeps the segmenter's score: {sv} -> {sbv}, {sm} -> {sbm}"
    );
}

/// The committed weights measured 0.778 / 0.741 here (tools/layout_ceiling.py, docs/eval_render.md); a retrained
/// segmenter must not be a worse judge.
const SEG_VEHICLE_MIN: f64 = 0.65;
const SEG_MARKING_MIN: f64 = 0.6;
