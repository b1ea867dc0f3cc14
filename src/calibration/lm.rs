//! A small dense Levenberg-Marquardt least-squares solver with a central-difference Jacobian.

use nalgebra::{DMatrix, DVector};

/// Outcome of [`minimise`].
#[derive(Debug, Clone)]
pub(crate) struct LmResult {
    /// The parameters at the lowest cost found.
    pub params: DVector<f64>,
    /// Sum of squared residuals there.
    pub cost: f64,
}

/// Minimise `Σ r_i(p)²` from `p0`. `residuals` writes the residual vector (fixed length) for a
/// parameter vector; `steps[k]` is the finite-difference step of parameter `k` (same units as it).
/// Parameters with a zero step are held fixed.
pub(crate) fn minimise<F>(p0: DVector<f64>, steps: &[f64], max_iter: usize, mut residuals: F) -> LmResult
where
    F: FnMut(&DVector<f64>, &mut DVector<f64>),
{
    let n = p0.len();
    let mut r = DVector::zeros(0);
    residuals(&p0, &mut r);
    let m = r.len();
    let mut p = p0;
    let mut cost = r.norm_squared();
    if m == 0 || !cost.is_finite() {
        return LmResult { params: p, cost };
    }
    let mut lambda = -1.0f64;
    let mut jac = DMatrix::zeros(m, n);
    let (mut rp, mut rm) = (DVector::zeros(m), DVector::zeros(m));
    for _ in 0..max_iter {
        // Jacobian by central differences.
        for k in 0..n {
            let h = steps[k];
            if h == 0.0 {
                jac.column_mut(k).fill(0.0);
                continue;
            }
            let mut q = p.clone();
            q[k] += h;
            residuals(&q, &mut rp);
            q[k] -= 2.0 * h;
            residuals(&q, &mut rm);
            jac.set_column(k, &((&rp - &rm) / (2.0 * h)));
        }
        let jtj = jac.transpose() * &jac;
        let g = jac.transpose() * &r;
        if lambda < 0.0 {
            lambda = 1e-3 * (0..n).map(|k| jtj[(k, k)]).fold(0.0, f64::max).max(1e-12);
        }
        let mut improved = false;
        for _ in 0..20 {
            let mut a = jtj.clone();
            for k in 0..n {
                // Marquardt scaling; a fixed parameter gets an identity row so the system stays regular.
                a[(k, k)] += if steps[k] == 0.0 { 1.0 } else { lambda * jtj[(k, k)].max(1e-12) };
            }
            let Some(ch) = a.cholesky() else {
                lambda *= 10.0;
                continue;
            };
            let delta = ch.solve(&(-&g));
            let q = &p + &delta;
            let mut rq = DVector::zeros(m);
            residuals(&q, &mut rq);
            let c = rq.norm_squared();
            if c.is_finite() && c < cost {
                let rel = (cost - c) / cost.max(1e-300);
                p = q;
                r = rq;
                cost = c;
                lambda = (lambda / 3.0).max(1e-15);
                improved = true;
                if rel < 1e-12 {
                    return LmResult { params: p, cost };
                }
                break;
            }
            lambda *= 4.0;
        }
        if !improved {
            break;
        }
    }
    LmResult { params: p, cost }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn fits_an_exponential() {
        // y = a exp(b x) with a = 2, b = -0.7.
        let xs: Vec<f64> = (0..20).map(|i| i as f64 * 0.2).collect();
        let ys: Vec<f64> = xs.iter().map(|x| 2.0 * (-0.7 * x).exp()).collect();
        let res = minimise(DVector::from_vec(vec![1.0, 0.0]), &[1e-6, 1e-6], 100, |p, r| {
            *r = DVector::from_iterator(xs.len(), xs.iter().zip(&ys).map(|(x, y)| p[0] * (p[1] * x).exp() - y));
        });
        assert!((res.params[0] - 2.0).abs() < 1e-6 && (res.params[1] + 0.7).abs() < 1e-6, "{}", res.params);
    }

    #[test]
    fn holds_fixed_parameters() {
        let res = minimise(DVector::from_vec(vec![3.0, 5.0]), &[1e-6, 0.0], 50, |p, r| {
            *r = DVector::from_vec(vec![p[0] - 1.0, p[1] - 1.0]);
        });
        assert!((res.params[0] - 1.0).abs() < 1e-9 && res.params[1] == 5.0);
    }
}
