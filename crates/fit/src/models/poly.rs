//! A field that is not radial: `q` and `u` each a polynomial in the field position.
//!
//! The radial model of section `sec:fors1` assumes an optical axis: `p` grows with the distance
//! from it and the angle is radial. A tilted or decentred element, a field lens with stress, or
//! the telescope's own term makes a pattern without that symmetry: a constant plus a gradient
//! across the field (a plane), or a smooth curved surface. This model fits it with no axis:
//!
//! ```text
//! q(x, y) = sum_k a_k x^i_k y^j_k,    u(x, y) = sum_k b_k x^i_k y^j_k,    i_k + j_k <= d
//! ```
//!
//! with `x, y` in arcmin about the detector centre (the field coordinates of
//! `docs/architecture.md`, Conventions) and `d` from 1 (a plane: 3 terms each) to 3 (10 terms
//! each). Terms are ordered by total degree, then by falling power of `x`: `1, x, y, x^2, x y,
//! y^2, ...` ([`PolyModel::powers`]). The parameters are `a` then `b`; the fit is linear
//! (weighted least squares on `(q, u)` with the robust reweighting and error scaling of the
//! radial fit, [`crate::models::radial::Robust`], [`crate::models::radial::ErrorScaling`]), so it has one
//! solution and needs no start.

use crate::models::radial::{robust_weights, CovarianceScaling, RadialFitOptions};
use crate::{Bin, Error, Result};
use field::{FieldModel, InstPol};
use nalgebra::{DMatrix, DVector};
use serde::{Deserialize, Serialize};

/// Highest total degree offered: 10 terms per component. Higher degrees chase the noise of a
/// binned map and swing wildly at the field's edge.
pub const MAX_DEGREE: usize = 3;

/// A polynomial field (module docs).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct PolyModel {
    pub degree: usize,
    /// Coefficients of `q`, in the order of [`PolyModel::powers`].
    pub q: Vec<f64>,
    /// Coefficients of `u`.
    pub u: Vec<f64>,
    /// Covariance of `(q coefficients, u coefficients)`, row-major `2m x 2m`.
    pub cov: Vec<f64>,
    /// How the covariance was scaled by the fit's reduced chi^2 (`None` when not known).
    pub scaling: Option<CovarianceScaling>,
}

impl PolyModel {
    /// The `(i, j)` powers of `x^i y^j` of each term of degree `d`, in the model's order.
    pub fn powers(d: usize) -> Vec<(usize, usize)> {
        (0..=d).flat_map(|k| (0..=k).rev().map(move |i| (i, k - i))).collect()
    }

    /// Terms per component, `(d + 1)(d + 2) / 2`.
    pub fn n_terms(d: usize) -> usize {
        (d + 1) * (d + 2) / 2
    }

    /// The terms' values at `(x, y)`.
    fn basis(&self, x: f64, y: f64) -> Vec<f64> {
        basis(self.degree, x, y)
    }

    /// `(q, u)` at `(x, y)` arcmin.
    pub fn qu(&self, x: f64, y: f64) -> (f64, f64) {
        let t = self.basis(x, y);
        let dot = |c: &[f64]| c.iter().zip(&t).map(|(a, b)| a * b).sum::<f64>();
        (dot(&self.q), dot(&self.u))
    }

    /// 1-sigma errors of the `q` then the `u` coefficients.
    pub fn coefficient_errors(&self) -> Vec<f64> {
        let n = 2 * self.q.len();
        (0..n).map(|i| self.cov[i * n + i].max(0.0).sqrt()).collect()
    }
}

/// The terms of degree `d` at `(x, y)` (the order of [`PolyModel::powers`]).
fn basis(d: usize, x: f64, y: f64) -> Vec<f64> {
    PolyModel::powers(d).iter().map(|&(i, j)| x.powi(i as i32) * y.powi(j as i32)).collect()
}

impl FieldModel for PolyModel {
    /// `(q, u)` with the variance the coefficients' covariance gives there (`J C J^T`).
    fn eval(&self, x: f64, y: f64) -> InstPol {
        let (q, u) = self.qu(x, y);
        let (jq, ju) = self.jacobian(x, y).unwrap_or_default();
        let n = jq.len();
        let quad = |a: &[f64], b: &[f64]| {
            let mut s = 0.0;
            for i in 0..n {
                for j in 0..n {
                    s += a[i] * self.cov[i * n + j] * b[j];
                }
            }
            s
        };
        InstPol { q, u, var_q: quad(&jq, &jq), var_u: quad(&ju, &ju), cov_qu: quad(&jq, &ju) }
    }
    /// A polynomial is defined everywhere; where it was fitted is the calibration's region.
    fn contains(&self, _: f64, _: f64) -> bool {
        true
    }
    fn params(&self) -> Vec<f64> {
        self.q.iter().chain(&self.u).copied().collect()
    }
    fn covariance(&self) -> Option<Vec<f64>> {
        Some(self.cov.clone())
    }
    fn jacobian(&self, x: f64, y: f64) -> Option<(Vec<f64>, Vec<f64>)> {
        let t = self.basis(x, y);
        let m = t.len();
        let mut jq = vec![0.0; 2 * m];
        let mut ju = vec![0.0; 2 * m];
        jq[..m].copy_from_slice(&t);
        ju[m..].copy_from_slice(&t);
        Some((jq, ju))
    }
    fn describe(&self) -> String {
        format!("a polynomial field of degree {} in x, y", self.degree)
    }
}

/// The conditioning judge's words for a polynomial field: its terms, and the layout that
/// determines them.
pub(crate) fn plane_words(degree: usize) -> crate::conditioning::Words {
    let names = PolyModel::powers(degree)
        .into_iter()
        .map(|(i, j)| match (i, j) {
            (0, 0) => "the constant term".to_string(),
            (i, j) => {
                let p = |v: &str, k: usize| match k {
                    0 => String::new(),
                    1 => v.to_string(),
                    k => format!("{v}^{k}"),
                };
                format!("the {}{} term", p("x", i), p("y", j))
            }
        })
        .collect();
    crate::conditioning::Words::new(
        names,
        format!(
            "a degree-{degree} polynomial in x and y needs positions (stars or bins) spread in two dimensions, \
             at {} or more distinct places not on one line (or curve of that degree): add positions off the line, \
             or fit a radial model instead",
            PolyModel::n_terms(degree)
        ),
    )
}

/// The result of a polynomial fit: the model and what the fit saw (as [`crate::RadialFit`]).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct PolyFit {
    pub model: PolyModel,
    pub chi2_reduced: f64,
    /// RMS per component of the residuals over the used bins.
    pub rms_residual: f64,
    pub n_used: usize,
    /// Per input bin: used (valid and not excluded).
    pub used: Vec<bool>,
    /// Per input bin: final robust weight (0 for unused bins).
    pub weights: Vec<f64>,
}

/// Fit a polynomial field of total degree `degree` (1 to [`MAX_DEGREE`]) to the bins by robust
/// weighted least squares on `(q, u)`: the bins' errors, the robust loss, the exclusions (about
/// `opts.centre`) and the error scaling of `opts` as the radial fit uses them. The covariance
/// is `(A^T W A)^-1` (robust weights in `W`) times the scaling's factor of the reduced chi^2.
pub fn fit_poly(bins: &[Bin], degree: usize, opts: &RadialFitOptions) -> Result<PolyFit> {
    if !(1..=MAX_DEGREE).contains(&degree) {
        return Err(Error::Input(format!("polynomial degree {degree}: expected 1 (a plane) to {MAX_DEGREE}")));
    }
    let used: Vec<bool> = bins
        .iter()
        .map(|b| b.is_valid() && !opts.exclusions.iter().any(|e| e.excludes_about(b.x, b.y, opts.centre)))
        .collect();
    let sel: Vec<&Bin> = bins.iter().zip(&used).filter(|(_, u)| **u).map(|(b, _)| b).collect();
    let m = PolyModel::n_terms(degree);
    let needed = (2 * m).max(m + 3);
    if sel.len() < needed {
        return Err(Error::TooFewBins { used: sel.len(), total: bins.len(), needed });
    }
    let mut a = DMatrix::<f64>::zeros(sel.len(), m);
    for (r, b) in sel.iter().enumerate() {
        for (c, t) in basis(degree, b.x, b.y).into_iter().enumerate() {
            a[(r, c)] = t;
        }
    }
    // Each component's weighted least squares with the bins' robust weights `w`: coefficients
    // and the inverse normal matrix.
    let solve = |w: &[f64], values: &dyn Fn(&Bin) -> (f64, f64)| -> Result<(DVector<f64>, DMatrix<f64>)> {
        let mut ata = DMatrix::<f64>::zeros(m, m);
        let mut atb = DVector::<f64>::zeros(m);
        let wts: Vec<f64> = sel.iter().zip(w).map(|(b, wr)| wr / values(b).1.powi(2)).collect();
        crate::conditioning::judge(&crate::conditioning::weighted_design(&a, &wts), &plane_words(degree))?;
        for (r, b) in sel.iter().enumerate() {
            let (v, s) = values(b);
            let wr = w[r] / (s * s);
            for i in 0..m {
                atb[i] += wr * a[(r, i)] * v;
                for j in 0..m {
                    ata[(i, j)] += wr * a[(r, i)] * a[(r, j)];
                }
            }
        }
        let inv = ata.try_inverse().ok_or_else(|| {
            Error::Degenerate(format!(
                "the {m} terms of a degree-{degree} polynomial are not constrained by the bins' positions (too few distinct positions, or all on a line)"
            ))
        })?;
        Ok((&inv * atb, inv))
    };
    let q_of = |b: &Bin| (b.qu.q, b.sigma_q());
    let u_of = |b: &Bin| (b.qu.u, b.sigma_u());
    let mut w = vec![1.0; sel.len()];
    let (mut cq, mut iq) = solve(&w, &q_of)?;
    let (mut cu, mut iu) = solve(&w, &u_of)?;
    if opts.robust != crate::models::radial::Robust::None {
        for _ in 0..30 {
            let t: Vec<f64> = sel
                .iter()
                .enumerate()
                .map(|(r, b)| {
                    let fit = |c: &DVector<f64>| (0..m).map(|i| a[(r, i)] * c[i]).sum::<f64>();
                    let (tq, tu) = ((fit(&cq) - b.qu.q) / b.sigma_q(), (fit(&cu) - b.qu.u) / b.sigma_u());
                    (0.5 * (tq * tq + tu * tu)).sqrt()
                })
                .collect();
            let w_new = robust_weights(&t, opts.robust);
            let change = w_new.iter().zip(&w).map(|(x, y)| (x - y).abs()).fold(0.0, f64::max);
            w = w_new;
            (cq, iq) = solve(&w, &q_of)?;
            (cu, iu) = solve(&w, &u_of)?;
            if change < 1e-4 {
                break;
            }
        }
    }
    let (mut chi2, mut ss) = (0.0, 0.0);
    for (r, b) in sel.iter().enumerate() {
        let rq = (0..m).map(|i| a[(r, i)] * cq[i]).sum::<f64>() - b.qu.q;
        let ru = (0..m).map(|i| a[(r, i)] * cu[i]).sum::<f64>() - b.qu.u;
        chi2 += w[r] * ((rq / b.sigma_q()).powi(2) + (ru / b.sigma_u()).powi(2));
        ss += rq * rq + ru * ru;
    }
    let dof = (2 * sel.len()).saturating_sub(2 * m).max(1);
    let chi2_reduced = chi2 / dof as f64;
    let chi2_factor = opts.error_scaling.factor(chi2_reduced);
    // The components are fitted apart (the bins give no q-u covariance): a block-diagonal
    // covariance, symmetrized (the numerical inverse is symmetric only to rounding).
    let n = 2 * m;
    let mut cov = vec![0.0; n * n];
    for i in 0..m {
        for j in 0..m {
            cov[i * n + j] = 0.5 * (iq[(i, j)] + iq[(j, i)]) * chi2_factor;
            cov[(m + i) * n + (m + j)] = 0.5 * (iu[(i, j)] + iu[(j, i)]) * chi2_factor;
        }
    }
    let scaling =
        CovarianceScaling { mode: opts.error_scaling, chi2_reduced, chi2_factor, correlation_inflation: None };
    let model = PolyModel {
        degree,
        q: cq.iter().copied().collect(),
        u: cu.iter().copied().collect(),
        cov,
        scaling: Some(scaling),
    };
    let n_used = sel.len();
    let mut weights = vec![0.0; bins.len()];
    let mut k = 0;
    for (i, u) in used.iter().enumerate() {
        if *u {
            weights[i] = w[k];
            k += 1;
        }
    }
    Ok(PolyFit { model, chi2_reduced, rms_residual: (ss / (2 * n_used) as f64).sqrt(), n_used, used, weights })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The terms' order, and a plane's model: its value, and its variance against a covariance
    /// propagated by hand at one point.
    #[test]
    fn terms_and_a_plane() {
        assert_eq!(PolyModel::powers(2), vec![(0, 0), (1, 0), (0, 1), (2, 0), (1, 1), (0, 2)]);
        assert_eq!(PolyModel::n_terms(3), 10);
        let mut cov = vec![0.0; 36];
        cov[0] = 1e-8; // var a0
        cov[7] = 4e-8; // var a1
        cov[1] = 1e-8; // cov a0 a1
        cov[6] = 1e-8;
        let m = PolyModel { degree: 1, q: vec![1e-3, 2e-4, -1e-4], u: vec![0.0, 0.0, 3e-4], cov, scaling: None };
        let v = m.eval(2.0, -1.0);
        assert!((v.q - (1e-3 + 4e-4 + 1e-4)).abs() < 1e-18 && (v.u + 3e-4).abs() < 1e-18);
        // var q = var a0 + 4 var a1 + 2 * 2 cov a0 a1 at x = 2.
        assert!((v.var_q - (1e-8 + 4.0 * 4e-8 + 4.0 * 1e-8)).abs() < 1e-20, "{}", v.var_q);
        assert_eq!(v.var_u, 0.0);
    }
}
