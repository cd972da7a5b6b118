//! Accuracy against time: what the Monte Carlo's answers are worth for the trials they cost,
//! what an observer's `sigma_P` and systematic floor are at each SNR (exposure time), and what
//! the fast noise modes cost in accuracy against exact Poisson noise.

use super::{run, Engine, McConfig, Noise};
use crate::stats::Error;
use crate::StokesSolver;
use mueller::{DualBeam, Harmonic, Hwp, Stokes};
use std::f64::consts::PI;
use std::time::Instant;

/// Precision of the Monte Carlo estimates for a number of trials, from the scatter of
/// independent repetitions.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct PrecisionRow {
    #[serde(rename = "n_trials")]
    pub trials: u64,
    #[serde(rename = "n_repetitions")]
    pub repetitions: usize,
    /// Mean wall time of one run (s).
    pub seconds: f64,
    pub sigma_p: f64,
    /// Scatter of `sigma_P` between repetitions.
    pub sigma_p_scatter: f64,
    pub bias_mean: f64,
    pub bias_mean_scatter: f64,
    pub bias_mode: f64,
    pub bias_mode_scatter: f64,
}

fn mean_sd(v: &[f64]) -> (f64, f64) {
    let n = v.len() as f64;
    let m = v.iter().sum::<f64>() / n;
    let s = if v.len() > 1 { (v.iter().map(|x| (x - m).powi(2)).sum::<f64>() / (n - 1.0)).sqrt() } else { f64::NAN };
    (m, s)
}

/// How the precision of `sigma_P`, the mean bias and the mode bias improve with trials.
pub fn precision_table(
    base: &McConfig,
    trials: &[u64],
    reps: usize,
    threads: Option<usize>,
) -> Result<Vec<PrecisionRow>, Error> {
    let mut rows = Vec::new();
    for &t in trials {
        let (mut sp, mut bm, mut bmo, mut secs) = (Vec::new(), Vec::new(), Vec::new(), 0.0);
        for r in 0..reps {
            let mut cfg = base.clone();
            cfg.trials = t;
            cfg.seed = base.seed.wrapping_add(7919 * r as u64 + t);
            let t0 = Instant::now();
            let res = run(&cfg, threads, None)?;
            secs += t0.elapsed().as_secs_f64();
            sp.push(res.rms_p);
            bm.push(res.mean_p - base.p0);
            bmo.push(res.mode_p.unwrap_or(f64::NAN) - base.p0);
        }
        let (a, b) = mean_sd(&sp);
        let (c, d) = mean_sd(&bm);
        let (e, f) = mean_sd(&bmo);
        rows.push(PrecisionRow {
            trials: t,
            repetitions: reps,
            seconds: secs / reps as f64,
            sigma_p: a,
            sigma_p_scatter: b,
            bias_mean: c,
            bias_mean_scatter: d,
            bias_mode: e,
            bias_mode_scatter: f,
        });
    }
    Ok(rows)
}

/// Systematic error of `(Q, U)` at infinite SNR: the largest `hypot(Q - Q0, U - U0)` over
/// input angles (every 5 deg) and the given inputs `(P0, V)`, for a plate `hwp` and `N` optimal
/// angles, computed with the `mueller` forward model and the one Stokes solver.
pub fn systematic_floor(n_hwp: usize, hwp: Hwp, inputs: &[(f64, f64)]) -> Result<f64, Error> {
    let theta = mueller::optimal_angles(n_hwp);
    let solver = StokesSolver::new(&theta).map_err(|e| Error::Model(e.to_string()))?;
    let inst = DualBeam { hwp, ..DualBeam::ideal() }.compile();
    let mut worst: f64 = 0.0;
    let mut f = vec![0.0; n_hwp];
    for &(p0, v) in inputs {
        for k in 0..36 {
            let chi = k as f64 * PI / 36.0;
            let (s2, c2) = (2.0 * chi).sin_cos();
            let s = Stokes::new(1.0, p0 * c2, p0 * s2, v);
            for (i, b) in inst.fluxes(&s, &theta).iter().enumerate() {
                f[i] = crate::normalized_difference(b.f_o, b.f_e);
            }
            let (q, u) = solver.solve(&f);
            worst = worst.max((q - p0 * c2).hypot(u - p0 * s2));
        }
    }
    Ok(worst)
}

/// The plate defects of the budget: name and the plates to try (the worst over harmonic
/// phases is taken).
pub fn defect_cases() -> Vec<(&'static str, Vec<Hwp>, Vec<(f64, f64)>)> {
    let amp = 5e-4; // 0.05 %: the k = 1, 2 amplitudes seen in FORS1 (sec:HWP)
    let phases: Vec<f64> = (0..12).map(|k| k as f64 * PI / 6.0).collect();
    let unpol = vec![(0.0, 0.0), (0.01, 0.0)];
    let dust =
        phases.iter().map(|&ph| Hwp { dust: Some(Harmonic { amplitude: amp, phase: ph }), ..Hwp::ideal() }).collect();
    let pleo = phases
        .iter()
        .map(|&ph| Hwp { pleochroism: Some(Harmonic { amplitude: amp, phase: ph }), ..Hwp::ideal() })
        .collect();
    let ret = vec![Hwp { retardance_error: 10f64.to_radians(), ..Hwp::ideal() }];
    vec![
        ("k=1 harmonic 0.05%", dust, unpol.clone()),
        ("k=2 harmonic 0.05%", pleo, unpol.clone()),
        ("retardance 10deg, V=0", ret.clone(), unpol),
        ("retardance 10deg, Q=U=V=1%", ret, vec![(0.01 * 2f64.sqrt(), 0.01)]),
    ]
}

/// One row of the observer's table.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct ObserverRow {
    pub n_hwp: usize,
    /// Systematic floor per defect case (fraction), in the order of [`defect_cases`].
    pub floors: Vec<(String, f64)>,
    /// `(SNR, sigma_P = 1/(sqrt(N/2) SNR), relative exposure time (SNR/100)^2)`.
    pub sigma_p: Vec<(f64, f64, f64)>,
    /// The SNR at which `sigma_P` equals the largest floor: more exposure buys nothing.
    pub snr_at_floor: f64,
}

/// `sigma_P` against SNR and the systematic floors for each `N`.
pub fn observer_table(ns: &[usize], snrs: &[f64]) -> Result<Vec<ObserverRow>, Error> {
    let cases = defect_cases();
    let mut rows = Vec::new();
    for &n in ns {
        let mut floors = Vec::new();
        for (name, plates, inputs) in &cases {
            let mut w: f64 = 0.0;
            for h in plates {
                w = w.max(systematic_floor(n, *h, inputs)?);
            }
            floors.push((name.to_string(), w));
        }
        let k = (n as f64 / 2.0).sqrt();
        let sigma_p = snrs.iter().map(|&s| (s, 1.0 / (k * s), (s / 100.0).powi(2))).collect();
        let fmax = floors.iter().map(|f| f.1).fold(0.0, f64::max);
        rows.push(ObserverRow {
            n_hwp: n,
            floors,
            sigma_p,
            snr_at_floor: if fmax > 0.0 { 1.0 / (k * fmax) } else { f64::INFINITY },
        });
    }
    Ok(rows)
}

/// One row of the noise-mode comparison.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct NoiseRow {
    pub snr: f64,
    pub noise: String,
    pub mean_p: f64,
    pub rms_p: f64,
    /// `(mean_p - mean_p[poisson]) / (combined MC error)`.
    pub mean_dev_sigma: f64,
    /// `(rms_p - rms_p[poisson]) / rms_p[poisson]`.
    pub rms_rel_dev: f64,
    pub trials_per_second: f64,
    #[serde(rename = "n_rejected")]
    pub rejected: u64,
}

/// Compare the three noise modes at each SNR on the same work: `N`, `eta = P0 SNR` (the
/// same regime of the Rice distribution at every SNR), trials.
pub fn noise_comparison(
    n_hwp: usize,
    eta: f64,
    snrs: &[f64],
    trials: u64,
    seed: u64,
    threads: Option<usize>,
) -> Result<Vec<NoiseRow>, Error> {
    let mut rows = Vec::new();
    for (j, &snr) in snrs.iter().enumerate() {
        let mut base = None;
        for noise in Noise::ALL {
            let mut cfg = McConfig::new(n_hwp, snr, (eta / snr).min(1.0), 0.5, trials, noise);
            // Independent streams per SNR so the rows are independent comparisons.
            cfg.seed = seed.wrapping_add(104_729 * j as u64);
            let eng = Engine::new(&cfg)?;
            let t0 = Instant::now();
            let r = match threads {
                None => eng.run(None),
                Some(j) => rayon::ThreadPoolBuilder::new()
                    .num_threads(j.max(1))
                    .build()
                    .map_err(|e| Error::Model(e.to_string()))?
                    .install(|| eng.run(None)),
            };
            let secs = t0.elapsed().as_secs_f64();
            let (m0, s0) = *base.get_or_insert((r.mean_p, r.rms_p));
            let err = (s0 * s0 / r.trials.max(1) as f64 + r.rms_p * r.rms_p / r.trials.max(1) as f64).sqrt();
            rows.push(NoiseRow {
                snr,
                noise: noise.name().into(),
                mean_p: r.mean_p,
                rms_p: r.rms_p,
                mean_dev_sigma: if noise == Noise::Poisson { 0.0 } else { (r.mean_p - m0) / err },
                rms_rel_dev: (r.rms_p - s0) / s0,
                trials_per_second: r.trials as f64 / secs,
                rejected: r.rejected,
            });
        }
    }
    Ok(rows)
}

/// `eta = P0 SNR` of the accuracy report's configuration: where the bias and `sigma_P` are
/// comparable (fig:deltap).
pub const REPORT_ETA: f64 = 2.0;

/// Independent repetitions of each number of trials in the report's precision table.
pub const REPORT_REPETITIONS: usize = 5;

/// The numbers of trials of the report's precision table: the decades from 1000 to
/// `max_trials` (at least 1000).
pub fn report_trials(max_trials: u64) -> Vec<u64> {
    let tmax = max_trials.max(1000);
    let mut out = vec![];
    let mut t = 1000u64;
    while t <= tmax {
        out.push(t);
        t = t.saturating_mul(10);
        if t == u64::MAX {
            break;
        }
    }
    out
}

/// Trials the report runs for `max_trials`, about: [`REPORT_REPETITIONS`] of each decade up
/// to it (5.6 times it) and the noise comparison; six times it, for a budget.
pub fn report_cost(max_trials: u64) -> u64 {
    max_trials.max(1000).saturating_mul(6)
}

/// The configuration of the report's precision table (no trials set): `P0 = REPORT_ETA / SNR`
/// (at most 1).
pub fn report_config(n_hwp: usize, snr: f64, chi0: f64, noise: Noise, seed: u64) -> McConfig {
    let mut base = McConfig::new(n_hwp, snr, (REPORT_ETA / snr).min(1.0), chi0, 0, noise);
    base.seed = seed;
    base
}

/// The accuracy-against-time report (`instpol mc --accuracy-report`).
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct AccuracyReport {
    pub precision: Vec<PrecisionRow>,
    pub observer: Vec<ObserverRow>,
    pub noise_modes: Vec<NoiseRow>,
    /// The precision table's configuration, in words.
    pub precision_config: String,
    /// Its `P0` (fraction): [`REPORT_ETA`] / SNR.
    #[serde(skip)]
    pub p0: f64,
    /// Trials per point of the noise comparison.
    #[serde(skip)]
    pub noise_trials: u64,
}

/// The report for `n_hwp` angles at `snr` (`chi0` rad, `noise`, `seed`) up to `max_trials`:
/// the Monte Carlo's precision against trials at `eta = 2` ([`precision_table`] over
/// [`report_trials`], [`REPORT_REPETITIONS`] each), the observer's `sigma_P` and systematic
/// floor for N = 4, 8, 16 at SNR 10 to 10 000 ([`observer_table`]), and the fast noise modes
/// against exact Poisson at SNR 3 to 300 and `eta = 2` ([`noise_comparison`], at most
/// 200 000 trials). Runs on the calling thread pool.
pub fn accuracy_report(
    n_hwp: usize,
    snr: f64,
    chi0: f64,
    noise: Noise,
    seed: u64,
    max_trials: u64,
) -> Result<AccuracyReport, Error> {
    let p0 = REPORT_ETA / snr;
    let base = report_config(n_hwp, snr, chi0, noise, seed);
    let tmax = max_trials.max(1000);
    let noise_trials = tmax.min(200_000);
    let precision = precision_table(&base, &report_trials(tmax), REPORT_REPETITIONS, None)?;
    let observer = observer_table(&[4, 8, 16], &[10.0, 30.0, 100.0, 300.0, 1000.0, 3000.0, 10000.0])?;
    let noise_modes = noise_comparison(n_hwp, REPORT_ETA, &[3.0, 10.0, 30.0, 100.0, 300.0], noise_trials, seed, None)?;
    Ok(AccuracyReport {
        precision,
        observer,
        noise_modes,
        precision_config: format!("N = {n_hwp}, SNR = {snr}, P0 = {p0} (eta = 2), noise {noise}"),
        p0,
        noise_trials,
    })
}

#[cfg(test)]
mod report_tests {
    use super::*;

    /// Decades from 1000 up to the largest not above the maximum; a small maximum gives 1000.
    #[test]
    fn report_trials_are_decades() {
        assert_eq!(report_trials(1_000_000), vec![1000, 10_000, 100_000, 1_000_000]);
        assert_eq!(report_trials(50_000), vec![1000, 10_000]);
        assert_eq!(report_trials(1), vec![1000]);
        assert_eq!(report_cost(1), 6000);
        assert!(!report_trials(u64::MAX).is_empty());
    }
}
