//! `instpol calibrate`: empty-field frames of known sky polarization to a calibration file.

use anyhow::{anyhow, bail, Context, Result};
use fit::models::pipeline::{CalibrateOptions, CalibrationRun, FitSummary};
use fit::models::radial::Robust;
use fit::RadialFitOptions;
use skyfield::solve::SkyPolarization;
use std::path::{Path, PathBuf};

/// Measure the instrumental polarization over the field from frames of an empty field whose
/// sky polarization is known (section sec:instr of Patat & Romaniello 2006), fit the radial
/// model p(r) = sum c_k r^k (r in arcmin, p a fraction) with its centre, run the polar-angle
/// test, and write a calibration file (multi-extension FITS) for the filter.
///
/// The frames are reduced in bins of --bin px (sigma-clipped), the sky-field equations are
/// solved exactly (eq:instpol) in each bin (the approximate eq:approx solution is kept for
/// comparison), and the bins' instrumental (Q/I, U/I) are fitted by robust weighted least
/// squares.
///
/// Example: instpol calibrate v_*.fits --sky-p 1.74 --sky-chi -53.8 --exclude sector:10:80
/// --out cal_V.fits
#[derive(clap::Args)]
pub struct Args {
    /// Frames of one filter at a complete set of HWP angles (FITS, as the instrument writes
    /// them).
    pub frames: Vec<PathBuf>,
    /// A Stokes map (FITS written by instpol) to use instead of frames.
    #[arg(long, conflicts_with = "frames")]
    pub map: Option<PathBuf>,
    /// Built-in instrument name or instrument TOML file.
    /// Default: the built-in instrument the first file's INSTRUME keyword names (said on
    /// stderr); a file without one, or of no built-in instrument, is refused.
    #[arg(long)]
    pub instrument: Option<String>,
    /// Sky polarization degree in PERCENT (Table tab:empty: B 6.45, V 1.74, I 1.34), not a
    /// fraction; a value below 0.1 draws a warning. Required.
    #[arg(long)]
    pub sky_p: Option<f64>,
    /// Sky polarization angle in degrees (any sign, taken modulo 180). Required.
    #[arg(long, allow_hyphen_values = true)]
    pub sky_chi: Option<f64>,
    #[command(flatten)]
    pub fit: FitArgs,
    /// Bin side in detector pixels (the paper: 30).
    #[arg(long, default_value_t = workflow::steps::DEFAULT_BIN_PX)]
    pub bin: usize,
    /// Output calibration file (FITS).
    #[arg(long)]
    pub out: PathBuf,
    /// Also draw the map, profile and residual plots (PNG and SVG) into this folder.
    #[arg(long)]
    pub plots: Option<PathBuf>,
    /// Print JSON instead of a table.
    #[arg(long)]
    pub json: bool,
    #[command(flatten)]
    pub frame: crate::cmd::frame_opts::FrameOpts,
}

/// Fit options shared by `calibrate` and `fit`.
#[derive(clap::Args, Clone)]
pub struct FitArgs {
    /// Model: radialN, a polynomial of degree N in r about the optical axis (default radial3,
    /// as the paper); polyN, a polynomial of total degree N (1 to 3) in x and y for each of q
    /// and u, for a field without an optical axis; plane, the same as poly1.
    #[arg(long, default_value = "radial3")]
    pub model: String,
    /// Fit a constant term c_0 too (the paper assumes p = 0 on the axis: no c_0).
    #[arg(long)]
    pub include_c0: bool,
    /// Fit the optical-axis centre instead of fixing it at the detector centre.
    #[arg(long)]
    pub free_centre: bool,
    /// Leave part of the field out; repeatable. sector:FROM:TO (polar angle, deg,
    /// counter-clockwise from +x, e.g. sector:10:80 as the paper's V band) and ring:R0:R1
    /// (arcmin) are measured about the model's optical-axis centre (with --free-centre: about
    /// the fitted centre, refitting until the excluded bins settle); box:X0:X1:Y0:Y1 is in
    /// arcmin from the detector centre.
    #[arg(long)]
    pub exclude: Vec<String>,
    /// Keep a natural-neighbour interpolant of the residuals in the model (for fields that are
    /// not radial, e.g. the B band).
    #[arg(long)]
    pub residual_map: bool,
    /// Robust loss: huber (default), cauchy or none.
    #[arg(long, default_value = "huber")]
    pub robust: String,
    /// How the parameter errors use the fit's reduced chi^2: conservative (default) multiplies
    /// the covariance by max(1, chi2_red), so errors grow when the bins scatter more than their
    /// errors say but never shrink below what those errors allow (chi2_red < 1 usually means
    /// correlated or overstated errors, e.g. smoothed maps); scaled always multiplies by
    /// chi2_red (scipy curve_fit's absolute_sigma=False); absolute trusts the bins' errors.
    /// Recorded in the calibration file (HIERARCH IP ERR SCALING) and the JSON.
    #[arg(long, default_value = "conservative", value_name = "MODE")]
    pub error_scaling: String,
    /// Also inflate the errors for correlated bin errors (smoothed maps such as the FORS2 INLA
    /// maps): the covariance is multiplied by tau, the sum of the residuals' autocorrelation
    /// over neighbouring bins (bins per independent one). Needs bins on a regular grid.
    #[arg(long)]
    pub correlated_errors: bool,
}

impl FitArgs {
    pub fn options(&self) -> Result<CalibrateOptions> {
        let mut fo =
            RadialFitOptions { include_c0: self.include_c0, free_centre: self.free_centre, ..Default::default() };
        for e in &self.exclude {
            fo.exclusions.push(e.parse()?);
        }
        fo.robust = self.robust.parse::<Robust>().map_err(|_| {
            anyhow!("unknown --robust '{}': use huber, cauchy or none", self.robust.to_ascii_lowercase())
        })?;
        fo.error_scaling = self.error_scaling.parse().context("--error-scaling")?;
        fo.correlated_errors = self.correlated_errors;
        let mut opts = CalibrateOptions { fit: fo, residual_map: self.residual_map, ..Default::default() };
        opts.set_model_name(&self.model)?;
        Ok(opts)
    }
}

/// The sky values are required: without them the sky-field equations have no solution.
pub fn sky_from_args(p: Option<f64>, chi: Option<f64>) -> Result<SkyPolarization> {
    match (p, chi) {
        (Some(p), Some(c)) => {
            // Other commands and the scene files take fractions: 0.0174 here is 0.0174 %, a sky
            // so weakly polarized that the fit would measure noise. Say so loudly.
            if p > 0.0 && p < 0.1 {
                eprintln!(
                    "warning: --sky-p {p} is in PERCENT: a sky polarization of {p} % = {:.2e} (fraction). \
                     If you meant the fraction {p} (= {:.2} %), give --sky-p {:.2}",
                    p / 100.0,
                    100.0 * p,
                    100.0 * p
                );
            }
            Ok(SkyPolarization::from_percent_deg(p, c)?)
        }
        _ => bail!(
            "the sky polarization is required: give --sky-p PERCENT and --sky-chi DEG (the sky-field method \
             needs the field's own polarization, e.g. from Table tab:empty: V 1.74 -53.8)"
        ),
    }
}

/// A human-readable table of a fit.
pub fn print_table(s: &FitSummary) {
    outln!("filter {}  model {}  bins used {} of {}", s.filter, s.model, s.n_bins_used, s.n_bins);
    out!(
        "centre ({:.4} +- {:.4}, {:.4} +- {:.4}) arcmin",
        s.centre_arcmin[0],
        s.centre_errors_arcmin[0],
        s.centre_arcmin[1],
        s.centre_errors_arcmin[1]
    );
    match s.centre_px {
        Some(c) => outln!("  = pixel ({:.1}, {:.1}){}", c[0], c[1], if s.centre_free { "" } else { "  (fixed)" }),
        None => outln!(),
    }
    if s.poly.is_some() {
        outln!("radial fit of the same bins (the polar-angle test's centre):");
    }
    outln!("{:>6} {:>14} {:>12}", "power", "c_k (%)", "error (%)");
    for ((k, c), e) in s.powers.iter().zip(&s.coefficients).zip(&s.coefficient_errors) {
        outln!("{:>6} {:>14.5} {:>12.5}", k, 100.0 * c, 100.0 * e);
    }
    if let Some(p) = &s.poly {
        outln!("stored model: a polynomial of degree {} in x, y (arcmin)", p.degree);
        outln!("{:>8} {:>12} {:>10} {:>12} {:>10}", "term", "q (%)", "error", "u (%)", "error");
        for (k, [i, j]) in p.powers.iter().enumerate() {
            outln!(
                "{:>8} {:>12.5} {:>10.5} {:>12.5} {:>10.5}",
                format!("x^{i} y^{j}"),
                100.0 * p.q[k],
                100.0 * p.sigma_q[k],
                100.0 * p.u[k],
                100.0 * p.sigma_u[k]
            );
        }
    }
    outln!("RMS residual {:.4}% (per component)   reduced chi2 {:.2}", 100.0 * s.rms_residual, s.chi2_reduced);
    outln!(
        "errors: covariance x {:.3} ({}{})",
        s.covariance_scale,
        s.error_scaling,
        if s.correlation.is_some() { ", with the correlated-errors inflation" } else { "" }
    );
    if !s.polar_angle_slope.is_finite() {
        outln!(
            "polar-angle test: undefined: no bin has a polarization angle (P = 0 everywhere; against noise p = {:.3})",
            s.polar_angle_noise_p
        );
    } else if s.polar_angle_pattern {
        outln!(
            "polar-angle test: slope {:.4} +- {:.4}, intercept {:.2} +- {:.2} deg (pattern against noise: p = {:.2e}, radial component {:+.1} sigma)",
            s.polar_angle_slope,
            s.polar_angle_slope_err,
            s.polar_angle_intercept_deg,
            s.polar_angle_intercept_err_deg,
            s.polar_angle_noise_p,
            s.polar_angle_radial_z
        );
    } else {
        outln!(
            "polar-angle test: no radial pattern: the bins are consistent with noise (p = {:.3}, radial component {:+.1} sigma); the line fit (slope {:.4}) describes noise",
            s.polar_angle_noise_p, s.polar_angle_radial_z, s.polar_angle_slope
        );
    }
    if let Some(a) = &s.approx_vs_exact {
        outln!(
            "eq:approx vs exact: max |dp| {:.5}%, rms {:.5}%, max |dphi| {:.3} deg",
            100.0 * a.max_dp,
            100.0 * a.rms_dp,
            a.max_dphi_deg
        );
    }
    if let Some(l) = s.residual_loo_rms {
        outln!("residual map: leave-one-out RMS {:.4}% (Q), {:.4}% (U)", 100.0 * l[0], 100.0 * l[1]);
    }
}

pub fn run(a: Args) -> Result<()> {
    // The options first: a missing --sky-p is said before any file is opened.
    let sky = sky_from_args(a.sky_p, a.sky_chi)?;
    let opts = a.fit.options()?;
    let first = a.frames.first().map(|p| p.as_path()).or(a.map.as_deref());
    let instrument = crate::util::instrument_of(&a.instrument, first)?;
    crate::util::inputs(
        a.frames.iter().map(|p| p.as_path()).chain(a.map.as_deref()).chain(crate::util::file_arg(&instrument)),
    )?;
    crate::util::check_output(&a.out)?;
    let inst = instrument::Instrument::load(&instrument)?;
    crate::util::check_bin(a.bin, &inst)?;
    let (map, inputs) = if let Some(m) = &a.map {
        // A map is reduced already: options that read frames would be ignored without a word.
        if let Some(opt) = a.frame.first_given() {
            bail!("{opt} applies to frames, not to --map {}: the map is reduced already", m.display());
        }
        (
            skyfield::StokesMap::read_uncorrected(m)
                .with_context(|| format!("cannot read Stokes map {}", m.display()))?,
            vec![m.display().to_string()],
        )
    } else {
        if a.frames.is_empty() {
            bail!("no frames given: list the FITS frames of one filter (or give --map MAP.fits)");
        }
        let bar = crate::plot::progress(a.frames.len() as u64, "reading frames", a.json);
        let cfg = skyfield::reduce::ReduceConfig { bin_px: a.bin, ..Default::default() };
        let read = a.frame.read_options()?;
        let red = skyfield::reduce::reduce_files_with(&a.frames, &inst, &cfg, &read, &|| bar.inc(1))?;
        bar.finish_and_clear();
        for w in &red.warnings {
            eprintln!("warning: {w}");
        }
        (red.map, a.frames.iter().map(|p| p.display().to_string()).collect())
    };
    // The one step (workflow::steps::calibrate_read_map); `finish` saves it beside its plots.
    let (run, warning) = workflow::steps::calibrate_read_map(&map, inputs, &sky, &inst, &opts, None)?;
    if let Some(w) = warning {
        eprintln!("warning: {w}");
    }
    finish(&run, Some(&a.out), a.plots.as_deref(), a.json)
}

/// Save the calibration (when `out` is given) and draw the plots into `plots`: the file's name
/// and the plots drawn. The plots folder is made first: a run that cannot write its plots fails
/// before it saves anything.
pub fn save_and_plot(
    run: &CalibrationRun,
    out: Option<&Path>,
    plots: Option<&Path>,
) -> Result<(Option<String>, Vec<String>)> {
    if let Some(dir) = plots {
        std::fs::create_dir_all(dir).with_context(|| format!("cannot create the plots folder {}", dir.display()))?;
    }
    let mut file = None;
    if let Some(out) = out {
        run.calibration.save(out)?;
        file = Some(out.display().to_string());
    }
    let mut drawn = vec![];
    if let Some(dir) = plots {
        let files = crate::cmd::plot::plot_run(dir, &run.calibration.filter, run)?;
        drawn = files.iter().map(|p| p.display().to_string()).collect();
    }
    Ok((file, drawn))
}

/// The end of `calibrate` and `fit`: save the calibration (when `out` is given), draw the plots
/// into `plots`, and print the fit summary as JSON or as a table.
pub fn finish(run: &CalibrationRun, out: Option<&Path>, plots: Option<&Path>, json: bool) -> Result<()> {
    let mut s = FitSummary::new(run);
    // A fit whose residuals are far from its errors is a wrong model or wrong errors (e.g. an
    // extreme Wollaston imbalance gave chi2_red = 1e9): the numbers still come, with a warning.
    if !(s.chi2_reduced >= 0.1 && s.chi2_reduced <= 10.0) {
        eprintln!(
            "warning: reduced chi^2 of the {} fit is {:.3e}, far from 1: the model or the errors do not describe \
             the bins (errors scaled: {}; check the model, the frames, the sky polarization and the Wollaston balance)",
            if s.poly.is_some() { "polynomial" } else { "radial" },
            s.chi2_reduced,
            s.error_scaling
        );
    }
    if !s.polar_angle_pattern && s.polar_angle_slope.is_finite() {
        eprintln!(
            "warning: polar-angle test: no radial pattern (the bins are consistent with noise, p = {:.3})",
            s.polar_angle_noise_p
        );
    }
    (s.calibration_file, s.plot_outputs) = save_and_plot(run, out, plots)?;
    if json {
        crate::util::print_json(&s)
    } else {
        print_table(&s);
        if let Some(out) = out {
            outln!("wrote {}", out.display());
        }
        Ok(())
    }
}
