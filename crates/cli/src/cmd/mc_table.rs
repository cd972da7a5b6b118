//! `instpol mc`'s text tables: the sweep (fig:deltap, fig:bias, the bias law) and the
//! accuracy report, as printed without --json.

use serde::Serialize;
use stokes::mc::budget::AccuracyReport;
use stokes::mc::sweep::{PAPER_C, PAPER_K};

/// One run's results (--json).
#[derive(Serialize)]
pub struct RunOut {
    #[serde(rename = "n_trials")]
    pub trials: u64,
    pub mean_p: f64,
    pub rms_p: f64,
    pub mode_p: Option<f64>,
    pub seconds: f64,
    pub trials_per_second: f64,
    pub median_p: Option<f64>,
    #[serde(rename = "percentile16_p")]
    pub q16_p: Option<f64>,
    #[serde(rename = "percentile84_p")]
    pub q84_p: Option<f64>,
    #[serde(rename = "n_rejected")]
    pub rejected: u64,
    pub sigma_p_analytic: f64,
    pub noise: String,
    pub n_hwp: usize,
    pub snr: f64,
    pub p0: f64,
    #[serde(rename = "chi0_deg")]
    pub chi0: f64,
    pub seed: u64,
    #[serde(rename = "n_threads")]
    pub threads: usize,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub rng_seconds: Option<f64>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub engine_over_rng: Option<f64>,
}

/// One run's summary: P's mean, mode, median, spread against eq:sigp, and the speed.
pub fn print_run(out: &RunOut) {
    let pc = |v: f64| format!("{:.5} %", 100.0 * v);
    let opc = |v: Option<f64>| v.map_or("n/a".into(), pc);
    outln!(
        "N = {}, SNR = {}, P0 = {}, chi0 = {} deg, noise {}, {} trials on {} threads",
        out.n_hwp,
        out.snr,
        pc(out.p0),
        out.chi0,
        out.noise,
        out.trials,
        out.threads
    );
    outln!("  mean P    {}", pc(out.mean_p));
    outln!("  mode P    {}", opc(out.mode_p));
    outln!("  median P  {}", opc(out.median_p));
    outln!("  sigma_P   {}   (eq:sigp: {})", pc(out.rms_p), pc(out.sigma_p_analytic));
    outln!("  68% band  [{}, {}]", opc(out.q16_p), opc(out.q84_p));
    if out.rejected > 0 {
        outln!("  {} trials dropped (no counts in both beams at some angle)", out.rejected);
    }
    outln!("  {:.3} s, {:.3e} trials/s", out.seconds, out.trials_per_second);
    if let Some(rs) = out.rng_seconds {
        outln!("  drawing the random numbers alone: {:.3} s (engine / draws = {:.2})", rs, out.seconds / rs);
    }
}

/// The sweep's results (--sweep --json).
#[derive(Serialize)]
pub struct SweepOut {
    pub n_hwp: usize,
    pub snr: f64,
    pub noise: String,
    #[serde(rename = "n_trials_per_point")]
    pub trials_per_point: u64,
    pub deltap: Vec<stokes::mc::sweep::DeltaPPoint>,
    pub bias: Vec<stokes::mc::sweep::BiasPoint>,
    pub fit_mc: Option<stokes::mc::sweep::LawFit>,
    pub fit_exact_rice: Option<stokes::mc::sweep::LawFit>,
    pub paper: (f64, f64),
    pub seconds: f64,
}

/// The sweep's tables: fig:deltap's values times SNR, fig:bias's, and the fitted bias laws.
pub fn print_sweep(out: &SweepOut) {
    let (n, trials) = (out.n_hwp, out.trials_per_point);
    let k = (n as f64 / 2.0).sqrt();
    outln!("fig:deltap  N = {n}, SNR = {}, noise {}, {trials} trials per point (values x SNR)", out.snr, out.noise);
    outln!(
        "{:>8} {:>9} {:>9} {:>9} {:>9} {:>10} {:>10} {:>10} {:>10}",
        "eta",
        "sigP*SNR",
        "eq:sigp",
        "Rice",
        "",
        "dP_mode",
        "WK(Rice)",
        "dP_mean",
        "Rice mean"
    );
    for p in &out.deltap {
        outln!(
            "{:>8.3} {:>9.4} {:>9.4} {:>9.4} {:>9} {:>10.4} {:>10.4} {:>10.4} {:>10.4}",
            p.eta,
            p.sigma_p * out.snr,
            p.sigma_p_eq * out.snr,
            p.sigma_p_rice * out.snr,
            "",
            p.delta_mode.map_or(f64::NAN, |d| d * out.snr),
            p.delta_mode_rice * out.snr,
            p.delta_mean * out.snr,
            p.delta_mean_rice * out.snr
        );
    }
    outln!("Rayleigh sigma_P x SNR = {:.4}", (2.0 - std::f64::consts::PI / 2.0).sqrt() / k);
    outln!();
    outln!("fig:bias  Delta P / sigma_P against SNR_P = P0 / sigma_P");
    let names: Vec<String> =
        out.bias.first().map(|b| b.estimators.iter().map(|e| e.0.clone()).collect()).unwrap_or_default();
    out!("{:>8} {:>8} {:>8} {:>8}", "SNR_P", "mode", "mean", "median");
    for nm in &names {
        out!(" {:>8}", format!("E[{nm}]"));
    }
    outln!();
    for b in &out.bias {
        out!(
            "{:>8.3} {:>8.4} {:>8.4} {:>8.4}",
            b.snr_p,
            b.mc_mode.unwrap_or(f64::NAN),
            b.mc_mean,
            b.mc_median.unwrap_or(f64::NAN)
        );
        for e in &b.estimators {
            out!(" {:>8.4}", e.1);
        }
        outln!();
    }
    outln!(
        "(mode/mean/median: Monte Carlo; E[...]: estimator bias over the Rice distribution, ml = Simmons & Stewart)"
    );
    outln!();
    outln!("bias law P0 = P~ [1 - (c / (sqrt(N/2) eta~))^k], fitted for sqrt(N/2) eta~ > 4:");
    outln!("{:>22} {:>8} {:>8} {:>7}", "", "c", "k", "points");
    if let Some(f) = out.fit_mc {
        outln!("{:>22} {:>8.3} {:>8.3} {:>7}", "this Monte Carlo", f.c, f.k, f.points);
    }
    if let Some(f) = out.fit_exact_rice {
        outln!("{:>22} {:>8.3} {:>8.3} {:>7}", "exact Rice mode", f.c, f.k, f.points);
    }
    outln!("{:>22} {:>8.3} {:>8.3}", "paper (sec:bias)", PAPER_C, PAPER_K);
    outln!("({:.1} s)", out.seconds);
}

/// The accuracy report's three tables (`n_hwp`: the noise comparison's N).
pub fn print_accuracy(out: &AccuracyReport, n_hwp: usize) {
    outln!("1. Monte Carlo precision against trials ({}), 5 repetitions each", out.precision_config);
    outln!("   values in % of polarization; +- is the scatter of one run");
    outln!("{:>10} {:>10} {:>22} {:>22} {:>22}", "trials", "seconds", "sigma_P", "bias (mean)", "bias (mode)");
    for r in &out.precision {
        let f = |v: f64, s: f64| format!("{:.5} +- {:.5}", 100.0 * v, 100.0 * s);
        outln!(
            "{:>10} {:>10.4} {:>22} {:>22} {:>22}",
            r.trials,
            r.seconds,
            f(r.sigma_p, r.sigma_p_scatter),
            f(r.bias_mean, r.bias_mean_scatter),
            f(r.bias_mode, r.bias_mode_scatter)
        );
    }
    outln!();
    outln!("2. Observer: sigma_P (eq:sigp, %) against SNR (exposure time ~ SNR^2, relative to SNR 100)");
    outln!("   and the systematic floor of HWP defects at infinite SNR (mueller forward model, %)");
    let snrs: Vec<f64> = out.observer[0].sigma_p.iter().map(|s| s.0).collect();
    out!("{:>6}", "N");
    for s in &snrs {
        out!(" {:>9}", format!("SNR {s}"));
    }
    outln!("  SNR where sigma_P = worst floor");
    for r in &out.observer {
        out!("{:>6}", r.n_hwp);
        for s in &r.sigma_p {
            out!(" {:>9.4}", 100.0 * s.1);
        }
        outln!("  {:.0}", r.snr_at_floor);
    }
    out!("{:>6}", "time");
    for s in &out.observer[0].sigma_p {
        out!(" {:>9.3}", s.2);
    }
    outln!();
    outln!("{:>30} {:>10} {:>10} {:>10}", "floor (%)", "N=4", "N=8", "N=16");
    for (k, (name, _)) in out.observer[0].floors.iter().enumerate() {
        out!("{:>30}", name);
        for r in &out.observer {
            out!(" {:>10.5}", 100.0 * r.floors[k].1);
        }
        outln!();
    }
    outln!();
    outln!("3. Fast noise modes against exact Poisson (N = {}, eta = P0 SNR = 2, {} trials)", n_hwp, out.noise_trials);
    outln!(
        "{:>6} {:>9} {:>11} {:>11} {:>14} {:>12} {:>14}",
        "SNR",
        "noise",
        "mean P %",
        "sigma_P %",
        "mean dev/err",
        "sigma rel",
        "trials/s"
    );
    for r in &out.noise_modes {
        outln!(
            "{:>6} {:>9} {:>11.5} {:>11.5} {:>14.2} {:>12.4} {:>14.3e}{}",
            r.snr,
            r.noise,
            100.0 * r.mean_p,
            100.0 * r.rms_p,
            r.mean_dev_sigma,
            r.rms_rel_dev,
            r.trials_per_second,
            if r.rejected > 0 { format!("  ({} dropped: no counts)", r.rejected) } else { String::new() }
        );
    }
}
