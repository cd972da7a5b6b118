//! The main job end to end on the paper's three empty fields, as a library workflow: what
//! `instpol demo` and the Python `instpol.demo` run and report.
//!
//! The paper's FORS1 patterns (section `sec:fors1`: V and I as fitted there, B the V pattern
//! scaled by the ray-traced wavelength law with an asymmetric component, [`fit::models::paper`]) are
//! seen on the empty fields of Table `tab:empty`, either through simulated frames (the `sim`
//! crate: photon and read noise, written as FITS and reduced by `skyfield` in 30 x 30 px
//! bins) or as binned maps measured directly through the same `M_I` ([`fit::models::synth`]); each
//! filter is calibrated by the sky-field method ([`fit::models::pipeline::calibrate_sky_field`]),
//! the wavelength law is fitted to the three models ([`fit::models::wavelength`]), and the V
//! calibration is validated on a simulated unpolarized standard in the lower-right corner
//! ([`corner_star`]), as the paper checks its V map. Scenes are built as `sim::Scene` values.
//! Plots are the faces' (the report lists the files a face drew, none here).

use field::{FieldModel, GridMap, NearestCell, RadialPattern};
use fit::files::calfile::Calibration;
use fit::models::paper::DemoField;
use fit::models::pipeline::{ApproxVsExact, CalibrateOptions, CalibrationRun, FitSummary};
use fit::standards::Expected;
use fit::validate::{ValidateOptions, ValidationReport};
use fit::RadialModel;
use serde::Serialize;
use std::path::{Path, PathBuf};
use std::sync::Arc;

/// Why the demo stopped; each names the step or file.
#[derive(Debug, thiserror::Error)]
pub enum Error {
    #[error("cannot create {}: {err}", path.display())]
    Create { path: PathBuf, err: std::io::Error },
    #[error(transparent)]
    Instrument(#[from] instrument::Error),
    #[error(transparent)]
    Scene(#[from] sim::Error),
    #[error("simulating the standard star")]
    Standard(#[source] sim::Error),
    #[error(transparent)]
    Frames(#[from] skyfield::Error),
    #[error(transparent)]
    Fit(#[from] fit::Error),
    #[error(transparent)]
    Validate(#[from] fit::validate::Error),
    #[error("the demo has no V field")]
    NoV,
}

/// How the demo runs.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct DemoOptions {
    /// Through simulated frames (the whole chain); else binned maps measured directly.
    pub through_frames: bool,
    /// Keep the simulated frames in `OUT/frames_<filter>/` and `OUT/standard_V/`.
    pub keep_frames: bool,
    /// Random seed: filter `k` is simulated with `seed + 7919 k`, the standard with `seed + 17`.
    pub seed: u64,
}

impl Default for DemoOptions {
    fn default() -> Self {
        Self { through_frames: true, keep_frames: false, seed: 2006 }
    }
}

/// What the demo is doing, for a face's progress display.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Progress<'a> {
    /// The step now running.
    Message(&'a str),
    /// One unit of work done: [`steps`] of them in all, less one per filter for the plots the
    /// face draws itself.
    Step,
}

/// Units of work ([`Progress::Step`]) of a demo, counting one plot step per filter that the
/// face adds: 3 filters of (4 frames written, 4 read, the fit, the plots) or, without frames,
/// (the fit, the plots), and the validation.
pub fn steps(opts: &DemoOptions) -> u64 {
    if opts.through_frames {
        3 * (4 + 4 + 2) + 1
    } else {
        3 * 2 + 1
    }
}

/// One filter of the report.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct FilterReport {
    pub filter: String,
    pub sky_p: f64,
    pub sky_chi_deg: f64,
    /// The input polynomial (powers 1, 2, 3 of r; fractions).
    pub input_coefficients: Vec<f64>,
    pub fitted_coefficients: Vec<f64>,
    pub sigma_fitted_coefficients: Vec<f64>,
    pub rms_residual: f64,
    pub polar_angle_slope: f64,
    /// The calibration file written.
    pub output: String,
    pub sigma_polar_angle_slope: f64,
    pub polar_angle_intercept_deg: f64,
    pub n_bins_used: usize,
    pub model: String,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub rms_residual_loo: Option<[f64; 2]>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub approx_vs_exact: Option<ApproxVsExact>,
    /// RMS over the field of (calibration - input field), per component (fraction).
    pub rms_vs_input: f64,
    /// The plots a face drew of this filter's run (none from the library).
    pub plot_outputs: Vec<String>,
}

/// The wavelength law fitted to the three filters' models, beside the paper's ray tracing.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct LawReport {
    pub a: f64,
    pub b: f64,
    pub sigma_a: f64,
    pub sigma_b: f64,
    pub paper_a: f64,
    pub paper_b: f64,
}

/// The demo's report (`instpol demo --json`).
#[derive(Debug, Clone, Serialize)]
pub struct DemoReport {
    pub filters: Vec<FilterReport>,
    pub wavelength_law: LawReport,
    /// The V calibration validated on a simulated unpolarized standard near the lower-right
    /// corner (the paper's check, section sec:fors1): the `instpol validate` JSON.
    pub validation: ValidationReport,
    pub through_frames: bool,
    /// The output folder.
    pub output: String,
}

/// The demo's report and each filter's calibration run (B, V, I), for the faces' plots.
pub struct Demo {
    pub report: DemoReport,
    pub runs: Vec<CalibrationRun>,
}

/// Frames of one field simulated (the input field handed to the simulator as a model value,
/// the scene built as a value) into `dir/frames_<filter>`, reduced to a Stokes map in 30 x 30 px
/// bins; the map and the frames' names.
fn map_through_frames(
    c: &DemoField,
    inst: &instrument::Instrument,
    dir: &Path,
    seed: u64,
    progress: &(dyn Fn(Progress<'_>) + Sync),
) -> Result<(skyfield::StokesMap, Vec<String>), Error> {
    let fdir = dir.join(format!("frames_{}", c.name));
    std::fs::create_dir_all(&fdir).map_err(|err| Error::Create { path: fdir.clone(), err })?;
    let field: Arc<dyn FieldModel> = if c.asymmetric {
        // The non-radial B field sampled on 16 x 16 px cells, each cell one M_I (the demo's
        // demo numbers were made so).
        let (nx, ny) = (inst.detector.nx.div_ceil(16), inst.detector.ny.div_ceil(16));
        Arc::new(NearestCell(GridMap::sample(&c.truth(), &inst.field_coords().binned(16), nx, ny)))
    } else {
        // The radial pattern with the paper's coefficients (the list starts at r^0; the paper's
        // polynomial has no constant term).
        let coeffs = std::iter::once(0.0).chain(c.coeffs_pct.iter().copied()).map(|k| k / 100.0).collect();
        Arc::new(RadialPattern::new(coeffs, [0.0, 0.0]))
    };
    let scene = sim::Scene {
        instrument: "fors1".into(),
        filter: c.name.into(),
        hwp_angles_deg: sim::scene::default_angles(),
        exposure_s: 1.0,
        seed,
        output: sim::scene::Output::default(),
        sky: Some(sim::scene::Sky {
            brightness_e: 20000.0,
            p: c.sky_p_pct / 100.0,
            chi_deg: c.sky_chi_deg,
            v: 0.0,
            gradient_e_per_arcmin: None,
        }),
        stars: vec![],
        extended: vec![],
        effects: sim::scene::Effects { photon_noise: true, read_noise: true, ..Default::default() },
        frame_shifts_px: vec![],
        telescope: None,
        hwp_motion: None,
        sky_pa_deg: None,
    }
    .checked(Path::new("<demo scene>"))?;
    progress(Progress::Message(&format!("{}: simulating frames", c.name)));
    let simd = sim::simulate_with_field(&scene, field, &fdir, &|| progress(Progress::Step))?;
    progress(Progress::Message(&format!("{}: reducing frames", c.name)));
    let cfg = skyfield::reduce::ReduceConfig { bin_px: 30, ..Default::default() };
    let red = skyfield::reduce::reduce_files(&simd.frames, inst, &cfg, &|| progress(Progress::Step))?;
    let names = simd.frames.iter().map(|p| p.display().to_string()).collect();
    Ok((red.map, names))
}

/// A binned map measured directly through `M_I` with the noise of a 30 x 30 px bin.
fn map_direct(c: &DemoField, inst: &instrument::Instrument, seed: u64) -> Result<skyfield::StokesMap, Error> {
    let d = &inst.detector;
    let geom = skyfield::BinGeometry::covering(30, 0, 0, d.nx, d.ny, d.pixel_scale_arcsec);
    let mut map = skyfield::StokesMap::empty(geom.clone(), &inst.name, c.name, vec![0.0, 22.5, 45.0, 67.5]);
    let centres: Vec<(f64, f64)> = (0..geom.len()).map(|k| geom.centre_arcmin(k % geom.nx, k / geom.nx)).collect();
    let sky = skyfield::solve::SkyPolarization::from_percent_deg(c.sky_p_pct, c.sky_chi_deg)?;
    let (q0, u0) = sky.qu();
    // SNR 280 per pixel, 4 HWP angles, 900 px: sigma of a bin mean ~ 1 / (280 sqrt(900)).
    let sigma = 1.0 / (280.0 * 30.0);
    let meas = fit::models::synth::sky_field(&centres, &c.truth(), q0, u0, sigma, seed);
    for (k, m) in meas.iter().enumerate() {
        map.q[k] = m.qu.q;
        map.u[k] = m.qu.u;
        map.sigma_q[k] = m.qu.sigma_q();
        map.sigma_u[k] = m.qu.sigma_u();
        map.cov_qu[k] = m.qu.cov_qu;
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

/// Run the demo into the folder `out` (created if missing): simulate the paper's three empty
/// fields (B, V, I with the sky polarization of Table `tab:empty`), calibrate each filter
/// (calibration files `out/cal_<filter>.fits`; the B field with a residual map), fit the
/// wavelength law over r = 1..3.3', and validate the V calibration on the corner standard
/// ([`corner_star`]). Simulated frames are removed unless `opts.keep_frames`. `progress` hears
/// of each step.
pub fn run(out: &Path, opts: &DemoOptions, progress: &(dyn Fn(Progress<'_>) + Sync)) -> Result<Demo, Error> {
    std::fs::create_dir_all(out).map_err(|err| Error::Create { path: out.to_path_buf(), err })?;
    let inst = instrument::Instrument::load("fors1")?;
    let cases = fit::models::paper::demo_fields(&inst)?;
    let mut filters = vec![];
    let mut runs: Vec<CalibrationRun> = vec![];
    for (k, c) in cases.iter().enumerate() {
        let seed = opts.seed.wrapping_add(k as u64 * 7919);
        let (map, inputs) = if opts.through_frames {
            map_through_frames(c, &inst, out, seed, progress)?
        } else {
            (map_direct(c, &inst, seed)?, vec![])
        };
        if opts.through_frames && !opts.keep_frames {
            let _ = std::fs::remove_dir_all(out.join(format!("frames_{}", c.name)));
        }
        progress(Progress::Message(&format!("{}: sky-field solution and fit", c.name)));
        let sky = skyfield::solve::SkyPolarization::from_percent_deg(c.sky_p_pct, c.sky_chi_deg)?;
        let copts = CalibrateOptions { residual_map: c.asymmetric, ..Default::default() };
        let run = fit::models::pipeline::calibrate_sky_field(&map, &sky, &inst, inputs, &copts)?;
        progress(Progress::Step);
        let path = out.join(format!("cal_{}.fits", c.name));
        run.calibration.save(&path)?;
        let s = FitSummary::new(&run);
        filters.push(FilterReport {
            filter: c.name.into(),
            sky_p: c.sky_p_pct / 100.0,
            sky_chi_deg: c.sky_chi_deg,
            input_coefficients: c.coeffs_pct.iter().map(|x| x / 100.0).collect(),
            fitted_coefficients: s.coefficients.clone(),
            sigma_fitted_coefficients: s.coefficient_errors.clone(),
            rms_residual: s.rms_residual,
            polar_angle_slope: s.polar_angle_slope,
            output: path.display().to_string(),
            sigma_polar_angle_slope: s.polar_angle_slope_err,
            polar_angle_intercept_deg: s.polar_angle_intercept_deg,
            n_bins_used: s.n_bins_used,
            model: s.model.clone(),
            rms_residual_loo: s.residual_loo_rms,
            approx_vs_exact: s.approx_vs_exact,
            rms_vs_input: rms_vs_input(&run.calibration, c),
            plot_outputs: vec![],
        });
        runs.push(run);
    }
    progress(Progress::Message("V: validation on an unpolarized standard at the lower-right corner"));
    let v = cases.iter().position(|c| c.name == "V").ok_or(Error::NoV)?;
    let mut v_true = vec![0.0];
    v_true.extend_from_slice(&cases[v].coeffs_pct);
    let star_dir = out.join("standard_V");
    let validation = corner_star(&runs[v].calibration, &v_true, &star_dir, opts.seed.wrapping_add(17))?;
    if !opts.keep_frames {
        let _ = std::fs::remove_dir_all(&star_dir);
    }
    progress(Progress::Step);
    let models: Vec<(f64, &RadialModel)> = runs.iter().map(|r| (r.calibration.lambda_nm, &r.fit.model)).collect();
    let law = fit::models::wavelength::fit_wavelength_law(&models, [1.0, 3.3])?;
    let report = DemoReport {
        filters,
        wavelength_law: LawReport {
            a: law.a,
            b: law.b,
            sigma_a: law.a_err,
            sigma_b: law.b_err,
            paper_a: fit::models::paper::RAYTRACED_LAW.0,
            paper_b: fit::models::paper::RAYTRACED_LAW.1,
        },
        validation,
        through_frames: opts.through_frames,
        output: out.display().to_string(),
    };
    Ok(Demo { report, runs })
}

/// The demo's validation step, as the paper did it (section `sec:fors1`): simulate (photon and
/// read noise, saturation) frames of an unpolarized standard of the paper's precision (3e6 e-
/// per exposure, sigma_P ~ 0.04%) at [`fit::models::paper::corner_position_arcmin`] seen through
/// the true V field `true_coeffs_percent` (index = power of r, as in a scene file), write them
/// into `dir`, and validate the calibration `cal` on them
/// ([`fit::validate::validate_frames`], default options; its warnings are in the report).
pub fn corner_star(
    cal: &Calibration,
    true_coeffs_percent: &[f64],
    dir: &Path,
    seed: u64,
) -> Result<ValidationReport, Error> {
    use sim::scene::{Coords, Effects, InstPolSpec, Output, Psf, Sky, Star};
    let (x, y) = fit::models::paper::corner_position_arcmin();
    let scene = sim::Scene {
        instrument: "fors1".into(),
        filter: "V".into(),
        hwp_angles_deg: vec![0.0, 22.5, 45.0, 67.5],
        exposure_s: 1.0,
        seed,
        output: Output { bitpix: -32, prefix: "standard".into(), ..Default::default() },
        sky: Some(Sky { brightness_e: 200.0, p: 0.0, chi_deg: 0.0, v: 0.0, gradient_e_per_arcmin: None }),
        stars: vec![Star {
            x,
            y,
            coords: Coords::Arcmin,
            flux_e: 3e6,
            p: 0.0,
            chi_deg: 0.0,
            v: 0.0,
            fwhm_arcsec: 1.4,
            psf: Psf::Gaussian,
            moffat_beta: sim::scene::DEFAULT_MOFFAT_BETA,
        }],
        extended: vec![],
        effects: Effects {
            photon_noise: true,
            read_noise: true,
            saturation: true,
            instpol: Some(InstPolSpec::Radial {
                coeffs_percent: true_coeffs_percent.to_vec(),
                centre_arcmin: [0.0, 0.0],
                phi_offset_deg: 0.0,
            }),
            ..Default::default()
        },
        frame_shifts_px: vec![],
        telescope: None,
        hwp_motion: None,
        sky_pa_deg: None,
    };
    std::fs::create_dir_all(dir).map_err(|err| Error::Create { path: dir.to_path_buf(), err })?;
    let sc = scene.checked(&dir.join("standard.toml"))?;
    let out = sim::simulate(&sc, dir, &|| {}).map_err(Error::Standard)?;
    let inst = instrument::Instrument::load("fors1")?;
    let (x_px, y_px) = inst.arcmin_to_pixel(x, y);
    Ok(fit::validate::validate_frames(
        cal,
        &inst,
        &out.frames,
        x_px,
        y_px,
        ("unpolarized", Expected::ZERO),
        &ValidateOptions::default(),
    )?)
}

#[cfg(test)]
mod tests {
    use super::*;
    use fit::files::calfile::{PixelGrid, Provenance, FORMAT_VERSION};
    use fit::FieldRegion;

    fn cal(filter: &str, coeffs: [f64; 3]) -> Calibration {
        let h = 1024.0 * 0.2 / 60.0;
        Calibration {
            format_version: FORMAT_VERSION,
            instrument: "FORS1".into(),
            filter: filter.into(),
            lambda_nm: f64::NAN,
            hwp_chi_offset_deg: 0.0,
            model: fit::Model::Radial(RadialModel::new(1, coeffs.to_vec(), [0.0, 0.0])),
            region: FieldRegion { x_min: -h, x_max: h, y_min: -h, y_max: h },
            rms_residual: 5e-4,
            n_bins_used: 0,
            polar_angle: None,
            exclusions: vec![],
            robust: "none".into(),
            pixel: Some(PixelGrid { scale_arcsec: 0.2, origin_px: [1023.5, 1023.5] }),
            provenance: Provenance::now("test", vec![]),
            bins: vec![],
            grid: None,
        }
    }

    /// The demo's step (section `sec:fors1`): a simulated unpolarized standard (photon and read
    /// noise) in the lower-right corner of the paper's V field: the V calibration predicts
    /// 0.96% at 128.1 deg and passes; the I calibration fails.
    #[test]
    fn demo_corner_star_passes_v_fails_i() {
        let dir = tempfile::tempdir().unwrap();
        let truth = [0.0, 0.012, 0.046, 0.002];
        let v = corner_star(&cal("V", [0.012e-2, 0.046e-2, 0.002e-2]), &truth, dir.path(), 7).unwrap();
        let r = &v.validation;
        assert!((r.predicted_p - 0.0096).abs() < 1e-9 && (r.predicted_chi_deg - 128.1).abs() < 1e-6, "{r:?}");
        assert!((r.measured_p - 0.0096).abs() < 4.0 * r.sigma_p, "{r:?}");
        assert!(r.sigma_p > 2e-4 && r.sigma_p < 8e-4, "{r:?}");
        assert!(r.pass, "{r:?}");
        let i = corner_star(&cal("I", [-0.017e-2, 0.105e-2, -0.006e-2]), &truth, dir.path(), 7).unwrap();
        assert!(!i.validation.pass && i.validation.residual_sigma > 3.0, "{:?}", i.validation);
    }
}
