//! f64 references for softmax and multi-head attention (plain loops; the oracles of the tests).

/// x: (rows, n) -> (rows, n), softmax over the last dimension (max-subtracted).
pub fn softmax(x: &[f64], rows: usize, n: usize) -> Vec<f64> {
    assert_eq!(
        x.len(),
        rows * n,
        "softmax reference: {} values for ({rows}, {n})",
        x.len()
    );
    let mut y = vec![0.0; rows * n];
    for r in 0..rows {
        let row = &x[r * n..(r + 1) * n];
        let m = row.iter().cloned().fold(f64::NEG_INFINITY, f64::max);
        let s: f64 = row.iter().map(|v| (v - m).exp()).sum();
        for (o, v) in y[r * n..(r + 1) * n].iter_mut().zip(row) {
            *o = (v - m).exp() / s;
        }
    }
    y
}

/// Shape of a multi-head attention call (token-major layout, heads interleaved in the last dim).
#[derive(Clone, Copy, Debug)]
pub struct AttnShape {
    pub batch: usize,
    pub lq: usize,
    pub lk: usize,
    pub heads: usize,
    pub head_dim: usize,
}

/// q: (B, Lq, H*d), k: (B, Lk, H*d), v: (B, Lk, H*d) -> (B, Lq, H*d);
/// out[b, i, h*d + e] = sum_j softmax_j(scale * q[b, i, h*d..] . k[b, j, h*d..]) v[b, j, h*d + e].
pub fn attention(q: &[f64], k: &[f64], v: &[f64], s: AttnShape, scale: f64) -> Vec<f64> {
    let AttnShape {
        batch,
        lq,
        lk,
        heads,
        head_dim: d,
    } = s;
    let w = heads * d;
    assert_eq!(q.len(), batch * lq * w, "attention reference: q length");
    assert_eq!(k.len(), batch * lk * w, "attention reference: k length");
    assert_eq!(v.len(), batch * lk * w, "attention reference: v length");
    let mut out = vec![0.0; batch * lq * w];
    let mut logits = vec![0.0; lk];
    for b in 0..batch {
        for h in 0..heads {
            for i in 0..lq {
                let qi = &q[(b * lq + i) * w + h * d..][..d];
                for (j, l) in logits.iter_mut().enumerate() {
                    let kj = &k[(b * lk + j) * w + h * d..][..d];
                    *l = scale * qi.iter().zip(kj).map(|(x, y)| x * y).sum::<f64>();
                }
                let p = softmax(&logits, 1, lk);
                let o = &mut out[(b * lq + i) * w + h * d..][..d];
                for (j, pj) in p.iter().enumerate() {
                    let vj = &v[(b * lk + j) * w + h * d..][..d];
                    for (oe, ve) in o.iter_mut().zip(vj) {
                        *oe += pj * ve;
                    }
                }
            }
        }
    }
    out
}
