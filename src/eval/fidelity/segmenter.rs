//! The layout segmenter: a small CNN that classifies each pixel of an image into the world's semantic classes
//! from its neighbourhood (about 70 px; python/b2dr_ref/layout_seg.py trains it and is its reference). It scores
//! "is a vehicle / a lane marking drawn here" where the colour-bin classifier ([`super::metrics`]) scores colour
//! exactness: the ground truth plus 4 levels of noise keeps the segmenter's vehicle IoU but takes the colour
//! classifier's from 0.97 to 0.28 (docs/training.md, "The layout score").
//!
//! Runs on the CPU in f32 (about 0.8 GFLOP for a 112 x 200 image): the evaluation stays independent of the
//! engine it evaluates. Net (every conv 3x3, zero padding, + ReLU unless said otherwise): x (3, H, W) =
//! rgb / 127.5 - 1 -> stem 3->C = f (C, H, W) -> down, stride 2, C->M (M, ceil(H/2), ceil(W/2)) -> M->M with
//! dilation d_i for d_i in the file's `dilations` -> nearest upsampling x2 cropped to (M, H, W) -> concat [f, up]
//! -> fuse C+M->C -> head conv1x1 C->17 (no ReLU): logits (17, H, W); class = argmax (ties: the lower id).
use anyhow::{bail, ensure, Context as _, Result};
use safetensors::SafeTensors;

/// The committed segmenter (models/layout-seg/seg.safetensors), compiled in.
const BUILTIN: &[u8] = include_bytes!("../../../models/layout-seg/seg.safetensors");

/// Semantic classes the segmenter outputs (SemanticClass ids 0..17).
pub const CLASSES: usize = 17;

struct Conv {
    cin: usize,
    cout: usize,
    k: usize,
    dil: usize,
    /// (cout, cin, k, k)
    w: Vec<f32>,
    /// (cout,)
    b: Vec<f32>,
}

impl Conv {
    /// Stride 2 (dilation 1, padding k / 2): x (cin, H, W) -> (cout, ceil(H/2), ceil(W/2)).
    fn forward_s2(&self, x: &[f32], h: usize, w: usize) -> (Vec<f32>, usize, usize) {
        let (ho, wo) = (h.div_ceil(2), w.div_ceil(2));
        let r = (self.k / 2) as isize;
        let mut y = vec![0f32; self.cout * ho * wo];
        for o in 0..self.cout {
            for oy in 0..ho {
                for ox in 0..wo {
                    let mut acc = self.b[o];
                    for i in 0..self.cin {
                        for ky in 0..self.k {
                            let sy = (2 * oy) as isize + ky as isize - r;
                            if sy < 0 || sy >= h as isize {
                                continue;
                            }
                            for kx in 0..self.k {
                                let sx = (2 * ox) as isize + kx as isize - r;
                                if sx < 0 || sx >= w as isize {
                                    continue;
                                }
                                acc += self.w[((o * self.cin + i) * self.k + ky) * self.k + kx]
                                    * x[(i * h + sy as usize) * w + sx as usize];
                            }
                        }
                    }
                    y[(o * ho + oy) * wo + ox] = acc.max(0.0);
                }
            }
        }
        (y, ho, wo)
    }

    /// x (cin, H, W) -> (cout, H, W); "same" output size with zero padding dil * (k / 2).
    fn forward(&self, x: &[f32], h: usize, w: usize, relu: bool) -> Vec<f32> {
        let hw = h * w;
        let r = (self.k / 2) as isize;
        let mut y = vec![0f32; self.cout * hw];
        for (o, yo) in y.chunks_exact_mut(hw).enumerate() {
            yo.fill(self.b[o]);
            for i in 0..self.cin {
                let xi = &x[i * hw..(i + 1) * hw];
                for ky in 0..self.k {
                    let dy = (ky as isize - r) * self.dil as isize;
                    for kx in 0..self.k {
                        let dx = (kx as isize - r) * self.dil as isize;
                        let wv = self.w[((o * self.cin + i) * self.k + ky) * self.k + kx];
                        // output columns whose input column c + dx is inside the image
                        let c0 = (-dx).max(0) as usize;
                        let c1 = (w as isize - dx.max(0)).max(0) as usize;
                        if c0 >= c1 {
                            continue;
                        }
                        for row in 0..h {
                            let sr = row as isize + dy;
                            if sr < 0 || sr >= h as isize {
                                continue;
                            }
                            let src = &xi[sr as usize * w..][..w];
                            let dst = &mut yo[row * w..][..w];
                            let off = (c0 as isize + dx) as usize;
                            for (d, s) in dst[c0..c1].iter_mut().zip(&src[off..off + (c1 - c0)]) {
                                *d += wv * s;
                            }
                        }
                    }
                }
            }
            if relu {
                yo.iter_mut().for_each(|v| *v = v.max(0.0));
            }
        }
        y
    }
}

pub struct LayoutSegmenter {
    stem: Conv,
    down: Conv,
    convs: Vec<Conv>,
    fuse: Conv,
    head: Conv,
}

fn tensor(st: &SafeTensors, name: &str, shape: &[usize]) -> Result<Vec<f32>> {
    let t = st
        .tensor(name)
        .with_context(|| format!("layout segmenter: no tensor {name}"))?;
    ensure!(
        t.dtype() == safetensors::Dtype::F32 && t.shape() == shape,
        "layout segmenter: {name} is {:?} {:?}, expected F32 {shape:?}",
        t.dtype(),
        t.shape()
    );
    Ok(t.data()
        .chunks_exact(4)
        .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
        .collect())
}

impl LayoutSegmenter {
    /// The committed segmenter.
    pub fn builtin() -> Result<Self> {
        Self::from_safetensors(BUILTIN).context("the built-in layout segmenter")
    }

    /// A segmenter file written by `python -m b2dr_ref.layout_seg train` (tensors `{stem, down, convs.{i},
    /// fuse, head}.{weight, bias}`; metadata `arch` = layout-seg-v2, `dilations`).
    pub fn from_safetensors(bytes: &[u8]) -> Result<Self> {
        let (_, meta) =
            SafeTensors::read_metadata(bytes).context("layout segmenter: not safetensors")?;
        let arch = meta.metadata().as_ref().and_then(|m| m.get("arch"));
        ensure!(
            arch.map(String::as_str) == Some("layout-seg-v2"),
            "layout segmenter: metadata `arch` is {arch:?}, expected \"layout-seg-v2\""
        );
        let st = SafeTensors::deserialize(bytes).context("layout segmenter: not safetensors")?;
        let dil: Vec<usize> = meta
            .metadata()
            .as_ref()
            .and_then(|m| m.get("dilations"))
            .context("layout segmenter: no `dilations` metadata")?
            .split(',')
            .map(|s| s.trim().parse::<usize>())
            .collect::<std::result::Result<_, _>>()
            .context("layout segmenter: `dilations` is not a list of integers")?;
        ensure!(
            !dil.is_empty() && dil.iter().all(|&d| (1..=64).contains(&d)),
            "layout segmenter: dilations {dil:?} (each in 1..=64)"
        );
        let conv = |name: &str, cin: usize, k: usize, dil: usize| -> Result<Conv> {
            let wname = format!("{name}.weight");
            let cout = match st.tensor(&wname) {
                Ok(t) if t.shape().len() == 4 => t.shape()[0],
                Ok(t) => bail!("layout segmenter: {wname} has shape {:?}", t.shape()),
                Err(_) => bail!("layout segmenter: no tensor {wname}"),
            };
            ensure!(
                (1..=1024).contains(&cout),
                "layout segmenter: {wname}: {cout} channels"
            );
            Ok(Conv {
                cin,
                cout,
                k,
                dil,
                w: tensor(&st, &wname, &[cout, cin, k, k])?,
                b: tensor(&st, &format!("{name}.bias"), &[cout])?,
            })
        };
        let stem = conv("stem", 3, 3, 1)?;
        let down = conv("down", stem.cout, 3, 1)?;
        let mut convs = vec![];
        for (i, &d) in dil.iter().enumerate() {
            convs.push(conv(&format!("convs.{i}"), down.cout, 3, d)?);
        }
        let fuse = conv("fuse", stem.cout + down.cout, 3, 1)?;
        let head = conv("head", fuse.cout, 1, 1)?;
        ensure!(
            head.cout == CLASSES && fuse.cout == stem.cout,
            "layout segmenter: head has {} classes (expected {CLASSES}), fuse {} channels (expected {})",
            head.cout,
            fuse.cout,
            stem.cout
        );
        Ok(Self {
            stem,
            down,
            convs,
            fuse,
            head,
        })
    }

    /// Logits (17, H, W) of an RGB8 image (H, W, 3).
    pub fn logits(&self, rgb: &[u8], h: usize, w: usize) -> Result<Vec<f32>> {
        ensure!(
            h >= 1 && w >= 1 && rgb.len() == 3 * h * w,
            "layout segmenter: {} bytes for a {h} x {w} RGB image",
            rgb.len()
        );
        let hw = h * w;
        let mut x = vec![0f32; 3 * hw];
        for (p, px) in rgb.chunks_exact(3).enumerate() {
            for c in 0..3 {
                x[c * hw + p] = px[c] as f32 / 127.5 - 1.0;
            }
        }
        let f = self.stem.forward(&x, h, w, true);
        let (mut y, hh, wh) = self.down.forward_s2(&f, h, w);
        for c in &self.convs {
            y = c.forward(&y, hh, wh, true);
        }
        // concat [f (C, H, W), nearest x2 of y cropped to (M, H, W)]
        let mut cat = f;
        cat.reserve(self.down.cout * hw);
        for ch in y.chunks_exact(hh * wh) {
            for row in 0..h {
                let src = &ch[(row / 2) * wh..][..wh];
                cat.extend((0..w).map(|col| src[col / 2]));
            }
        }
        let g = self.fuse.forward(&cat, h, w, true);
        Ok(self.head.forward(&g, h, w, false))
    }

    /// The class image (H, W) of an RGB8 image (H, W, 3).
    pub fn classify(&self, rgb: &[u8], h: usize, w: usize) -> Result<Vec<u8>> {
        let l = self.logits(rgb, h, w)?;
        let hw = h * w;
        Ok((0..hw)
            .map(|p| {
                let mut best = 0;
                for c in 1..CLASSES {
                    if l[c * hw + p] > l[best * hw + p] {
                        best = c;
                    }
                }
                best as u8
            })
            .collect())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A dilated, strided convolution by its definition (output size ceil(H / stride)), in f64.
    fn conv_ref(c: &Conv, x: &[f32], h: usize, w: usize, stride: usize) -> Vec<f64> {
        let r = (c.k / 2) as isize * c.dil as isize;
        let (ho, wo) = (h.div_ceil(stride), w.div_ceil(stride));
        let mut y = vec![0f64; c.cout * ho * wo];
        for o in 0..c.cout {
            for orow in 0..ho as isize {
                for ocol in 0..wo as isize {
                    let (row, col) = (orow * stride as isize, ocol * stride as isize);
                    let mut s = c.b[o] as f64;
                    for i in 0..c.cin {
                        for ky in 0..c.k as isize {
                            for kx in 0..c.k as isize {
                                let (sr, sc) =
                                    (row + ky * c.dil as isize - r, col + kx * c.dil as isize - r);
                                if sr < 0 || sc < 0 || sr >= h as isize || sc >= w as isize {
                                    continue;
                                }
                                let wv =
                                    c.w[((o * c.cin + i) * c.k + ky as usize) * c.k + kx as usize];
                                s += wv as f64 * x[(i * h + sr as usize) * w + sc as usize] as f64;
                            }
                        }
                    }
                    y[(o * ho + orow as usize) * wo + ocol as usize] = s;
                }
            }
        }
        y
    }

    #[test]
    fn dilated_conv_matches_its_definition_at_the_borders() {
        let mut seed = 7u64;
        let mut rnd = || {
            seed = crate::world::palette::mix64(seed);
            (seed >> 40) as f32 / (1u64 << 24) as f32 - 0.5
        };
        for (dil, h, w) in [(1, 5, 7), (1, 6, 8), (2, 6, 5), (4, 3, 9), (8, 11, 4)] {
            let c = Conv {
                cin: 2,
                cout: 3,
                k: 3,
                dil,
                w: (0..54).map(|_| rnd()).collect(),
                b: (0..3).map(|_| rnd()).collect(),
            };
            let x: Vec<f32> = (0..2 * h * w).map(|_| rnd()).collect();
            let got = c.forward(&x, h, w, false);
            let want = conv_ref(&c, &x, h, w, 1);
            for (g, e) in got.iter().zip(&want) {
                assert!(
                    (*g as f64 - e).abs() < 1e-5,
                    "dil {dil} {h}x{w}: {g} vs {e}"
                );
            }
            if dil == 1 {
                // the down conv: stride 2, odd and even sizes, ReLU applied
                let (got, ho, wo) = c.forward_s2(&x, h, w);
                assert_eq!((ho, wo), (h.div_ceil(2), w.div_ceil(2)));
                let want = conv_ref(&c, &x, h, w, 2);
                for (g, e) in got.iter().zip(&want) {
                    assert!(
                        (*g as f64 - e.max(0.0)).abs() < 1e-5,
                        "s2 {h}x{w}: {g} vs {e}"
                    );
                }
            }
        }
    }

    /// The committed weights against their PyTorch reference (tools/make_golden_layout_seg.py).
    #[test]
    fn the_builtin_segmenter_matches_pytorch() {
        let bytes = std::fs::read(
            std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
                .join("tests/golden/layout_seg_case.safetensors"),
        )
        .unwrap();
        let st = SafeTensors::deserialize(&bytes).unwrap();
        let rgb = st.tensor("rgb").unwrap();
        let (h, w) = (rgb.shape()[0], rgb.shape()[1]);
        let want = tensor(&st, "logits", &[CLASSES, h, w]).unwrap();
        let want_cls = st.tensor("classes").unwrap().data().to_vec();
        let s = LayoutSegmenter::builtin().unwrap();
        let got = s.logits(rgb.data(), h, w).unwrap();
        let scale = want.iter().fold(0f32, |m, v| m.max(v.abs()));
        let err = got
            .iter()
            .zip(&want)
            .fold(0f32, |m, (g, e)| m.max((g - e).abs()));
        assert!(
            err <= 1e-5 * scale.max(1.0) * 10.0,
            "max |logit error| {err} (max |logit| {scale})"
        );
        let cls = s.classify(rgb.data(), h, w).unwrap();
        let differ = cls.iter().zip(&want_cls).filter(|(a, b)| a != b).count();
        assert_eq!(
            differ,
            0,
            "{differ} of {} pixels classed differently",
            h * w
        );
        let kinds: std::collections::BTreeSet<u8> = cls.iter().copied().collect();
        assert!(
            kinds.len() >= 3,
            "the golden crop must hold several classes: {kinds:?}"
        );
    }

    #[test]
    fn the_builtin_segmenter_loads_and_refuses_bad_input() {
        let s = LayoutSegmenter::builtin().unwrap();
        assert_eq!(s.classify(&[0u8; 3 * 4 * 5], 4, 5).unwrap().len(), 20);
        assert!(s.classify(&[0u8; 10], 4, 5).is_err());
        assert!(LayoutSegmenter::from_safetensors(b"not a file").is_err());
    }
}
