//! Reproductions of the paper's section `sec:mc`: `sigma_P` and the bias against
//! `eta = P0 SNR` (fig:deltap), the bias over `sigma_P` against `SNR_P` for several
//! estimators (fig:bias), and a re-fit of the law
//! `P0 = <P> [1 - (0.62 / (sqrt(N/2) <eta>))^1.92]` (sec:bias).

use super::{run, McConfig, McResult, Noise};
use crate::stats::estimators::expected_n;
use crate::stats::rice::{mean_bias_n, mode_n, std_n};
use crate::stats::{Error, Estimator};

/// The paper's constants of the bias law (sec:bias).
pub const PAPER_C: f64 = 0.62;
pub const PAPER_K: f64 = 1.92;

/// `sqrt(N/2) eta` (= `P0 / sigma_P`, `eq:sigp`) above which sec:bias fits its law; the fits
/// of this module take it as `x_min`.
pub const LAW_FIT_FROM: f64 = 4.0;

/// The `eta = P0 SNR` grid of fig:deltap for `n_hwp` angles at `snr`: 25 points from 0.1 to
/// 10^1.5 ~ 30, evenly spaced in log, joined by the 13 points `sqrt(N/2) eta = 4, 5, ..., 16`
/// where sec:bias fits its law, sorted; points with `P0 = eta / SNR > 1` are left out.
pub fn deltap_etas(n_hwp: usize, snr: f64) -> Vec<f64> {
    let k = (n_hwp as f64 / 2.0).sqrt();
    let mut etas: Vec<f64> = (0..=24).map(|i| 10f64.powf(-1.0 + i as f64 * 2.5 / 24.0)).collect();
    etas.extend((0..=12).map(|i| (4.0 + i as f64) / k));
    etas.sort_by(|x, y| x.total_cmp(y));
    etas.retain(|&e| e / snr <= 1.0);
    etas
}

/// The `SNR_P = P0 / sigma_P` grid of fig:bias: 21 points from 0.1 to 10, evenly spaced in log
/// (the figure's abscissa).
pub fn bias_snr_ps() -> Vec<f64> {
    (0..=20).map(|i| 10f64.powf(-1.0 + i as f64 * 2.0 / 20.0)).collect()
}

/// The `a = P0 / sigma_P` values at which [`fit_law_exact`] samples the exact Rice mode to
/// refit the sec:bias law: 4 to 16 in steps of 0.1, the range of the paper's fit.
pub fn law_a_values() -> Vec<f64> {
    (0..=120).map(|i| 4.0 + i as f64 * 0.1).collect()
}

/// One point of fig:deltap (everything as a fraction; `eta = P0 SNR`).
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct DeltaPPoint {
    pub eta: f64,
    pub p0: f64,
    /// Monte Carlo standard deviation of `P`.
    pub sigma_p: f64,
    /// `eq:sigp`, `1 / (sqrt(N/2) SNR)`.
    pub sigma_p_eq: f64,
    /// Rice standard deviation for this `P0` (the exact curve; Rayleigh value at `P0 = 0`).
    pub sigma_p_rice: f64,
    pub mode: Option<f64>,
    pub mean: f64,
    /// Monte Carlo bias of the mode, `mode - P0` (the paper's `Delta P`).
    pub delta_mode: Option<f64>,
    /// Monte Carlo bias of the mean.
    pub delta_mean: f64,
    /// Wardle & Kronberg: exact Rice mode minus `P0`.
    pub delta_mode_rice: f64,
    /// Rice mean minus `P0` (the curve for the average).
    pub delta_mean_rice: f64,
    pub seconds: f64,
}

/// Run the fig:deltap sweep for `N` angles at fixed `snr` over `etas`.
pub fn deltap_sweep(
    n_hwp: usize,
    snr: f64,
    etas: &[f64],
    trials: u64,
    noise: Noise,
    seed: u64,
    threads: Option<usize>,
    progress: Option<&(dyn Fn(u64) + Sync)>,
) -> Result<Vec<DeltaPPoint>, Error> {
    let sig = 1.0 / ((n_hwp as f64 / 2.0).sqrt() * snr);
    let mut out = Vec::with_capacity(etas.len());
    for (k, &eta) in etas.iter().enumerate() {
        let p0 = eta / snr;
        let mut cfg = McConfig::new(n_hwp, snr, p0, 0.5, trials, noise);
        cfg.seed = seed.wrapping_add(k as u64);
        let t = std::time::Instant::now();
        let r: McResult = run(&cfg, threads, progress)?;
        let a = p0 / sig;
        out.push(DeltaPPoint {
            eta,
            p0,
            sigma_p: r.rms_p,
            sigma_p_eq: sig,
            sigma_p_rice: sig * std_n(a),
            mode: r.mode_p,
            mean: r.mean_p,
            delta_mode: r.mode_p.map(|m| m - p0),
            delta_mean: r.mean_p - p0,
            delta_mode_rice: sig * (mode_n(a) - a),
            delta_mean_rice: sig * mean_bias_n(a),
            seconds: t.elapsed().as_secs_f64(),
        });
    }
    Ok(out)
}

/// One point of fig:bias: biases in units of `sigma_P` (`eq:sigp`) at `SNR_P = P0 / sigma_P`.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct BiasPoint {
    pub snr_p: f64,
    /// Monte Carlo `(mode - P0) / sigma_P`.
    pub mc_mode: Option<f64>,
    /// Monte Carlo `(mean - P0) / sigma_P`.
    pub mc_mean: f64,
    /// Monte Carlo `(median - P0) / sigma_P`.
    pub mc_median: Option<f64>,
    /// `(E[estimator] - P0) / sigma_P` over the Rice distribution, per estimator name
    /// (quadrature; `ml` is Simmons & Stewart's curve).
    pub estimators: Vec<(String, f64)>,
}

/// Run the fig:bias sweep: `N` angles, `snr`, over `snr_p` values.
pub fn bias_sweep(
    n_hwp: usize,
    snr: f64,
    snr_ps: &[f64],
    trials: u64,
    noise: Noise,
    seed: u64,
    threads: Option<usize>,
    progress: Option<&(dyn Fn(u64) + Sync)>,
) -> Result<Vec<BiasPoint>, Error> {
    let sig = 1.0 / ((n_hwp as f64 / 2.0).sqrt() * snr);
    let mut out = Vec::new();
    for (k, &sp) in snr_ps.iter().enumerate() {
        let p0 = sp * sig;
        let mut cfg = McConfig::new(n_hwp, snr, p0, 0.5, trials, noise);
        cfg.seed = seed.wrapping_add(1000 + k as u64);
        let r = run(&cfg, threads, progress)?;
        let ests = [Estimator::Naive, Estimator::As, Estimator::Wk, Estimator::Ml, Estimator::Mas, Estimator::Mb]
            .iter()
            .map(|e| (e.name().to_string(), expected_n(*e, sp) - sp))
            .collect();
        out.push(BiasPoint {
            snr_p: sp,
            mc_mode: r.mode_p.map(|m| (m - p0) / sig),
            mc_mean: (r.mean_p - p0) / sig,
            mc_median: r.median_p.map(|m| (m - p0) / sig),
            estimators: ests,
        });
    }
    Ok(out)
}

/// Fitted constants of `P0 = P~ [1 - (c / x)^k]`, `x = P~ / sigma_P = sqrt(N/2) <eta>`.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct LawFit {
    pub c: f64,
    pub k: f64,
    /// Points used (those with `x > x_min` and a positive bias).
    #[serde(rename = "n_points")]
    pub points: usize,
}

/// Least-squares fit of `ln(Delta P / P~) = k ln c - k ln x` over pairs
/// `(x = P~ / sigma, a = P0 / sigma)` with `x > x_min` (the paper uses 4), as in sec:bias.
pub fn fit_law(pairs: &[(f64, f64)], x_min: f64) -> Option<LawFit> {
    let pts: Vec<(f64, f64)> =
        pairs.iter().filter(|(x, a)| *x > x_min && x > a).map(|(x, a)| (x.ln(), ((x - a) / x).ln())).collect();
    let n = pts.len();
    if n < 2 {
        return None;
    }
    let nf = n as f64;
    let mx = pts.iter().map(|p| p.0).sum::<f64>() / nf;
    let my = pts.iter().map(|p| p.1).sum::<f64>() / nf;
    let sxx: f64 = pts.iter().map(|p| (p.0 - mx).powi(2)).sum();
    let sxy: f64 = pts.iter().map(|p| (p.0 - mx) * (p.1 - my)).sum();
    if sxx <= 0.0 {
        return None;
    }
    let slope = sxy / sxx;
    let icpt = my - slope * mx;
    let k = -slope;
    Some(LawFit { c: (icpt / k).exp(), k, points: n })
}

/// The law fitted to the exact Rice mode (no Monte Carlo noise) for `a` in `a_values`.
pub fn fit_law_exact(a_values: &[f64], x_min: f64) -> Option<LawFit> {
    let pairs: Vec<(f64, f64)> = a_values.iter().map(|&a| (mode_n(a), a)).collect();
    fit_law(&pairs, x_min)
}

/// The law fitted to Monte Carlo modes: pairs `(mode / sigma_P, P0 / sigma_P)` from a
/// fig:deltap sweep.
pub fn fit_law_mc(points: &[DeltaPPoint], x_min: f64) -> Option<LawFit> {
    let pairs: Vec<(f64, f64)> =
        points.iter().filter_map(|p| p.mode.map(|m| (m / p.sigma_p_eq, p.p0 / p.sigma_p_eq))).collect();
    fit_law(&pairs, x_min)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// fig:deltap's abscissa runs from eta = 0.1 to 10^1.5 and holds sec:bias's fit points
    /// sqrt(N/2) eta = 4..16 (integers); no point has P0 = eta / SNR above 1. fig:bias's runs
    /// from SNR_P = 0.1 to 10, a tenth of a decade apart.
    #[test]
    fn grids_span_the_figures() {
        let e = deltap_etas(8, 100.0);
        assert_eq!(e.len(), 25 + 13);
        assert!((e[0] - 0.1).abs() < 1e-15 && (e[e.len() - 1] - 10f64.powf(1.5)).abs() < 1e-12);
        assert!(e.windows(2).all(|w| w[0] <= w[1]));
        let fit_points = e.iter().filter(|&&x| (2.0 * x - (2.0 * x).round()).abs() < 1e-12 && 2.0 * x >= 4.0);
        assert_eq!(fit_points.count(), 13);
        assert!(deltap_etas(8, 10.0).iter().all(|&x| x / 10.0 <= 1.0));
        assert_eq!(deltap_etas(8, 10.0).len(), e.iter().filter(|&&x| x <= 10.0).count());
        let s = bias_snr_ps();
        assert_eq!(s.len(), 21);
        assert!((s[0] - 0.1).abs() < 1e-15 && (s[20] - 10.0).abs() < 1e-12 && (s[10] - 1.0).abs() < 1e-15);
        let a = law_a_values();
        assert_eq!((a.len(), a[0], a[120]), (121, LAW_FIT_FROM, 16.0));
    }
}
