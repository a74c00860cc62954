//! Image fidelity metrics of `b2dr eval-render` (world.md 4), on interleaved RGB8 images `(H, W, 3)`:
//! - PSNR over all pixels and channels, peak 255; `None` when the images are identical (the ceiling);
//! - SSIM (Wang et al. 2004): 11 x 11 Gaussian window, sigma 1.5, K1 = 0.01, K2 = 0.03, L = 255, computed per
//!   channel over the windows that lie inside the image ("valid"), averaged over windows and channels;
//! - the layout score: a fixed colour classifier ([`PaletteClassifier`]) turns an image into a class image;
//!   per-class IoU against the true class image of the ground-truth renderer.
use std::collections::HashMap;

use anyhow::{ensure, Result};

/// Peak signal-to-noise ratio (dB) of `a` against `b`; `None` when they are equal.
pub fn psnr(a: &[u8], b: &[u8]) -> Result<Option<f64>> {
    ensure!(
        a.len() == b.len() && !a.is_empty(),
        "psnr: {} vs {} values",
        a.len(),
        b.len()
    );
    let se: f64 = a
        .iter()
        .zip(b)
        .map(|(&x, &y)| {
            let d = x as f64 - y as f64;
            d * d
        })
        .sum();
    let mse = se / a.len() as f64;
    Ok((mse > 0.0).then(|| 10.0 * (255.0f64 * 255.0 / mse).log10()))
}

const WIN: usize = 11;
const SIGMA: f64 = 1.5;

fn gauss_window() -> [f64; WIN] {
    let mut g = [0.0; WIN];
    let c = (WIN / 2) as f64;
    for (i, v) in g.iter_mut().enumerate() {
        let d = i as f64 - c;
        *v = (-d * d / (2.0 * SIGMA * SIGMA)).exp();
    }
    let s: f64 = g.iter().sum();
    g.map(|v| v / s)
}

/// Separable 'valid' filtering of one plane `(h, w)` with the window: `(h - 10, w - 10)`.
fn filter_valid(x: &[f64], h: usize, w: usize, g: &[f64; WIN]) -> Vec<f64> {
    let (oh, ow) = (h + 1 - WIN, w + 1 - WIN);
    let mut tmp = vec![0.0; h * ow];
    for r in 0..h {
        for c in 0..ow {
            tmp[r * ow + c] = (0..WIN).map(|k| g[k] * x[r * w + c + k]).sum();
        }
    }
    let mut out = vec![0.0; oh * ow];
    for r in 0..oh {
        for c in 0..ow {
            out[r * ow + c] = (0..WIN).map(|k| g[k] * tmp[(r + k) * ow + c]).sum();
        }
    }
    out
}

/// Mean SSIM of `a` against `b`, both `(h, w, 3)` RGB8; each side must be at least 11 pixels.
pub fn ssim(a: &[u8], b: &[u8], h: usize, w: usize) -> Result<f64> {
    ensure!(
        a.len() == 3 * h * w && b.len() == 3 * h * w,
        "ssim: images of {} and {} values for {h} x {w} x 3",
        a.len(),
        b.len()
    );
    ensure!(
        h >= WIN && w >= WIN,
        "ssim: {h} x {w} is smaller than the {WIN} x {WIN} window"
    );
    let g = gauss_window();
    let (c1, c2) = ((0.01f64 * 255.0).powi(2), (0.03f64 * 255.0).powi(2));
    let mut total = 0.0;
    let mut count = 0usize;
    for ch in 0..3 {
        let pa: Vec<f64> = (0..h * w).map(|p| a[3 * p + ch] as f64).collect();
        let pb: Vec<f64> = (0..h * w).map(|p| b[3 * p + ch] as f64).collect();
        let prod =
            |x: &[f64], y: &[f64]| -> Vec<f64> { x.iter().zip(y).map(|(u, v)| u * v).collect() };
        let ma = filter_valid(&pa, h, w, &g);
        let mb = filter_valid(&pb, h, w, &g);
        let saa = filter_valid(&prod(&pa, &pa), h, w, &g);
        let sbb = filter_valid(&prod(&pb, &pb), h, w, &g);
        let sab = filter_valid(&prod(&pa, &pb), h, w, &g);
        for i in 0..ma.len() {
            let (mx, my) = (ma[i], mb[i]);
            let vx = saa[i] - mx * mx;
            let vy = sbb[i] - my * my;
            let cxy = sab[i] - mx * my;
            total += ((2.0 * mx * my + c1) * (2.0 * cxy + c2))
                / ((mx * mx + my * my + c1) * (vx + vy + c2));
            count += 1;
        }
    }
    Ok(total / count as f64)
}

/// Colour bins per channel of the classifier (5 bits: 32 levels).
const LEVELS: usize = 32;

fn bin(p: &[u8]) -> usize {
    let q = |v: u8| v as usize * LEVELS / 256;
    (q(p[0]) * LEVELS + q(p[1])) * LEVELS + q(p[2])
}

fn bin_centre(b: usize) -> [f64; 3] {
    let c = |q: usize| (q as f64 + 0.5) * 256.0 / LEVELS as f64;
    [
        c(b / (LEVELS * LEVELS)),
        c((b / LEVELS) % LEVELS),
        c(b % LEVELS),
    ]
}

/// The fixed "nearest palette colour" classifier of the layout score: fitted once on ground-truth images and
/// their class images (every colour bin of 32^3 takes the class most of its ground-truth pixels have; ties:
/// the lower class id), applied unchanged to every image scored. A colour bin no ground-truth pixel fell in
/// takes the class of the nearest filled bin (Euclidean in RGB; ties: the lower bin). Deterministic.
pub struct PaletteClassifier {
    table: Vec<Option<u8>>,
    filled: Vec<(usize, u8)>,
    nearest: std::cell::RefCell<HashMap<usize, u8>>,
}

impl PaletteClassifier {
    /// `samples`: (RGB8 `(H, W, 3)`, class ids `(H, W)`) pairs of the ground truth.
    pub fn fit(samples: &[(&[u8], &[u8])]) -> Result<Self> {
        let mut votes: HashMap<usize, HashMap<u8, u64>> = HashMap::new();
        for (rgb, cls) in samples {
            ensure!(
                rgb.len() == 3 * cls.len(),
                "classifier: {} RGB values for {} class ids",
                rgb.len(),
                cls.len()
            );
            for (p, &c) in cls.iter().enumerate() {
                *votes
                    .entry(bin(&rgb[3 * p..3 * p + 3]))
                    .or_default()
                    .entry(c)
                    .or_default() += 1;
            }
        }
        ensure!(!votes.is_empty(), "classifier: no ground-truth pixels");
        let mut table = vec![None; LEVELS * LEVELS * LEVELS];
        for (b, v) in &votes {
            let best = v
                .iter()
                .max_by(|(ca, na), (cb, nb)| na.cmp(nb).then(cb.cmp(ca)))
                .map(|(c, _)| *c);
            table[*b] = best;
        }
        let filled = table
            .iter()
            .enumerate()
            .filter_map(|(b, c)| c.map(|c| (b, c)))
            .collect();
        Ok(Self {
            table,
            filled,
            nearest: Default::default(),
        })
    }

    fn class_of_bin(&self, b: usize) -> u8 {
        if let Some(c) = self.table[b] {
            return c;
        }
        if let Some(&c) = self.nearest.borrow().get(&b) {
            return c;
        }
        let p = bin_centre(b);
        let mut best = (f64::INFINITY, 0u8);
        for &(fb, c) in &self.filled {
            let q = bin_centre(fb);
            let d = (0..3).map(|k| (p[k] - q[k]).powi(2)).sum::<f64>();
            if d < best.0 {
                best = (d, c);
            }
        }
        self.nearest.borrow_mut().insert(b, best.1);
        best.1
    }

    /// The class image `(H, W)` of an RGB8 image `(H, W, 3)`.
    pub fn classify(&self, rgb: &[u8]) -> Vec<u8> {
        rgb.chunks_exact(3)
            .map(|p| self.class_of_bin(bin(p)))
            .collect()
    }
}

/// Per-class intersection and union pixel counts of a predicted class image against the truth, accumulated
/// over images (IoU = sum of intersections / sum of unions, the usual dataset-level IoU).
#[derive(Clone, Debug, Default, PartialEq)]
pub struct IouCounts {
    /// class id -> (intersection, union)
    pub counts: std::collections::BTreeMap<u8, (u64, u64)>,
}

impl IouCounts {
    pub fn add(&mut self, pred: &[u8], truth: &[u8]) {
        let mut seen = [false; 256];
        for (&p, &t) in pred.iter().zip(truth) {
            seen[p as usize] = true;
            seen[t as usize] = true;
        }
        for c in 0..=255u8 {
            if !seen[c as usize] {
                continue;
            }
            let (mut i, mut u) = (0u64, 0u64);
            for (&p, &t) in pred.iter().zip(truth) {
                let (a, b) = (p == c, t == c);
                i += (a && b) as u64;
                u += (a || b) as u64;
            }
            let e = self.counts.entry(c).or_default();
            e.0 += i;
            e.1 += u;
        }
    }

    pub fn merge(&mut self, o: &IouCounts) {
        for (c, (i, u)) in &o.counts {
            let e = self.counts.entry(*c).or_default();
            e.0 += i;
            e.1 += u;
        }
    }

    /// IoU of one class; None when the class is in neither image set.
    pub fn iou(&self, class: u8) -> Option<f64> {
        self.counts
            .get(&class)
            .filter(|(_, u)| *u > 0)
            .map(|(i, u)| *i as f64 / *u as f64)
    }

    /// Mean IoU over the classes in `classes` that occur.
    pub fn mean_iou(&self, classes: &[u8]) -> Option<f64> {
        let v: Vec<f64> = classes.iter().filter_map(|&c| self.iou(c)).collect();
        (!v.is_empty()).then(|| v.iter().sum::<f64>() / v.len() as f64)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// SSIM by its definition, one window at a time, in f64 (no separable filtering).
    fn ssim_brute(a: &[u8], b: &[u8], h: usize, w: usize) -> f64 {
        let g = gauss_window();
        let (c1, c2) = ((0.01f64 * 255.0).powi(2), (0.03f64 * 255.0).powi(2));
        let (mut t, mut n) = (0.0, 0);
        for ch in 0..3 {
            for r in 0..=h - WIN {
                for c in 0..=w - WIN {
                    let (mut mx, mut my, mut xx, mut yy, mut xy) = (0.0, 0.0, 0.0, 0.0, 0.0);
                    for i in 0..WIN {
                        for j in 0..WIN {
                            let wt = g[i] * g[j];
                            let p = ((r + i) * w + c + j) * 3 + ch;
                            let (x, y) = (a[p] as f64, b[p] as f64);
                            mx += wt * x;
                            my += wt * y;
                            xx += wt * x * x;
                            yy += wt * y * y;
                            xy += wt * x * y;
                        }
                    }
                    let (vx, vy, cxy) = (xx - mx * mx, yy - my * my, xy - mx * my);
                    t += ((2.0 * mx * my + c1) * (2.0 * cxy + c2))
                        / ((mx * mx + my * my + c1) * (vx + vy + c2));
                    n += 1;
                }
            }
        }
        t / n as f64
    }

    fn noise_image(h: usize, w: usize, seed: u64) -> Vec<u8> {
        (0..3 * h * w)
            .map(|i| {
                (crate::world::palette::mix64(i as u64 ^ seed.wrapping_mul(0x9e37)) >> 56) as u8
            })
            .collect()
    }

    #[test]
    fn ssim_matches_its_definition_and_is_one_on_equal_images() {
        let (h, w) = (17, 23);
        let a = noise_image(h, w, 1);
        let mut b = a.clone();
        for (i, v) in b.iter_mut().enumerate() {
            *v = v.saturating_add((i % 7) as u8 * 9);
        }
        let fast = ssim(&a, &b, h, w).unwrap();
        let slow = ssim_brute(&a, &b, h, w);
        assert!((fast - slow).abs() < 1e-12, "{fast} vs {slow}");
        assert!(fast < 0.99, "different images must not score ~1: {fast}");
        assert!((ssim(&a, &a, h, w).unwrap() - 1.0).abs() < 1e-12);
        assert!(ssim(&a, &b, 5, 5).is_err());
    }

    #[test]
    fn psnr_of_a_known_error() {
        let a = vec![100u8; 300];
        let mut b = a.clone();
        b[0] = 110; // mse = 100 / 300
        let p = psnr(&a, &b).unwrap().unwrap();
        let want = 10.0 * (255.0f64.powi(2) / (100.0 / 300.0)).log10();
        assert!((p - want).abs() < 1e-12);
        assert_eq!(psnr(&a, &a).unwrap(), None);
        assert!(psnr(&a, &b[..3]).is_err());
    }

    #[test]
    fn classifier_and_iou() {
        // two classes: red (class 4) on the left, blue (class 11) on the right
        let (h, w) = (4, 8);
        let mut rgb = vec![0u8; 3 * h * w];
        let mut cls = vec![0u8; h * w];
        for p in 0..h * w {
            let right = p % w >= w / 2;
            rgb[3 * p..3 * p + 3].copy_from_slice(if right {
                &[20, 20, 200]
            } else {
                &[200, 20, 20]
            });
            cls[p] = if right { 11 } else { 4 };
        }
        let k = PaletteClassifier::fit(&[(&rgb, &cls)]).unwrap();
        assert_eq!(k.classify(&rgb), cls);
        // unseen colours go to the nearest filled bin
        assert_eq!(k.classify(&[30, 40, 180, 180, 50, 40]), vec![11, 4]);
        // a prediction shifted by one column
        let mut pred = cls.clone();
        for r in 0..h {
            pred[r * w + w / 2] = 4;
        }
        let mut c = IouCounts::default();
        c.add(&pred, &cls);
        assert_eq!(c.iou(11), Some(3.0 / 4.0));
        assert_eq!(c.iou(4), Some(4.0 / 5.0));
        assert_eq!(c.iou(7), None);
        assert_eq!(c.mean_iou(&[4, 11, 7]), Some((0.75 + 0.8) / 2.0));
    }
}
