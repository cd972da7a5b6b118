//! `instpol mc`: Monte Carlo of dual-beam polarimetry, the paper's section-mc reproductions
//! and the accuracy-against-time report.

use anyhow::{bail, Context, Result};
use indicatif::{ProgressBar, ProgressDrawTarget, ProgressStyle};
use serde::Serialize;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Instant;
use stokes::mc::budget::{noise_comparison, observer_table, precision_table};
use stokes::mc::sweep::{
    bias_snr_ps, bias_sweep, deltap_etas, deltap_sweep, fit_law_exact, fit_law_mc, law_a_values, LAW_FIT_FROM, PAPER_C,
    PAPER_K,
};
use stokes::mc::{Engine, McConfig, Noise};

/// Monte Carlo of dual-beam linear polarimetry: draw the ordinary and extraordinary fluxes
/// at N half-wave-plate angles (theta_i = i x 22.5 deg), reduce each trial with the Stokes
/// solver and report the distribution of the measured P.
///
/// Noise models (--noise): poisson (exact photon counts, SNR^2 counts per angle, plus --sky
/// and --read-noise), gauss-f (Gaussian on each F_i, sigma_F = 1/SNR) and gauss-qu (Gaussian on
/// Q and U, sigma = 1/(sqrt(N/2) SNR), eq:sigp). SNR is that of the intensity f_O + f_E at each
/// angle. The same --seed gives the same result on any number of --threads.
///
/// Three modes:
///
///   instpol mc --n-hwp 4 --snr 100 --p0 0.01 --trials 10000000 --noise poisson --json
///
///   instpol mc --sweep --plot sweep.png      (fig:deltap, fig:bias, refit of the bias law)
///
///   instpol mc --accuracy-report --plot acc.png   (precision vs trials and wall time;
///       sigma_P and the HWP systematic floor vs SNR for N = 4, 8, 16; fast noise modes vs
///       exact Poisson)
#[derive(clap::Args)]
pub struct Args {
    /// Number of HWP angles N (optimal set i x 22.5 deg).
    #[arg(long, default_value_t = 4)]
    pub n_hwp: usize,
    /// Signal-to-noise ratio of the intensity at each HWP angle.
    #[arg(long, default_value_t = 100.0)]
    pub snr: f64,
    /// True polarization degree (fraction, 0..1).
    #[arg(long, default_value_t = 0.01)]
    pub p0: f64,
    /// True polarization angle (degrees).
    #[arg(long, default_value_t = 30.0)]
    pub chi0: f64,
    /// Number of trials (with --sweep: per point; default there 400000).
    #[arg(long)]
    pub trials: Option<u64>,
    /// Noise model: poisson, gauss-f or gauss-qu.
    #[arg(long, default_value = "poisson")]
    pub noise: String,
    /// Random seed.
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// Worker threads (default: all cores).
    #[arg(long)]
    pub threads: Option<usize>,
    /// Sky counts per beam and HWP angle in the aperture (poisson only; subtracted as known).
    #[arg(long, default_value_t = 0.0)]
    pub sky: f64,
    /// Read noise per beam and HWP angle in the aperture, electrons rms (poisson only).
    #[arg(long, default_value_t = 0.0)]
    pub read_noise: f64,
    /// Also time drawing the same random numbers alone (the engine's cost floor); reported as
    /// rng_seconds.
    #[arg(long)]
    pub rng_baseline: bool,
    /// Reproduce fig:deltap and fig:bias of the paper and refit its bias law.
    #[arg(long, conflicts_with = "accuracy_report")]
    pub sweep: bool,
    /// Accuracy against time: Monte Carlo precision vs trials, sigma_P and the systematic
    /// floor vs SNR, and the accuracy cost of the fast noise modes.
    #[arg(long)]
    pub accuracy_report: bool,
    /// PNG file for the plot of --sweep or --accuracy-report.
    #[arg(long)]
    pub plot: Option<std::path::PathBuf>,
    /// Run even when the estimated run time exceeds 10 minutes (the estimate is printed first).
    #[arg(long)]
    pub force: bool,
    /// Print JSON (single run: trials, mean_p, rms_p, mode_p, seconds, trials_per_second, ...).
    #[arg(long)]
    pub json: bool,
}

#[derive(Serialize)]
struct RunOut {
    #[serde(rename = "n_trials")]
    trials: u64,
    mean_p: f64,
    rms_p: f64,
    mode_p: Option<f64>,
    seconds: f64,
    trials_per_second: f64,
    median_p: Option<f64>,
    #[serde(rename = "percentile16_p")]
    q16_p: Option<f64>,
    #[serde(rename = "percentile84_p")]
    q84_p: Option<f64>,
    #[serde(rename = "n_rejected")]
    rejected: u64,
    sigma_p_analytic: f64,
    noise: String,
    n_hwp: usize,
    snr: f64,
    p0: f64,
    #[serde(rename = "chi0_deg")]
    chi0: f64,
    seed: u64,
    #[serde(rename = "n_threads")]
    threads: usize,
    #[serde(skip_serializing_if = "Option::is_none")]
    rng_seconds: Option<f64>,
    #[serde(skip_serializing_if = "Option::is_none")]
    engine_over_rng: Option<f64>,
}

/// A progress bar over `total` trials that appears only once the work has run for a second,
/// and never with --json.
struct Progress {
    bar: ProgressBar,
    start: Instant,
    shown: AtomicBool,
    enabled: bool,
}

impl Progress {
    fn new(total: u64, enabled: bool) -> Self {
        let bar = ProgressBar::with_draw_target(Some(total), ProgressDrawTarget::hidden());
        if let Ok(st) = ProgressStyle::with_template(
            "{spinner} [{elapsed_precise}] {wide_bar} {human_pos}/{human_len} trials ({per_sec}, eta {eta})",
        ) {
            bar.set_style(st);
        }
        Self { bar, start: Instant::now(), shown: AtomicBool::new(false), enabled }
    }
    fn inc(&self, n: u64) {
        self.bar.inc(n);
        if self.enabled && !self.shown.load(Ordering::Relaxed) && self.start.elapsed().as_secs_f64() > 1.0 {
            self.shown.store(true, Ordering::Relaxed);
            self.bar.set_draw_target(ProgressDrawTarget::stderr());
        }
    }
    fn finish(&self) {
        self.bar.finish_and_clear();
    }
}

/// The longest run (estimated, seconds) started without --force.
const MAX_SECONDS: f64 = 600.0;

fn human(s: f64) -> String {
    if s < 120.0 {
        format!("{s:.0} s")
    } else if s < 7200.0 {
        format!("{:.0} min", s / 60.0)
    } else if s < 2.0 * 86400.0 {
        format!("{:.1} h", s / 3600.0)
    } else {
        format!("{:.1} days", s / 86400.0)
    }
}

/// Before a long run: time a short probe of the same configuration on the same pool, print the
/// estimated run time when it is over 10 s, and refuse beyond [`MAX_SECONDS`] unless `force`
/// (a `--trials 1e12` typo would otherwise run for hours without a word).
fn check_budget(cfg: &McConfig, total: u64, pool: &rayon::ThreadPool, force: bool) -> Result<()> {
    const PROBE: u64 = 100_000;
    if total <= 10 * PROBE {
        return Ok(());
    }
    let mut c = cfg.clone();
    c.trials = PROBE;
    let e = Engine::new(&c)?;
    let t0 = Instant::now();
    std::hint::black_box(pool.install(|| e.run(None)));
    let rate = PROBE as f64 / t0.elapsed().as_secs_f64().max(1e-9);
    let est = total as f64 / rate;
    if est > 10.0 {
        eprintln!(
            "note: {total} trials: estimated run time {} ({rate:.3e} trials/s on {} threads)",
            human(est),
            pool.current_num_threads()
        );
    }
    if est > MAX_SECONDS && !force {
        bail!(
            "--trials {total}: estimated run time {} exceeds the {} limit; lower --trials, or pass --force to run it",
            human(est),
            human(MAX_SECONDS)
        );
    }
    Ok(())
}

fn pool(threads: Option<usize>) -> Result<rayon::ThreadPool> {
    let mut b = rayon::ThreadPoolBuilder::new();
    if let Some(j) = threads {
        if j == 0 {
            bail!("--threads must be >= 1");
        }
        // More threads than cores only adds switching (and 1e6 threads exhaust the machine);
        // results do not depend on the thread count, so cap it and say so.
        let cores = std::thread::available_parallelism().map(|n| n.get()).unwrap_or(1);
        let j = if j > cores {
            eprintln!("note: --threads {j} capped at the machine's {cores} cores");
            cores
        } else {
            j
        };
        b = b.num_threads(j);
    }
    b.build().context("cannot start the worker threads")
}

pub fn run(a: Args) -> Result<()> {
    let noise: Noise = a.noise.parse()?;
    if !a.chi0.is_finite() {
        bail!("--chi0 = {} must be finite (degrees)", a.chi0);
    }
    if a.plot.is_some() && !(a.sweep || a.accuracy_report) {
        bail!("--plot needs --sweep or --accuracy-report");
    }
    // Checked before minutes of simulation, not after.
    if let Some(p) = &a.plot {
        crate::plot::ImageFormat::of(p)?;
        crate::util::check_output(p)?;
    }
    if a.sweep {
        return sweep(&a, noise);
    }
    if a.accuracy_report {
        return accuracy(&a);
    }
    let trials = a.trials.unwrap_or(1_000_000);
    if trials == 0 {
        bail!("--trials must be >= 1");
    }
    let mut cfg = McConfig::new(a.n_hwp, a.snr, a.p0, a.chi0.to_radians(), trials, noise);
    cfg.seed = a.seed;
    cfg.sky = a.sky;
    cfg.read_noise = a.read_noise;
    let engine = Engine::new(&cfg)?;
    let pool = pool(a.threads)?;
    check_budget(&cfg, trials, &pool, a.force)?;
    let prog = Progress::new(trials, !a.json);
    let t0 = Instant::now();
    let r = pool.install(|| engine.run(Some(&|n| prog.inc(n))));
    let secs = t0.elapsed().as_secs_f64();
    prog.finish();
    let rng_seconds = if a.rng_baseline {
        let t1 = Instant::now();
        let chk = pool.install(|| engine.draw_only());
        std::hint::black_box(chk);
        Some(t1.elapsed().as_secs_f64())
    } else {
        None
    };
    let out = RunOut {
        trials: r.trials,
        mean_p: r.mean_p,
        rms_p: r.rms_p,
        mode_p: r.mode_p,
        seconds: secs,
        trials_per_second: trials as f64 / secs,
        median_p: r.median_p,
        q16_p: r.q16_p,
        q84_p: r.q84_p,
        rejected: r.rejected,
        sigma_p_analytic: r.sigma_p_analytic,
        noise: noise.name().into(),
        n_hwp: a.n_hwp,
        snr: a.snr,
        p0: a.p0,
        chi0: a.chi0,
        seed: a.seed,
        threads: pool.current_num_threads(),
        rng_seconds,
        engine_over_rng: rng_seconds.map(|r| secs / r),
    };
    if a.json {
        return crate::util::print_json(&out);
    }
    let pc = |v: f64| format!("{:.5} %", 100.0 * v);
    let opc = |v: Option<f64>| v.map_or("n/a".into(), pc);
    outln!(
        "N = {}, SNR = {}, P0 = {}, chi0 = {} deg, noise {}, {} trials on {} threads",
        a.n_hwp,
        a.snr,
        pc(a.p0),
        a.chi0,
        noise,
        r.trials,
        out.threads
    );
    outln!("  mean P    {}", pc(r.mean_p));
    outln!("  mode P    {}", opc(r.mode_p));
    outln!("  median P  {}", opc(r.median_p));
    outln!("  sigma_P   {}   (eq:sigp: {})", pc(r.rms_p), pc(r.sigma_p_analytic));
    outln!("  68% band  [{}, {}]", opc(r.q16_p), opc(r.q84_p));
    if r.rejected > 0 {
        outln!("  {} trials dropped (no counts in both beams at some angle)", r.rejected);
    }
    outln!("  {:.3} s, {:.3e} trials/s", secs, out.trials_per_second);
    if let Some(rs) = rng_seconds {
        outln!("  drawing the random numbers alone: {:.3} s (engine / draws = {:.2})", rs, secs / rs);
    }
    Ok(())
}

#[derive(Serialize)]
struct SweepOut {
    n_hwp: usize,
    snr: f64,
    noise: String,
    #[serde(rename = "n_trials_per_point")]
    trials_per_point: u64,
    deltap: Vec<stokes::mc::sweep::DeltaPPoint>,
    bias: Vec<stokes::mc::sweep::BiasPoint>,
    fit_mc: Option<stokes::mc::sweep::LawFit>,
    fit_exact_rice: Option<stokes::mc::sweep::LawFit>,
    paper: (f64, f64),
    seconds: f64,
}

fn sweep(a: &Args, noise: Noise) -> Result<()> {
    let trials = a.trials.unwrap_or(400_000);
    let n = a.n_hwp;
    let k = (n as f64 / 2.0).sqrt();
    let (etas, snr_ps) = (deltap_etas(n, a.snr), bias_snr_ps());
    if trials == 0 {
        bail!("--trials must be >= 1");
    }
    let total = trials.saturating_mul((etas.len() + snr_ps.len()) as u64);
    let pool = pool(a.threads)?;
    // The sweep's points cost about what a single run of the same SNR does.
    let probe = McConfig::new(n, a.snr, 0.5 / a.snr.max(1.0), 0.5, 0, noise);
    check_budget(&probe, total, &pool, a.force)?;
    let prog = Progress::new(total, !a.json);
    let t0 = Instant::now();
    let cb = |x| prog.inc(x);
    let (dp, bs) = pool.install(|| -> Result<_> {
        let dp = deltap_sweep(n, a.snr, &etas, trials, noise, a.seed, None, Some(&cb))?;
        let bs = bias_sweep(n, a.snr, &snr_ps, trials, noise, a.seed, None, Some(&cb))?;
        Ok((dp, bs))
    })?;
    prog.finish();
    let fit_mc = fit_law_mc(&dp, LAW_FIT_FROM);
    let fit_exact = fit_law_exact(&law_a_values(), LAW_FIT_FROM);
    let out = SweepOut {
        n_hwp: n,
        snr: a.snr,
        noise: noise.name().into(),
        trials_per_point: trials,
        deltap: dp,
        bias: bs,
        fit_mc,
        fit_exact_rice: fit_exact,
        paper: (PAPER_C, PAPER_K),
        seconds: t0.elapsed().as_secs_f64(),
    };
    if let Some(path) = &a.plot {
        super::mc_plot::sweep_png(path, &out.deltap, &out.bias, n, a.snr)?;
    }
    if a.json {
        return crate::util::print_json(&out);
    }
    outln!("fig:deltap  N = {n}, SNR = {}, noise {}, {trials} trials per point (values x SNR)", a.snr, noise);
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
            p.sigma_p * a.snr,
            p.sigma_p_eq * a.snr,
            p.sigma_p_rice * a.snr,
            "",
            p.delta_mode.map_or(f64::NAN, |d| d * a.snr),
            p.delta_mode_rice * a.snr,
            p.delta_mean * a.snr,
            p.delta_mean_rice * a.snr
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
    Ok(())
}

#[derive(Serialize)]
struct AccuracyOut {
    precision: Vec<stokes::mc::budget::PrecisionRow>,
    observer: Vec<stokes::mc::budget::ObserverRow>,
    noise_modes: Vec<stokes::mc::budget::NoiseRow>,
    precision_config: String,
}

fn accuracy(a: &Args) -> Result<()> {
    let pool = pool(a.threads)?;
    let noise: Noise = a.noise.parse()?;
    let snr = a.snr;
    let p0 = 2.0 / snr; // eta = 2, where bias and sigma_P are comparable
    let mut base = McConfig::new(a.n_hwp, snr, p0.min(1.0), a.chi0.to_radians(), 0, noise);
    base.seed = a.seed;
    let tmax = a.trials.unwrap_or(1_000_000).max(1000);
    // 5 repeats of each decade up to tmax: about 5.6 tmax trials.
    check_budget(&base, tmax.saturating_mul(6), &pool, a.force)?;
    let mut trial_list = vec![];
    let mut t = 1000u64;
    while t <= tmax {
        trial_list.push(t);
        t *= 10;
    }
    let spin = Progress::new(0, !a.json);
    let (precision, observer, noise_modes) = pool.install(|| -> Result<_> {
        let p = precision_table(&base, &trial_list, 5, None)?;
        let o = observer_table(&[4, 8, 16], &[10.0, 30.0, 100.0, 300.0, 1000.0, 3000.0, 10000.0])?;
        let nm = noise_comparison(a.n_hwp, 2.0, &[3.0, 10.0, 30.0, 100.0, 300.0], tmax.min(200_000), a.seed, None)?;
        Ok((p, o, nm))
    })?;
    spin.finish();
    let out = AccuracyOut {
        precision,
        observer,
        noise_modes,
        precision_config: format!("N = {}, SNR = {snr}, P0 = {p0} (eta = 2), noise {noise}", a.n_hwp),
    };
    if let Some(path) = &a.plot {
        super::mc_plot::accuracy_png(path, &out.precision, &out.observer, &out.noise_modes, p0)?;
    }
    if a.json {
        return crate::util::print_json(&out);
    }
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
    outln!(
        "3. Fast noise modes against exact Poisson (N = {}, eta = P0 SNR = 2, {} trials)",
        a.n_hwp,
        tmax.min(200_000)
    );
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
    Ok(())
}
