//! `instpol demo`: the main job end to end on the paper's three empty fields.

use anyhow::Result;
use std::path::PathBuf;
use workflow::demo::{Demo, DemoOptions, Progress};

/// Simulate the paper's three empty fields (B, V, I with the sky polarization of Table
/// tab:empty), calibrate each filter, fit the wavelength law, and write the calibration files
/// and plots into a folder, with a table of recovered against input coefficients.
///
/// The instrumental fields are the paper's FORS1 patterns (section sec:fors1, percent):
/// V p(r) = 0.012 r + 0.046 r^2 + 0.002 r^3, I p(r) = -0.017 r + 0.105 r^2 - 0.006 r^3, and a
/// B band scaled from V by the paper's wavelength law with an added asymmetric component of up
/// to 0.5% (fit with a residual map). By default the fields go through the whole chain: frames
/// are simulated (sim crate, photon and read noise, SNR ~ 280 per pixel), written as FITS,
/// reduced in 30 x 30 px bins, solved for the instrumental field and fitted. --no-frames
/// measures binned maps directly through the same Mueller model (fast).
///
/// Example: instpol demo --out demo/
#[derive(clap::Args)]
pub struct Args {
    /// Output folder (created if missing).
    #[arg(long)]
    pub out: PathBuf,
    /// Skip the frames: measure 30 x 30 px binned maps directly with Gaussian noise.
    #[arg(long)]
    pub no_frames: bool,
    /// Keep the simulated frames (about 33 MB per filter) in OUT/frames_<filter>/.
    #[arg(long)]
    pub keep_frames: bool,
    /// Random seed.
    #[arg(long, default_value_t = 2006)]
    pub seed: u64,
    /// Print JSON instead of a table.
    #[arg(long)]
    pub json: bool,
}

pub fn run(a: Args) -> Result<()> {
    let opts = DemoOptions { through_frames: !a.no_frames, keep_frames: a.keep_frames, seed: a.seed };
    let bar = crate::plot::progress(workflow::demo::steps(&opts), "starting", a.json);
    let progress = |p: Progress<'_>| match p {
        Progress::Message(m) => bar.set_message(m.to_string()),
        Progress::Step => bar.inc(1),
    };
    let Demo { report: mut out, runs } = workflow::demo::run(&a.out, &opts, &progress)?;
    for (f, run) in out.filters.iter_mut().zip(&runs) {
        bar.set_message(format!("{}: plots", f.filter));
        let plots = crate::cmd::plot::plot_run(&a.out, &f.filter, run)?;
        f.plot_outputs = plots.iter().map(|p| p.display().to_string()).collect();
        bar.inc(1);
    }
    bar.finish_and_clear();
    for w in &out.validation.warnings {
        eprintln!("warning: {w}");
    }
    let law = out.wavelength_law;
    if a.json {
        return crate::util::print_json(&out);
    }
    outln!(
        "instpol demo: the paper's empty fields (Table tab:empty), FORS1, 30 x 30 px bins, {}",
        if a.no_frames { "binned maps measured directly" } else { "through simulated frames" }
    );
    outln!(
        "{:<3} {:>6} {:>7} {:>5} {:>9} {:>19} {:>9} {:>9} {:>14} {:>9}",
        "",
        "sky %",
        "chi",
        "k",
        "input %",
        "fitted % +- err",
        "pull",
        "rms %",
        "polar slope",
        "vs true %"
    );
    for f in &out.filters {
        for (i, ((inp, fit), err)) in
            f.input_coefficients.iter().zip(&f.fitted_coefficients).zip(&f.sigma_fitted_coefficients).enumerate()
        {
            let head = if i == 0 {
                format!("{:<3} {:>6.2} {:>7.1}", f.filter, 100.0 * f.sky_p, f.sky_chi_deg)
            } else {
                format!("{:<3} {:>6} {:>7}", "", "", "")
            };
            let tail = if i == 0 {
                format!(
                    "{:>9.4} {:>8.4}+-{:<5.4} {:>9.4}",
                    100.0 * f.rms_residual,
                    f.polar_angle_slope,
                    f.sigma_polar_angle_slope,
                    100.0 * f.rms_vs_input
                )
            } else {
                String::new()
            };
            outln!(
                "{head} {:>5} {:>9.4} {:>10.4}+-{:<7.4} {:>8.1} {tail}",
                i + 1,
                100.0 * inp,
                100.0 * fit,
                100.0 * err,
                (fit - inp) / err
            );
        }
        if let Some(l) = f.rms_residual_loo {
            outln!(
                "    {} model {}: residual map leave-one-out RMS {:.4}% / {:.4}% (Q / U); the asymmetric component's azimuthal mean goes into the polynomial",
                f.filter, f.model, 100.0 * l[0], 100.0 * l[1]
            );
        }
        if let Some(d) = &f.approx_vs_exact {
            outln!(
                "    {} eq:approx vs exact: max |dp| {:.4}%, max |dphi| {:.2} deg",
                f.filter,
                100.0 * d.max_dp,
                d.max_dphi_deg
            );
        }
    }
    outln!(
        "wavelength law p(l)/p(550) = {:.3} (+-{:.3}) + {:.3e} (+-{:.1e}) l[nm]   (paper's ray tracing: 0.02 + 1.73e-3 l)",
        law.a, law.sigma_a, law.b, law.sigma_b
    );
    let v = &out.validation.validation;
    outln!(
        "validation (sec:fors1): unpolarized standard at ({:.2}', {:.2}') in V: measured P = {:.3} +- {:.3} % at {:.1} deg, \
         predicted {:.3} % at {:.1} deg: {:.2} sigma, {}   (paper: 0.92 +- 0.04 % at -48 deg measured, 0.96 % at -51.9 deg predicted)",
        out.validation.x_arcmin,
        out.validation.y_arcmin,
        100.0 * v.measured_p,
        100.0 * v.sigma_p,
        v.measured_chi_deg,
        100.0 * v.predicted_p,
        v.predicted_chi_deg,
        v.residual_sigma,
        if v.pass { "PASS" } else { "FAIL" }
    );
    outln!("wrote calibration files and plots to {}", a.out.display());
    Ok(())
}
