//! Savitzky-Golay filter, a port of scipy's `savgol_coeffs` and `savgol_filter(..., mode="interp")`
//! [scipy/signal/_savitzky_golay.py], as nuPlan's comfort metrics use it
//! [planning/metrics/utils/state_extractors.py].
//!
//! - Coefficients: least-squares fit of a degree-`polyorder` polynomial to `window_length` equally spaced
//!   points; scipy solves the (underdetermined) system `x^order c = y` with `lstsq`, i.e. the minimum-norm
//!   solution. We solve the same system through a Householder QR of its transpose.
//! - Even windows: scipy puts the evaluation point between the two middle samples (`pos = halflen - 0.5`) and
//!   `ndimage.convolve1d` shifts even kernels by one sample; the net effect (kept here, quirk) is that the
//!   output at `i` uses samples `i - halflen + 1 ..= i + halflen` and evaluates the fit half a sample later.
//! - `mode="interp"`: the first and last `window_length // 2` outputs come from `numpy.polyfit` of degree
//!   `polyorder` on the first / last `window_length` samples, differentiated `deriv` times, evaluated at the
//!   sample indices and divided by `delta^deriv`.
use anyhow::{bail, ensure, Result};

/// Householder QR of a tall matrix `m` (rows x cols, row-major, rows >= cols). Returns the thin Q
/// (rows x cols, row-major) and R (cols x cols, upper triangular, row-major).
fn householder_qr(m: &[f64], rows: usize, cols: usize) -> (Vec<f64>, Vec<f64>) {
    let mut a = m.to_vec();
    let mut vs: Vec<Vec<f64>> = Vec::with_capacity(cols);
    for k in 0..cols {
        let norm = (k..rows)
            .map(|i| a[i * cols + k] * a[i * cols + k])
            .sum::<f64>()
            .sqrt();
        let mut v = vec![0.0; rows];
        if norm > 0.0 {
            let alpha = if a[k * cols + k] > 0.0 { -norm } else { norm };
            for i in k..rows {
                v[i] = a[i * cols + k];
            }
            v[k] -= alpha;
            let vnorm2: f64 = v[k..].iter().map(|x| x * x).sum();
            if vnorm2 > 0.0 {
                for j in k..cols {
                    let s: f64 =
                        (k..rows).map(|i| v[i] * a[i * cols + j]).sum::<f64>() * 2.0 / vnorm2;
                    for i in k..rows {
                        a[i * cols + j] -= s * v[i];
                    }
                }
            }
        }
        vs.push(v);
    }
    let mut r = vec![0.0; cols * cols];
    for i in 0..cols {
        for j in i..cols {
            r[i * cols + j] = a[i * cols + j];
        }
    }
    // Q = H_0 H_1 ... H_{cols-1} applied to the first `cols` columns of the identity.
    let mut q = vec![0.0; rows * cols];
    for j in 0..cols {
        q[j * cols + j] = 1.0;
    }
    for k in (0..cols).rev() {
        let v = &vs[k];
        let vnorm2: f64 = v[k..].iter().map(|x| x * x).sum();
        if vnorm2 == 0.0 {
            continue;
        }
        for j in 0..cols {
            let s: f64 = (k..rows).map(|i| v[i] * q[i * cols + j]).sum::<f64>() * 2.0 / vnorm2;
            for i in k..rows {
                q[i * cols + j] -= s * v[i];
            }
        }
    }
    (q, r)
}

/// Least squares `min ||M c - y||` for a tall full-rank `m` (rows x cols).
fn least_squares(m: &[f64], rows: usize, cols: usize, y: &[f64]) -> Vec<f64> {
    let (q, r) = householder_qr(m, rows, cols);
    let mut qty = vec![0.0; cols];
    for (j, v) in qty.iter_mut().enumerate() {
        *v = (0..rows).map(|i| q[i * cols + j] * y[i]).sum();
    }
    let mut c = vec![0.0; cols];
    for i in (0..cols).rev() {
        let s: f64 = (i + 1..cols).map(|j| r[i * cols + j] * c[j]).sum();
        c[i] = (qty[i] - s) / r[i * cols + i];
    }
    c
}

/// Minimum-norm solution of the wide system `A c = y` where `at` = A^T is tall (rows x cols).
fn min_norm(at: &[f64], rows: usize, cols: usize, y: &[f64]) -> Vec<f64> {
    let (q, r) = householder_qr(at, rows, cols);
    // A = R^T Q^T, so c = Q z with R^T z = y (forward substitution).
    let mut z = vec![0.0; cols];
    for i in 0..cols {
        let s: f64 = (0..i).map(|j| r[j * cols + i] * z[j]).sum();
        z[i] = (y[i] - s) / r[i * cols + i];
    }
    (0..rows)
        .map(|i| (0..cols).map(|j| q[i * cols + j] * z[j]).sum())
        .collect()
}

fn factorial(n: usize) -> f64 {
    (1..=n).map(|k| k as f64).product()
}

fn check_args(window_length: usize, polyorder: usize) -> Result<()> {
    ensure!(window_length >= 1, "savgol: window_length must be >= 1");
    ensure!(
        polyorder < window_length,
        "savgol: polyorder ({polyorder}) must be less than window_length ({window_length})"
    );
    Ok(())
}

/// scipy `savgol_coeffs(window_length, polyorder, deriv, delta, use="conv")`: kernel in convolution order
/// (the weight of the latest sample first). `x: (window_length,)`.
pub fn savgol_coeffs(
    window_length: usize,
    polyorder: usize,
    deriv: usize,
    delta: f64,
) -> Result<Vec<f64>> {
    check_args(window_length, polyorder)?;
    if deriv > polyorder {
        return Ok(vec![0.0; window_length]);
    }
    let halflen = window_length / 2;
    let pos = if window_length % 2 == 0 {
        halflen as f64 - 0.5
    } else {
        halflen as f64
    };
    // x = arange(-pos, window_length - pos)[::-1]
    let x: Vec<f64> = (0..window_length)
        .map(|k| (window_length - 1 - k) as f64 - pos)
        .collect();
    let cols = polyorder + 1;
    // A^T: (window_length, polyorder + 1), A^T[k][i] = x_k^i (0^0 = 1 like numpy).
    let mut at = vec![0.0; window_length * cols];
    for (k, &xk) in x.iter().enumerate() {
        for i in 0..cols {
            at[k * cols + i] = xk.powi(i as i32);
        }
    }
    let mut y = vec![0.0; cols];
    y[deriv] = factorial(deriv) / delta.powi(deriv as i32);
    Ok(min_norm(&at, window_length, cols, &y))
}

/// numpy `polyfit(arange(n), y, deg)`: coefficients, highest power first (numpy scales the Vandermonde
/// columns to unit norm before `lstsq`; we do the same).
pub fn polyfit_index(y: &[f64], deg: usize) -> Vec<f64> {
    let n = y.len();
    let cols = deg + 1;
    let mut v = vec![0.0; n * cols];
    for i in 0..n {
        for j in 0..cols {
            v[i * cols + j] = (i as f64).powi((deg - j) as i32);
        }
    }
    let scale: Vec<f64> = (0..cols)
        .map(|j| (0..n).map(|i| v[i * cols + j].powi(2)).sum::<f64>().sqrt())
        .collect();
    for i in 0..n {
        for j in 0..cols {
            if scale[j] > 0.0 {
                v[i * cols + j] /= scale[j];
            }
        }
    }
    let c = least_squares(&v, n, cols, y);
    c.iter()
        .zip(&scale)
        .map(|(c, s)| if *s > 0.0 { c / s } else { 0.0 })
        .collect()
}

/// scipy `_polyder`: `m`-th derivative of a polynomial given highest power first.
fn polyder(p: &[f64], m: usize) -> Vec<f64> {
    let n = p.len();
    if m == 0 {
        return p.to_vec();
    }
    if n <= m {
        return vec![0.0];
    }
    let mut dp = p[..n - m].to_vec();
    for k in 0..m {
        for (j, v) in dp.iter_mut().enumerate() {
            *v *= (n - k - 1 - j) as f64;
        }
    }
    dp
}

/// numpy `polyval` (Horner).
fn polyval(p: &[f64], x: f64) -> f64 {
    p.iter().fold(0.0, |acc, c| acc * x + c)
}

/// scipy `savgol_filter(x, window_length, polyorder, deriv, delta, mode="interp")`. `x: (n,)` -> `(n,)`.
/// Errors (like scipy) when `polyorder >= window_length` or `window_length > n`.
pub fn savgol_filter(
    x: &[f64],
    window_length: usize,
    polyorder: usize,
    deriv: usize,
    delta: f64,
) -> Result<Vec<f64>> {
    check_args(window_length, polyorder)?;
    let n = x.len();
    if window_length > n {
        bail!("savgol: with mode 'interp', window_length ({window_length}) must be <= the signal length ({n})");
    }
    let c = savgol_coeffs(window_length, polyorder, deriv, delta)?;
    let halflen = window_length / 2;
    // ndimage.convolve1d(x, c, mode="constant"): y[i] = sum_k c[k] x[i + halflen - k] (see module docs).
    let mut y = vec![0.0; n];
    for (i, out) in y.iter_mut().enumerate() {
        let mut acc = 0.0;
        for (k, ck) in c.iter().enumerate() {
            let idx = i as isize + halflen as isize - k as isize;
            if idx >= 0 && (idx as usize) < n {
                acc += ck * x[idx as usize];
            }
        }
        *out = acc;
    }
    // _fit_edges_polyfit
    let scale = delta.powi(deriv as i32);
    let fit_edge = |y: &mut [f64], w0: usize, i0: usize, i1: usize| {
        let p = polyder(&polyfit_index(&x[w0..w0 + window_length], polyorder), deriv);
        for (i, out) in y.iter_mut().enumerate().take(i1).skip(i0) {
            *out = polyval(&p, (i - w0) as f64) / scale;
        }
    };
    fit_edge(&mut y, 0, 0, halflen);
    fit_edge(&mut y, n - window_length, n - halflen, n);
    Ok(y)
}

/// numpy `round(x, decimals)`: `rint(x * 10^d) / 10^d`, ties to even.
pub fn np_round(x: f64, decimals: i32) -> f64 {
    let s = 10f64.powi(decimals);
    (x * s).round_ties_even() / s
}

#[cfg(test)]
mod tests {
    use super::*;

    fn close(a: &[f64], b: &[f64], tol: f64) {
        assert_eq!(a.len(), b.len());
        for (x, y) in a.iter().zip(b) {
            assert!((x - y).abs() <= tol, "{a:?} vs {b:?}");
        }
    }

    #[test]
    fn coeffs_known_values() {
        // scipy: savgol_coeffs(5, 2) = [-3, 12, 17, 12, -3] / 35
        let c = savgol_coeffs(5, 2, 0, 1.0).unwrap();
        close(
            &c,
            &[
                -3.0 / 35.0,
                12.0 / 35.0,
                17.0 / 35.0,
                12.0 / 35.0,
                -3.0 / 35.0,
            ],
            1e-15,
        );
        // savgol_coeffs(5, 2, deriv=1) = [0.2, 0.1, 0, -0.1, -0.2] (conv order)
        let c = savgol_coeffs(5, 2, 1, 1.0).unwrap();
        close(&c, &[0.2, 0.1, 0.0, -0.1, -0.2], 1e-15);
        // window 15, poly 2, deriv 1, delta 0.1: x_k = 7 - k, weights x / sum(x^2) / delta; sum(x^2) = 280.
        let c = savgol_coeffs(15, 2, 1, 0.1).unwrap();
        let want: Vec<f64> = (0..15).map(|k| (7.0 - k as f64) / 280.0 / 0.1).collect();
        close(&c, &want, 1e-13);
        // window 5, poly 3, deriv 2: second derivative weights (2 x^2 - 4)/14 ... = [2,-1,-2,-1,2]/7.
        let c = savgol_coeffs(5, 3, 2, 1.0).unwrap();
        close(
            &c,
            &[2.0 / 7.0, -1.0 / 7.0, -2.0 / 7.0, -1.0 / 7.0, 2.0 / 7.0],
            1e-14,
        );
        // Even window 4, poly 1: x = [1.5, 0.5, -0.5, -1.5] -> mean weights 0.25 each.
        close(&savgol_coeffs(4, 1, 0, 1.0).unwrap(), &[0.25; 4], 1e-15);
        // Even window 4, poly 1, deriv 1: x / sum(x^2) = x / 5.
        close(
            &savgol_coeffs(4, 1, 1, 1.0).unwrap(),
            &[0.3, 0.1, -0.1, -0.3],
            1e-15,
        );
    }

    #[test]
    fn filter_known_scipy_output() {
        // scipy docs: savgol_filter([2, 2, 5, 2, 1, 0, 1, 4, 9], 5, 2) (mode interp)
        let x = [2.0, 2.0, 5.0, 2.0, 1.0, 0.0, 1.0, 4.0, 9.0];
        let y = savgol_filter(&x, 5, 2, 0, 1.0).unwrap();
        let want = [
            1.65714286, 3.17142857, 3.54285714, 2.85714286, 0.65714286, 0.17142857, 1.0, 4.0, 9.0,
        ];
        close(&y, &want, 1e-8);
    }

    #[test]
    fn interp_reproduces_polynomials() {
        // A degree-2 signal is reproduced exactly (value and derivatives), edges included, odd and even windows.
        let dt = 0.1;
        let f = |t: f64| 1.5 - 2.0 * t + 0.75 * t * t;
        let df = |t: f64| -2.0 + 1.5 * t;
        let x: Vec<f64> = (0..20).map(|i| f(i as f64 * dt)).collect();
        let y = savgol_filter(&x, 15, 2, 0, dt).unwrap();
        close(&y, &x, 1e-12);
        let d = savgol_filter(&x, 15, 2, 1, dt).unwrap();
        let want: Vec<f64> = (0..20).map(|i| df(i as f64 * dt)).collect();
        close(&d, &want, 1e-10);
        let d2 = savgol_filter(&x, 5, 3, 2, dt).unwrap();
        close(&d2, &[1.5; 20], 1e-8);
        // Even window 8: a LINEAR signal is reproduced with the half-sample shift in the interior
        // (value at i + 0.5), and exactly at the edges (polyfit evaluated at the indices).
        let lin: Vec<f64> = (0..12).map(|i| 2.0 + 3.0 * i as f64).collect();
        let y = savgol_filter(&lin, 8, 2, 0, 1.0).unwrap();
        for (i, v) in y.iter().enumerate() {
            let want = if (4..8).contains(&i) {
                2.0 + 3.0 * (i as f64 + 0.5)
            } else {
                lin[i]
            };
            assert!((v - want).abs() < 1e-10, "i={i} {v} {want}");
        }
    }

    #[test]
    fn errors_and_rounding() {
        assert!(savgol_filter(&[1.0, 2.0], 5, 2, 0, 1.0).is_err());
        assert!(savgol_coeffs(3, 3, 0, 1.0).is_err());
        assert_eq!(np_round(0.125, 2), 0.12);
        assert_eq!(np_round(0.135, 2), 0.14);
        assert_eq!(np_round(-1.23456789123, 8), -1.23456789);
    }
}
