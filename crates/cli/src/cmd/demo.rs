//! `instpol demo`: the main job end to end on the paper's three empty fields.

use anyhow::{Context, Result};
use field::{FieldModel, GridMap, NearestCell, RadialPattern};
use fit::calfile::Calibration;
use fit::paper::DemoField;
use fit::pipeline::{CalibrateOptions, CalibrationRun, FitSummary};
use fit::wavelength::fit_wavelength_law;
use fit::RadialModel;
use serde::Serialize;
use std::path::{Path, PathBuf};
use std::sync::Arc;

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

#[derive(Serialize)]
struct FilterOut {
    filter: String,
    sky_p: f64,
    sky_chi_deg: f64,
    input_coefficients: Vec<f64>,
    fitted_coefficients: Vec<f64>,
    #[serde(rename = "sigma_fitted_coefficients")]
    fitted_errors: Vec<f64>,
    rms_residual: f64,
    polar_angle_slope: f64,
    #[serde(rename = "output")]
    calibration_file: String,
    #[serde(flatten)]
    extra: Extra,
}

#[derive(Serialize)]
struct Extra {
    #[serde(rename = "sigma_polar_angle_slope")]
    polar_angle_slope_err: f64,
    polar_angle_intercept_deg: f64,
    n_bins_used: usize,
    model: String,
    #[serde(skip_serializing_if = "Option::is_none")]
    #[serde(rename = "rms_residual_loo")]
    residual_loo_rms: Option<[f64; 2]>,
    #[serde(skip_serializing_if = "Option::is_none")]
    approx_vs_exact: Option<fit::pipeline::ApproxVsExact>,
    /// RMS over the field of (calibration - input field), per component (fraction).
    rms_vs_input: f64,
    #[serde(rename = "plot_outputs")]
    plots: Vec<String>,
}

#[derive(Serialize)]
struct Law {
    a: f64,
    b: f64,
    #[serde(rename = "sigma_a")]
    a_err: f64,
    #[serde(rename = "sigma_b")]
    b_err: f64,
    paper_a: f64,
    paper_b: f64,
}

#[derive(Serialize)]
struct Out {
    filters: Vec<FilterOut>,
    wavelength_law: Law,
    /// The V calibration validated on a simulated unpolarized standard near the lower-right
    /// corner (the paper's check, section sec:fors1): the `instpol validate` JSON.
    validation: crate::cmd::validate::ValidationReport,
    through_frames: bool,
    #[serde(rename = "output")]
    out_dir: String,
}

/// Frames for one case with the simulator, reduced to a Stokes map.
fn map_through_frames(
    c: &DemoField,
    inst: &instrument::Instrument,
    dir: &Path,
    seed: u64,
    bar: &indicatif::ProgressBar,
) -> Result<(skyfield::StokesMap, Vec<String>)> {
    let fdir = dir.join(format!("frames_{}", c.name));
    std::fs::create_dir_all(&fdir).with_context(|| format!("cannot create {}", fdir.display()))?;
    // The input field goes to the simulator as a model value.
    let field: Arc<dyn FieldModel> = if c.asymmetric {
        // The non-radial B field sampled on 16 x 16 px cells, each cell one M_I (the README's
        // demo numbers were made so).
        let (nx, ny) = (inst.detector.nx.div_ceil(16), inst.detector.ny.div_ceil(16));
        Arc::new(NearestCell(GridMap::sample(&c.truth(), &inst.field_coords().binned(16), nx, ny)))
    } else {
        // The radial pattern with the paper's coefficients (the list starts at r^0; the paper's
        // polynomial has no constant term).
        let coeffs = std::iter::once(0.0).chain(c.coeffs_pct.iter().copied()).map(|k| k / 100.0).collect();
        Arc::new(RadialPattern::new(coeffs, [0.0, 0.0]))
    };
    let scene = format!(
        "instrument = \"fors1\"\nfilter = \"{}\"\nseed = {}\n\n[sky]\nbrightness_e = 20000.0\np = {}\nchi_deg = {}\n\n\
         [effects]\nphoton_noise = true\nread_noise = true\n",
        c.name,
        seed,
        c.sky_p_pct / 100.0,
        c.sky_chi_deg,
    );
    let scene = sim::Scene::from_toml_str(&scene, Path::new("<demo scene>"))?;
    bar.set_message(format!("{}: simulating frames", c.name));
    let simd = sim::simulate_with_field(&scene, field, &fdir, &|| bar.inc(1))?;
    bar.set_message(format!("{}: reducing frames", c.name));
    let cfg = skyfield::reduce::ReduceConfig { bin_px: 30, ..Default::default() };
    let red = skyfield::reduce::reduce_files(&simd.frames, inst, &cfg, &|| bar.inc(1))?;
    let names = simd.frames.iter().map(|p| p.display().to_string()).collect();
    Ok((red.map, names))
}

/// A binned map measured directly through `M_I` with the noise of a 30 x 30 px bin.
fn map_direct(c: &DemoField, inst: &instrument::Instrument, seed: u64) -> Result<skyfield::StokesMap> {
    let d = &inst.detector;
    let geom = skyfield::BinGeometry::covering(30, 0, 0, d.nx, d.ny, d.pixel_scale_arcsec);
    let mut map = skyfield::StokesMap::empty(geom.clone(), &inst.name, c.name, vec![0.0, 22.5, 45.0, 67.5]);
    let centres: Vec<(f64, f64)> = (0..geom.len()).map(|k| geom.centre_arcmin(k % geom.nx, k / geom.nx)).collect();
    let sky = skyfield::solve::SkyPolarization::from_percent_deg(c.sky_p_pct, c.sky_chi_deg)?;
    let (q0, u0) = sky.qu();
    // SNR 280 per pixel, 4 HWP angles, 900 px: sigma of a bin mean ~ 1 / (280 sqrt(900)).
    let sigma = 1.0 / (280.0 * 30.0);
    let meas = fit::synth::sky_field(&centres, &c.truth(), q0, u0, sigma, seed);
    for (k, m) in meas.iter().enumerate() {
        map.q[k] = m.q1;
        map.u[k] = m.u1;
        map.sigma_q[k] = m.sigma;
        map.sigma_u[k] = m.sigma;
        map.cov_qu[k] = 0.0;
        map.valid[k] = true;
        map.n_pixels[k] = 900;
    }
    Ok(map)
}

/// RMS per component of (calibration - input) over the calibrated bins.
fn rms_vs_input(cal: &Calibration, c: &DemoField) -> f64 {
    let t = c.truth();
    let mut ss = 0.0;
    let mut n = 0;
    for b in cal.bins.iter().filter(|b| b.used) {
        if !cal.contains(b.x, b.y) {
            continue;
        }
        let v = cal.eval(b.x, b.y);
        let (q, u) = t.qu(b.x, b.y);
        ss += (v.q - q).powi(2) + (v.u - u).powi(2);
        n += 2;
    }
    (ss / n.max(1) as f64).sqrt()
}

pub fn run(a: Args) -> Result<()> {
    std::fs::create_dir_all(&a.out).with_context(|| format!("cannot create {}", a.out.display()))?;
    let inst = instrument::Instrument::load("fors1")?;
    let cases = fit::paper::demo_fields(&inst)?;
    let steps = if a.no_frames { 3 * 2 + 1 } else { 3 * (4 + 4 + 2) + 1 };
    let bar = crate::plot::progress(steps as u64, "starting", a.json);
    let mut outs = vec![];
    let mut runs: Vec<CalibrationRun> = vec![];
    for (k, c) in cases.iter().enumerate() {
        let seed = a.seed.wrapping_add(k as u64 * 7919);
        let (map, inputs) = if a.no_frames {
            (map_direct(c, &inst, seed)?, vec![])
        } else {
            map_through_frames(c, &inst, &a.out, seed, &bar)?
        };
        if !a.no_frames && !a.keep_frames {
            let _ = std::fs::remove_dir_all(a.out.join(format!("frames_{}", c.name)));
        }
        bar.set_message(format!("{}: sky-field solution and fit", c.name));
        let sky = skyfield::solve::SkyPolarization::from_percent_deg(c.sky_p_pct, c.sky_chi_deg)?;
        let opts = CalibrateOptions { residual_map: c.asymmetric, ..Default::default() };
        let run = crate::cmd::calibrate::calibrate_map(&map, &sky, &inst, inputs, &opts)?;
        bar.inc(1);
        let path = a.out.join(format!("cal_{}.fits", c.name));
        run.calibration.save(&path)?;
        bar.set_message(format!("{}: plots", c.name));
        let plots = crate::cmd::plot::plot_run(&a.out, c.name, &run)?;
        bar.inc(1);
        let s = FitSummary::new(&run);
        outs.push(FilterOut {
            filter: c.name.into(),
            sky_p: c.sky_p_pct / 100.0,
            sky_chi_deg: c.sky_chi_deg,
            input_coefficients: c.coeffs_pct.iter().map(|x| x / 100.0).collect(),
            fitted_coefficients: s.coefficients.clone(),
            fitted_errors: s.coefficient_errors.clone(),
            rms_residual: s.rms_residual,
            polar_angle_slope: s.polar_angle_slope,
            calibration_file: path.display().to_string(),
            extra: Extra {
                polar_angle_slope_err: s.polar_angle_slope_err,
                polar_angle_intercept_deg: s.polar_angle_intercept_deg,
                n_bins_used: s.n_bins_used,
                model: s.model.clone(),
                residual_loo_rms: s.residual_loo_rms,
                approx_vs_exact: s.approx_vs_exact,
                rms_vs_input: rms_vs_input(&run.calibration, c),
                plots: plots.iter().map(|p| p.display().to_string()).collect(),
            },
        });
        runs.push(run);
    }
    bar.set_message("V: validation on an unpolarized standard at the lower-right corner");
    let v = cases.iter().position(|c| c.name == "V").context("the demo has no V field")?;
    let mut v_true = vec![0.0];
    v_true.extend_from_slice(&cases[v].coeffs_pct);
    let star_dir = a.out.join("standard_V");
    let validation =
        crate::cmd::validate::demo_corner_star(&runs[v].calibration, &v_true, &star_dir, a.seed.wrapping_add(17))?;
    if !a.keep_frames {
        let _ = std::fs::remove_dir_all(&star_dir);
    }
    bar.inc(1);
    bar.finish_and_clear();
    let models: Vec<(f64, &RadialModel)> = runs.iter().map(|r| (r.calibration.lambda_nm, &r.fit.model)).collect();
    let law = fit_wavelength_law(&models, [1.0, 3.3])?;
    let out = Out {
        filters: outs,
        wavelength_law: Law {
            a: law.a,
            b: law.b,
            a_err: law.a_err,
            b_err: law.b_err,
            paper_a: fit::paper::RAYTRACED_LAW.0,
            paper_b: fit::paper::RAYTRACED_LAW.1,
        },
        validation,
        through_frames: !a.no_frames,
        out_dir: a.out.display().to_string(),
    };
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
            f.input_coefficients.iter().zip(&f.fitted_coefficients).zip(&f.fitted_errors).enumerate()
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
                    f.extra.polar_angle_slope_err,
                    100.0 * f.extra.rms_vs_input
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
        if let Some(l) = f.extra.residual_loo_rms {
            outln!(
                "    {} model {}: residual map leave-one-out RMS {:.4}% / {:.4}% (Q / U); the asymmetric component's azimuthal mean goes into the polynomial",
                f.filter, f.extra.model, 100.0 * l[0], 100.0 * l[1]
            );
        }
        if let Some(d) = &f.extra.approx_vs_exact {
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
        law.a, law.a_err, law.b, law.b_err
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
