//! Plain-loop CPU references in f64 for every op (the oracles of the tests). Row-major, shapes in comments.
pub mod attention;
pub mod conv2d;
pub mod matmul;

/// erf via libm-quality series / continued fraction (f64, |err| < 1e-15 for our use).
pub fn erf(x: f64) -> f64 {
    // Abramowitz-Stegun 7.1.28 is too coarse for an oracle; use the Taylor series near 0 and erfc's continued
    // fraction elsewhere.
    let a = x.abs();
    let r = if a < 2.5 {
        let mut term = a;
        let mut sum = a;
        let x2 = a * a;
        for n in 1..200 {
            term *= -x2 / n as f64;
            let t = term / (2 * n + 1) as f64;
            sum += t;
            if t.abs() < 1e-17 {
                break;
            }
        }
        2.0 / std::f64::consts::PI.sqrt() * sum
    } else {
        // erfc(a) = exp(-a^2)/sqrt(pi) * 1/(a + 1/2/(a + 1/(a + 3/2/(a + ...))))
        let mut f = a;
        for k in (1..60).rev() {
            f = a + (k as f64 / 2.0) / f;
        }
        1.0 - (-a * a).exp() / std::f64::consts::PI.sqrt() / f
    };
    r.copysign(x)
}

pub fn silu(x: f64) -> f64 {
    x / (1.0 + (-x).exp())
}

pub fn relu(x: f64) -> f64 {
    x.max(0.0)
}

/// clamp(x / 2 + 0.5, 0, 1)
pub fn to_unit(x: f64) -> f64 {
    (x * 0.5 + 0.5).clamp(0.0, 1.0)
}

pub fn gelu(x: f64) -> f64 {
    0.5 * x * (1.0 + erf(x / std::f64::consts::SQRT_2))
}

/// x: (rows, 2d) -> (rows, d) = value * gelu(gate)
pub fn geglu(x: &[f64], rows: usize, d: usize) -> Vec<f64> {
    let mut o = vec![0.0; rows * d];
    for r in 0..rows {
        for c in 0..d {
            o[r * d + c] = x[r * 2 * d + c] * gelu(x[r * 2 * d + d + c]);
        }
    }
    o
}

/// Numpy-broadcast binary op; shapes right-aligned.
pub fn broadcast(
    a: &[f64],
    sa: &[usize],
    b: &[f64],
    sb: &[usize],
    f: impl Fn(f64, f64) -> f64,
) -> (Vec<f64>, Vec<usize>) {
    let n = sa.len().max(sb.len());
    let pad = |s: &[usize]| {
        let mut v = vec![1; n - s.len()];
        v.extend_from_slice(s);
        v
    };
    let (pa, pb) = (pad(sa), pad(sb));
    let so: Vec<usize> = pa.iter().zip(&pb).map(|(x, y)| *x.max(y)).collect();
    let total: usize = so.iter().product();
    let mut out = vec![0.0; total];
    for (i, o) in out.iter_mut().enumerate() {
        let mut rem = i;
        let (mut ia, mut ib) = (0, 0);
        let (mut ma, mut mb) = (1, 1);
        for k in (0..n).rev() {
            let idx = rem % so[k];
            rem /= so[k];
            if pa[k] != 1 {
                ia += idx * ma;
            }
            if pb[k] != 1 {
                ib += idx * mb;
            }
            ma *= pa[k];
            mb *= pb[k];
        }
        *o = f(a[ia], b[ib]);
    }
    (out, so)
}

/// Normalised MSE: sum (a - b)^2 / sum b^2 (b is the reference). Infinite if `a` has a NaN/Inf.
pub fn nmse(a: &[f32], b: &[f64]) -> f64 {
    assert_eq!(a.len(), b.len(), "nmse: lengths differ");
    let mut num = 0.0;
    let mut den = 0.0;
    for (x, y) in a.iter().zip(b) {
        if !x.is_finite() {
            return f64::INFINITY;
        }
        num += (*x as f64 - y).powi(2);
        den += y * y;
    }
    if den == 0.0 {
        if num == 0.0 {
            0.0
        } else {
            f64::INFINITY
        }
    } else {
        num / den
    }
}
pub mod image;
