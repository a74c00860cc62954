//! References for normalisation, resampling, blur and the timestep embedding (f64, plain loops).

/// x: (N, C, H, W) -> (N, C, H, W); PyTorch GroupNorm (biased variance), optional SiLU.
#[allow(clippy::too_many_arguments)]
pub fn group_norm(
    x: &[f64],
    n: usize,
    c: usize,
    hw: usize,
    g: usize,
    gamma: &[f64],
    beta: &[f64],
    eps: f64,
    silu: bool,
) -> Vec<f64> {
    let cpg = c / g;
    let len = cpg * hw;
    let mut y = vec![0.0; x.len()];
    for seg in 0..n * g {
        let s = &x[seg * len..(seg + 1) * len];
        let mean = s.iter().sum::<f64>() / len as f64;
        let var = s.iter().map(|v| (v - mean).powi(2)).sum::<f64>() / len as f64;
        let rstd = 1.0 / (var + eps).sqrt();
        for i in 0..len {
            let ch = (seg % g) * cpg + i / hw;
            let v = (s[i] - mean) * rstd * gamma[ch] + beta[ch];
            y[seg * len + i] = if silu { super::silu(v) } else { v };
        }
    }
    y
}

/// x: (rows, d) -> (rows, d); PyTorch LayerNorm.
pub fn layer_norm(x: &[f64], d: usize, gamma: &[f64], beta: &[f64], eps: f64) -> Vec<f64> {
    let mut y = vec![0.0; x.len()];
    for (r, row) in x.chunks(d).enumerate() {
        let mean = row.iter().sum::<f64>() / d as f64;
        let var = row.iter().map(|v| (v - mean).powi(2)).sum::<f64>() / d as f64;
        for i in 0..d {
            y[r * d + i] = (row[i] - mean) / (var + eps).sqrt() * gamma[i] + beta[i];
        }
    }
    y
}

/// x: (planes, h, w) -> (planes, oh, ow), PyTorch nearest (scale computed in f32 like PyTorch).
pub fn upsample_nearest(
    x: &[f64],
    planes: usize,
    h: usize,
    w: usize,
    oh: usize,
    ow: usize,
) -> Vec<f64> {
    let (sh, sw) = (h as f32 / oh as f32, w as f32 / ow as f32);
    let mut y = vec![0.0; planes * oh * ow];
    for p in 0..planes {
        for oy in 0..oh {
            let sy = ((oy as f32 * sh).floor() as usize).min(h - 1);
            for ox in 0..ow {
                let sx = ((ox as f32 * sw).floor() as usize).min(w - 1);
                y[(p * oh + oy) * ow + ox] = x[(p * h + sy) * w + sx];
            }
        }
    }
    y
}

fn cubic(t: f64) -> [f64; 4] {
    let a = -0.75;
    let k = |x: f64| {
        let x = x.abs();
        if x <= 1.0 {
            ((a + 2.0) * x - (a + 3.0)) * x * x + 1.0
        } else if x < 2.0 {
            ((a * x - 5.0 * a) * x + 8.0 * a) * x - 4.0 * a
        } else {
            0.0
        }
    };
    [k(t + 1.0), k(t), k(1.0 - t), k(2.0 - t)]
}

/// x: (planes, h, w) -> (planes, oh, ow), PyTorch bicubic, align_corners=False, A=-0.75, clamped taps.
pub fn resize_bicubic(
    x: &[f64],
    planes: usize,
    h: usize,
    w: usize,
    oh: usize,
    ow: usize,
) -> Vec<f64> {
    let (sh, sw) = (h as f64 / oh as f64, w as f64 / ow as f64);
    let mut y = vec![0.0; planes * oh * ow];
    for p in 0..planes {
        for oy in 0..oh {
            let fy = (oy as f64 + 0.5) * sh - 0.5;
            let y0 = fy.floor();
            let wy = cubic(fy - y0);
            for ox in 0..ow {
                let fx = (ox as f64 + 0.5) * sw - 0.5;
                let x0 = fx.floor();
                let wx = cubic(fx - x0);
                let mut acc = 0.0;
                for (j, wyj) in wy.iter().enumerate() {
                    let yy = (y0 as i64 - 1 + j as i64).clamp(0, h as i64 - 1) as usize;
                    for (i, wxi) in wx.iter().enumerate() {
                        let xx = (x0 as i64 - 1 + i as i64).clamp(0, w as i64 - 1) as usize;
                        acc += wyj * wxi * x[(p * h + yy) * w + xx];
                    }
                }
                y[(p * oh + oy) * ow + ox] = acc;
            }
        }
    }
    y
}

/// x: (planes, h, w) -> (planes, h, w); Gaussian blur, radius ceil(3 sigma), reflect borders (torchvision).
pub fn gaussian_blur(x: &[f64], planes: usize, h: usize, w: usize, sigma: f64) -> Vec<f64> {
    let r = (3.0 * sigma).ceil() as i64;
    let wts: Vec<f64> = (-r..=r)
        .map(|k| (-(k * k) as f64 / (2.0 * sigma * sigma)).exp())
        .collect();
    let sum: f64 = wts.iter().sum();
    let refl = |i: i64, n: i64| {
        let i = if i < 0 { -i } else { i };
        if i >= n {
            2 * n - 2 - i
        } else {
            i
        }
    };
    let pass = |src: &[f64], horizontal: bool| {
        let mut dst = vec![0.0; src.len()];
        for p in 0..planes {
            for yy in 0..h as i64 {
                for xx in 0..w as i64 {
                    let mut acc = 0.0;
                    for (t, k) in (-r..=r).enumerate() {
                        let (sy, sx) = if horizontal {
                            (yy, refl(xx + k, w as i64))
                        } else {
                            (refl(yy + k, h as i64), xx)
                        };
                        acc += wts[t] * src[(p * h + sy as usize) * w + sx as usize];
                    }
                    dst[(p * h + yy as usize) * w + xx as usize] = acc / sum;
                }
            }
        }
        dst
    };
    pass(&pass(x, true), false)
}

/// t: (B) -> (B, dim); diffusers get_timestep_embedding.
pub fn timestep_embedding(
    t: &[f64],
    dim: usize,
    flip: bool,
    shift: f64,
    max_period: f64,
    scale: f64,
) -> Vec<f64> {
    let half = dim / 2;
    let mut out = vec![0.0; t.len() * dim];
    for (n, tv) in t.iter().enumerate() {
        for j in 0..half {
            let freq = (-(max_period.ln()) * j as f64 / (half as f64 - shift)).exp();
            let a = scale * tv * freq;
            let (first, second) = if flip {
                (a.cos(), a.sin())
            } else {
                (a.sin(), a.cos())
            };
            out[n * dim + j] = first;
            out[n * dim + half + j] = second;
        }
    }
    out
}

/// x: (n, c, h, w), grid: (n, h, w, 2) source (x, y) in pixel-index units -> (n, c, h, w): PyTorch grid_sample
/// (bilinear, padding "border", align_corners false) of x at the normalised grid, i.e. the source clipped to
/// [0, W - 1] x [0, H - 1] and interpolated; a grid point outside [-0.5, W - 0.5] x [-0.5, H - 0.5] keeps x's pixel.
pub fn warp_bilinear(x: &[f64], grid: &[f64], n: usize, c: usize, h: usize, w: usize) -> Vec<f64> {
    let mut y = vec![0.0; x.len()];
    for b in 0..n {
        for yy in 0..h {
            for xx in 0..w {
                let g = 2 * ((b * h + yy) * w + xx);
                let (gx, gy) = (grid[g], grid[g + 1]);
                let inside =
                    gx >= -0.5 && gx <= w as f64 - 0.5 && gy >= -0.5 && gy <= h as f64 - 0.5;
                for ch in 0..c {
                    let plane = &x[(b * c + ch) * h * w..(b * c + ch + 1) * h * w];
                    let o = (b * c + ch) * h * w + yy * w + xx;
                    if !inside {
                        y[o] = plane[yy * w + xx];
                        continue;
                    }
                    // PyTorch's border padding: clip the coordinate, then interpolate
                    let sx = gx.clamp(0.0, (w - 1) as f64);
                    let sy = gy.clamp(0.0, (h - 1) as f64);
                    let (x0, y0) = (sx.floor() as usize, sy.floor() as usize);
                    let (x1, y1) = ((x0 + 1).min(w - 1), (y0 + 1).min(h - 1));
                    let (ax, ay) = (sx - x0 as f64, sy - y0 as f64);
                    let at = |yy: usize, xx: usize| plane[yy * w + xx];
                    y[o] = (1.0 - ay) * ((1.0 - ax) * at(y0, x0) + ax * at(y0, x1))
                        + ay * ((1.0 - ax) * at(y1, x0) + ax * at(y1, x1));
                }
            }
        }
    }
    y
}
