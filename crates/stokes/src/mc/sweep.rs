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
