//! 2-D convolution reference (f64, NCHW, cross-correlation like PyTorch).

/// Geometry of a conv2d: kernel, stride, padding (top, bottom, left, right).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct ConvGeom {
    pub kh: usize,
    pub kw: usize,
    pub stride: usize,
    pub pad: [usize; 4],
}

impl ConvGeom {
    /// Output (OH, OW) for an input (H, W).
    pub fn out_hw(&self, h: usize, w: usize) -> (usize, usize) {
        let oh = (h + self.pad[0] + self.pad[1] - self.kh) / self.stride + 1;
        let ow = (w + self.pad[2] + self.pad[3] - self.kw) / self.stride + 1;
        (oh, ow)
    }
}

/// x: (N, C, H, W), w: (O, C, kh, kw) (+ bias (O)) -> (N, O, OH, OW)
pub fn conv2d(
    x: &[f64],
    w: &[f64],
    bias: Option<&[f64]>,
    (n, c, h, wd): (usize, usize, usize, usize),
    o: usize,
    g: ConvGeom,
) -> Vec<f64> {
    let (oh, ow) = g.out_hw(h, wd);
    let mut out = vec![0.0; n * o * oh * ow];
    for b in 0..n {
        for oc in 0..o {
            for y in 0..oh {
                for xo in 0..ow {
                    let mut s = bias.map_or(0.0, |bv| bv[oc]);
                    for ic in 0..c {
                        for ky in 0..g.kh {
                            let iy = (y * g.stride + ky) as isize - g.pad[0] as isize;
                            if iy < 0 || iy >= h as isize {
                                continue;
                            }
                            for kx in 0..g.kw {
                                let ix = (xo * g.stride + kx) as isize - g.pad[2] as isize;
                                if ix < 0 || ix >= wd as isize {
                                    continue;
                                }
                                s += w[((oc * c + ic) * g.kh + ky) * g.kw + kx]
                                    * x[((b * c + ic) * h + iy as usize) * wd + ix as usize];
                            }
                        }
                    }
                    out[((b * o + oc) * oh + y) * ow + xo] = s;
                }
            }
        }
    }
    out
}
