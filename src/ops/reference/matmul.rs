//! Matmul reference (f64, row-major).

/// a: (batch_a, M, K), b: (batch_b, K, N) or with `trans_b` (batch_b, N, K), batch_a/batch_b in {1, B}
/// (+ bias (N)) -> (B, M, N)
#[allow(clippy::too_many_arguments)]
pub fn matmul(
    a: &[f64],
    b: &[f64],
    bias: Option<&[f64]>,
    batch: usize,
    m: usize,
    n: usize,
    k: usize,
    trans_b: bool,
) -> Vec<f64> {
    let a_batched = a.len() == batch * m * k && batch > 1;
    let b_batched = b.len() == batch * n * k && batch > 1;
    let mut out = vec![0.0; batch * m * n];
    for z in 0..batch {
        let ao = if a_batched { z * m * k } else { 0 };
        let bo = if b_batched { z * k * n } else { 0 };
        for i in 0..m {
            for j in 0..n {
                let mut s = bias.map_or(0.0, |bv| bv[j]);
                for l in 0..k {
                    let bv = if trans_b {
                        b[bo + j * k + l]
                    } else {
                        b[bo + l * n + j]
                    };
                    s += a[ao + i * k + l] * bv;
                }
                out[(z * m + i) * n + j] = s;
            }
        }
    }
    out
}
