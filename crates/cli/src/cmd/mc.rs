//! `instpol mc`: Monte Carlo of dual-beam polarimetry, the paper's section-mc reproductions
//! and the accuracy-against-time report.

use super::mc_table::{RunOut, SweepOut};
use anyhow::{bail, Context, Result};
use indicatif::{ProgressBar, ProgressDrawTarget, ProgressStyle};
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Instant;
use stokes::mc::budget::{accuracy_report, report_config, report_cost};
use stokes::mc::sweep::{
    bias_snr_ps, bias_sweep, deltap_etas, deltap_sweep, fit_law_exact, fit_law_mc, law_a_values, LAW_FIT_FROM, PAPER_C,
    PAPER_K,
};
use stokes::mc::{estimate_seconds, Engine, McConfig, Noise};

/// Monte Carlo of dual-beam linear polarimetry: draw the ordinary and extraordinary fluxes
/// at N half-wave-plate angles (theta_i = i x 22.5 deg), reduce each trial with the Stokes
/// solver and report the distribution of the measured P.
///
/// Noise models (--noise): poisson (exact photon counts, SNR^2 counts per angle, plus --sky
/// and --read-noise), gauss-f (Gaussian on each F_i, sigma_F = 1/SNR) and gauss-qu (Gaussian on
/// Q and U, sigma = 1/(sqrt(N/2) SNR), eq:sigp). SNR is that of the intensity f_O + f_E at each
/// angle. The same --seed gives the same result on any number of --threads.
///
/// Examples, one per mode:
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

/// Before a long run: time a short probe of the same configuration on the same pool, print the
/// estimated run time when it is over 10 s, and refuse beyond [`MAX_SECONDS`] unless `force`
/// (a `--trials 1e12` typo would otherwise run for hours without a word).
fn check_budget(cfg: &McConfig, total: u64, pool: &rayon::ThreadPool, force: bool) -> Result<()> {
    let Some((est, rate)) = pool.install(|| estimate_seconds(cfg, total))? else { return Ok(()) };
    if est > 10.0 {
        eprintln!(
            "note: {total} trials: estimated run time {} ({rate:.3e} trials/s on {} threads)",
            crate::util::human_seconds(est),
            pool.current_num_threads()
        );
    }
    if est > MAX_SECONDS && !force {
        bail!(
            "--trials {total}: estimated run time {} exceeds the {} limit; lower --trials, or pass --force to run it",
            crate::util::human_seconds(est),
            crate::util::human_seconds(MAX_SECONDS)
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
    let engine = Engine::new(&cfg).map_err(|e| match &e {
        stokes::stats::Error::Invalid { name, .. } => match mc_option(name) {
            Some(flag) => anyhow::anyhow!("{flag}: {e}"),
            None => e.into(),
        },
        _ => e.into(),
    })?;
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
    super::mc_table::print_run(&out);
    Ok(())
}

fn sweep(a: &Args, noise: Noise) -> Result<()> {
    let trials = a.trials.unwrap_or(400_000);
    let n = a.n_hwp;
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
    super::mc_table::print_sweep(&out);
    Ok(())
}

fn accuracy(a: &Args) -> Result<()> {
    let pool = pool(a.threads)?;
    let noise: Noise = a.noise.parse()?;
    let tmax = a.trials.unwrap_or(1_000_000).max(1000);
    let base = report_config(a.n_hwp, a.snr, a.chi0.to_radians(), noise, a.seed);
    check_budget(&base, report_cost(tmax), &pool, a.force)?;
    let spin = Progress::new(0, !a.json);
    let out = pool.install(|| accuracy_report(a.n_hwp, a.snr, a.chi0.to_radians(), noise, a.seed, tmax))?;
    spin.finish();
    let p0 = out.p0;
    if let Some(path) = &a.plot {
        super::mc_plot::accuracy_png(path, &out.precision, &out.observer, &out.noise_modes, p0)?;
    }
    if a.json {
        return crate::util::print_json(&out);
    }
    super::mc_table::print_accuracy(&out, a.n_hwp);
    Ok(())
}

/// The option that sets the Monte Carlo engine's input `name` (the names
/// `stokes::mc::Engine::new` refuses by), so that a refusal names what to change.
fn mc_option(name: &str) -> Option<&'static str> {
    Some(match name {
        "P0" => "--p0",
        "SNR" => "--snr",
        "number of HWP angles" => "--n-hwp",
        "chi0" => "--chi0",
        "sky" => "--sky",
        "read noise" => "--read-noise",
        _ => return None,
    })
}
