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
