//! Correlated bin errors: how much a parameter covariance computed as if the bins were
//! independent understates the truth when neighbouring bins share their noise (a smoothed map,
//! such as the FORS2 INLA maps, or overlapping bins).
//!
//! For noise with correlation `rho(lag)` between bins, a least-squares parameter whose
//! derivatives vary slowly over the correlation length has variance `(J^T W J)^-1` times
//! `tau = sum over all lags of rho(lag)` (the number of bins per independent one; the
//! "effective number of bins" is `N / tau`). White noise smoothed with a kernel `k` of sum 1
//! has `tau = 1 / sum k^2` exactly (`4 pi s^2` for a Gaussian of `s` bins, `s >~ 1`).
//!
//! `tau` is estimated from the fit's standardized residuals `(data - model) / sigma`, laid on
//! the bins' regular grid, pooled over `q` and `u`: the autocorrelation at each lag is summed
//! ring by ring (Chebyshev distance 1, 2, ...) and the sum stops before the first ring whose
//! total is not positive (Geyer's initial-positive-sequence rule for time series, in 2-D), or at
//! a window cap. A smooth model misfit (a non-circular field fitted by a circular model) is
//! correlated too and is counted: the factor then also says how much the misfit is worth.

use crate::{Error, Result};
use serde::{Deserialize, Serialize};

/// The inflation factor and how it was found.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct CorrelationInflation {
    /// `tau`, the factor applied to the covariance (at least 1: anti-correlated residuals are
    /// not taken as a licence to shrink errors).
    pub factor: f64,
    /// Mean correlation of the residuals of neighbouring bins (the four lags of distance 1).
    pub rho_neighbour: f64,
    /// Half-width (bins) of the window the correlations were summed over.
    pub window_bins: usize,
    /// False when the ring sums were still positive at the window cap: the factor is then a
    /// lower bound (correlations reach further than the window).
    pub resolved: bool,
    /// Grid step (arcmin) found in the bin positions.
    pub step_arcmin: [f64; 2],
}

/// Largest window half-width in bins (and at most a quarter of the grid's smaller side).
const MAX_WINDOW: usize = 30;

/// The distinct values of `v` (sorted), merged within `tol`.
fn distinct(v: &mut [f64], tol: f64) -> Vec<f64> {
    v.sort_by(|a, b| a.total_cmp(b));
    let mut out: Vec<f64> = vec![];
    for &x in v.iter() {
        if out.last().is_none_or(|l| x - l > tol) {
            out.push(x);
        }
    }
    out
}

/// A regular grid holding the points: origin, step, size, and each point's cell.
struct Grid {
    step: [f64; 2],
    nx: usize,
    ny: usize,
    cell: Vec<usize>,
}

fn grid_of(xy: &[(f64, f64)]) -> Result<Grid> {
    let axis = |vals: Vec<f64>, name: &str| -> Result<(f64, f64, usize, Vec<usize>)> {
        let (lo, hi) = vals.iter().fold((f64::INFINITY, f64::NEG_INFINITY), |(l, h), v| (l.min(*v), h.max(*v)));
        let tol = 1e-9 * (1.0 + (hi - lo).abs());
        let d = distinct(&mut vals.clone(), tol);
        let step = d.windows(2).map(|w| w[1] - w[0]).fold(f64::INFINITY, f64::min);
        if d.len() < 3 || !step.is_finite() || step <= 0.0 {
            return Err(Error::Input(format!(
                "correlated errors: the bins span only {} distinct {name} positions; the residual autocorrelation needs a \
                 map (bins on a regular grid)",
                d.len()
            )));
        }
        let mut idx = Vec::with_capacity(vals.len());
        for v in &vals {
            let f = (v - lo) / step;
            if (f - f.round()).abs() > 1e-3 {
                return Err(Error::Input(format!(
                    "correlated errors: the bins are not on a regular grid ({name} = {v} arcmin is {f:.4} steps of \
                     {step} arcmin from the first bin); the residual autocorrelation needs a map"
                )));
            }
            idx.push(f.round() as usize);
        }
        let n = ((hi - lo) / step).round() as usize + 1;
        Ok((lo, step, n, idx))
    };
    let (_, sx, nx, ix) = axis(xy.iter().map(|p| p.0).collect(), "x")?;
    let (_, sy, ny, iy) = axis(xy.iter().map(|p| p.1).collect(), "y")?;
    if nx.saturating_mul(ny) > 50_000_000 {
        return Err(Error::Input(format!(
            "correlated errors: the bins' grid would be {nx} x {ny} cells (steps {sx}, {sy} arcmin): too sparse a set of \
             bins for a residual autocorrelation"
        )));
    }
    let cell = ix.iter().zip(&iy).map(|(i, j)| j * nx + i).collect();
    Ok(Grid { step: [sx, sy], nx, ny, cell })
}

/// Estimate the covariance inflation `tau` from standardized residuals `(x, y, z_q, z_u)` of
/// the bins a fit used (`z = (data - model) / sigma`), the bins lying on a regular grid (a map
/// or a binned frame; missing cells are allowed).
pub fn residual_inflation(points: &[(f64, f64, f64, f64)]) -> Result<CorrelationInflation> {
    let pts: Vec<&(f64, f64, f64, f64)> = points.iter().filter(|p| p.0.is_finite() && p.1.is_finite()).collect();
    if pts.len() < 16 {
        return Err(Error::TooFewBins { used: pts.len(), total: points.len(), needed: 16 });
    }
    let g = grid_of(&pts.iter().map(|p| (p.0, p.1)).collect::<Vec<_>>())?;
    let n = pts.len() as f64;
    let (mq, mu) = (pts.iter().map(|p| p.2).sum::<f64>() / n, pts.iter().map(|p| p.3).sum::<f64>() / n);
    // Dense grid of mean-subtracted residuals; NaN where there is no bin.
    let mut zq = vec![f64::NAN; g.nx * g.ny];
    let mut zu = vec![f64::NAN; g.nx * g.ny];
    for (p, &c) in pts.iter().zip(&g.cell) {
        zq[c] = p.2 - mq;
        zu[c] = p.3 - mu;
    }
    let (nx, ny) = (g.nx as isize, g.ny as isize);
    // Mean product of the residuals at lag (a, b) over the pairs present.
    let cov_at = |a: isize, b: isize| -> Option<f64> {
        let (mut s, mut m) = (0.0, 0usize);
        for j in 0.max(-b)..ny.min(ny - b) {
            let row = j * nx;
            let row2 = (j + b) * nx;
            for i in 0.max(-a)..nx.min(nx - a) {
                let (k, k2) = ((row + i) as usize, (row2 + i + a) as usize);
                let (q1, q2) = (zq[k], zq[k2]);
                if q1.is_nan() || q2.is_nan() {
                    continue;
                }
                s += q1 * q2 + zu[k] * zu[k2];
                m += 2;
            }
        }
        (m > 0).then(|| s / m as f64)
    };
    let c0 = cov_at(0, 0).filter(|c| *c > 0.0).ok_or_else(|| {
        Error::Degenerate(
            "correlated errors: the residuals are all zero (a perfect fit has no noise to correlate)".into(),
        )
    })?;
    let rho = |a: isize, b: isize| cov_at(a, b).map_or(0.0, |c| c / c0);
    let cap = MAX_WINDOW.min(g.nx.min(g.ny) / 4).max(1) as isize;
    let mut tau = 1.0;
    let mut window = 0;
    let mut resolved = false;
    let mut rho_neighbour = 0.0;
    for k in 1..=cap {
        // The ring max(|a|, |b|) = k, half of it by the symmetry rho(a, b) = rho(-a, -b): lags
        // (a, k), (k, b <= 0) and (-k, b < 0), one of each pair +-(a, b).
        let mut ring = 0.0;
        for a in -k..=k {
            ring += rho(a, k);
        }
        for b in (1 - k)..=0 {
            ring += rho(k, b);
        }
        for b in (1 - k)..0 {
            ring += rho(-k, b);
        }
        if k == 1 {
            rho_neighbour = 0.5 * (rho(1, 0) + rho(0, 1));
        }
        let ring = 2.0 * ring;
        if ring <= 0.0 {
            resolved = true;
            break;
        }
        tau += ring;
        window = k as usize;
    }
    Ok(CorrelationInflation { factor: tau.max(1.0), rho_neighbour, window_bins: window, resolved, step_arcmin: g.step })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ring_enumeration_visits_each_lag_pair_once() {
        // The half rings of k = 1..3 must hold (2k+1)^2 - (2k-1)^2 = 8k lags / 2 each.
        for k in 1isize..=3 {
            let mut lags = vec![];
            for a in -k..=k {
                lags.push((a, k));
            }
            for b in (1 - k)..=0 {
                lags.push((k, b));
            }
            for b in (1 - k)..0 {
                lags.push((-k, b));
            }
            assert_eq!(lags.len() as isize, 4 * k);
            for &(a, b) in &lags {
                assert!(!lags.contains(&(-a, -b)), "lag ({a}, {b}) and its mirror both counted");
                assert_eq!(a.abs().max(b.abs()), k);
            }
        }
    }

    #[test]
    fn independent_residuals_give_no_inflation_and_off_grid_bins_are_refused() {
        use rand::SeedableRng;
        use rand_distr::{Distribution, StandardNormal};
        let mut rng = rand_xoshiro::Xoshiro256PlusPlus::seed_from_u64(11);
        let mut pts = vec![];
        for j in 0..60 {
            for i in 0..60 {
                let (a, b): (f64, f64) = (StandardNormal.sample(&mut rng), StandardNormal.sample(&mut rng));
                pts.push((0.1 * i as f64 - 2.0, 0.1 * j as f64 - 3.0, a, b));
            }
        }
        let c = residual_inflation(&pts).unwrap();
        // White noise: rho = 0 at every lag, so tau ~ 1 (+ a few rings of noise).
        assert!(c.factor < 1.3 && c.rho_neighbour.abs() < 0.05, "{c:?}");
        assert!((c.step_arcmin[0] - 0.1).abs() < 1e-12 && (c.step_arcmin[1] - 0.1).abs() < 1e-12);
        pts[7].0 += 0.037;
        let e = residual_inflation(&pts).unwrap_err().to_string();
        assert!(e.contains("regular grid"), "{e}");
    }
}
