//! `instpol fit-standards`: fit a Mueller model of the telescope's M3 to standard stars
//! measured at many parallactic angles (library: `fit::telescope`).

use anyhow::{bail, Context, Result};
use fit::telescope::{fit_band, fit_joint, read_observations, FitOptions, ModelKind, Observation, TelescopeFit};
use fit::ErrorScaling;
use mueller::mirror::MetalTable;
use plotters::prelude::*;
use serde::Serialize;
use std::path::{Path, PathBuf};

/// Fit the instrumental polarization of a Nasmyth telescope's 45 deg tertiary mirror to
/// standard stars (unpolarized, or polarized of known P, chi) observed at many parallactic
/// angles, band by band and jointly.
///
/// Models (sky to instrument: R(offset) M3(plane at 90 deg - parallactic angle), Wiersema et
/// al. 2018, PASA 35, e012):
///   wiersema: the metal's n and k times an empirical factor; free: factor, offset.
///   oxide:    the metal under an alumina layer; free: thickness, offset, constant q0, u0.
/// With --joint, the mirror parameter (factor or thickness) is shared by all bands, offsets
/// and q0, u0 stay per band.
///
/// Input files: one line per measurement, "star, parallactic_deg, q, sigma_q, u, sigma_u,
/// wavelength_um" (no header; the EFOSC2 files of Wiersema et al.), or a CSV with a header
/// naming those columns (any order) and optionally "filter", "rotator_deg", and for polarized
/// standards "p_true" (a fraction) with "chi_true_deg" (their catalogued polarization, passed
/// through the model; empty for unpolarized stars). q, u are taken in the sky frame, with the
/// HWP zero angle already added to chi (as published standards, photometry and catalog give
/// them): the frame in which correct and validate use the model. The band is the filter, or else the
/// wavelength. Points whose pull exceeds --clip times max(1, robust scatter) are flagged
/// and the fit repeated without them. Errors: sqrt of the covariance's diagonal times
/// max(1, chi2/dof) by default (--error-scaling).
///
/// The mirror: --instrument's [telescope] M3 (metal table, fixed alumina over-layer under the
/// wiersema model's factor) unless --metal overrides it. The oxide model's chi2 has several
/// minima in the thickness: every local minimum within delta chi2 < 4 of the best is listed
/// (text and JSON "minima").
///
/// Calibration files (--output, --output-dir): the fitted model (--save-model, default
/// wiersema) is written as a TELESCOPE HDU (fit::telescope_cal): with --field-cal beside that
/// field calibration (its filter must be the band), else alone. `instpol correct` then takes
/// the parallactic angle per row (catalog column parang_deg, optionally parang_end_deg).
///
/// Example (EFOSC2 2018 standards, all five bands, plots in plots/):
///
///   instpol fit-standards ../shared/data/efosc2-standards/p?_standards.txt --joint --plot-dir plots
///
/// Example (V only, written as a calibration for `instpol correct`):
///
///   instpol fit-standards ../shared/data/efosc2-standards/pv_standards.txt --instrument efosc2 --output tel_V.fits
#[derive(clap::Args)]
pub struct Args {
    /// Measurement files (one or more; bands may be mixed).
    #[arg(required = true)]
    pub files: Vec<PathBuf>,
    /// Which model: wiersema, oxide or both.
    #[arg(long, default_value = "both")]
    pub model: String,
    /// Also fit all bands at once with a shared mirror parameter.
    #[arg(long)]
    pub joint: bool,
    /// The mirror metal: "aluminium" or "silver" (built-in tables, Rakic et al. 1998) or a
    /// "lambda,n,k" table file (micron). Default: the M3 of --instrument's [telescope] section
    /// (its metal and alumina over-layer), else aluminium. Given with an instrument whose M3
    /// differs, it overrides it (with a warning).
    #[arg(long)]
    pub metal: Option<String>,
    /// Flag points with a pull above this many sigma (0: no flagging).
    #[arg(long, default_value_t = 4.0)]
    pub clip: f64,
    /// conservative (x max(1, chi2_red), default), scaled (x chi2_red) or absolute.
    #[arg(long, default_value = "conservative")]
    pub error_scaling: String,
    /// Write q and u against parallactic angle with the model, and the residuals (PNG), here
    /// (polarized standards, triangles: their own polarization removed as the model has it).
    #[arg(long)]
    pub plot_dir: Option<PathBuf>,
    /// Write the fitted model as a calibration file: one band, or all bands with --joint.
    #[arg(long, value_name = "CAL.fits")]
    pub output: Option<PathBuf>,
    /// Write one calibration file per band here (telescope_<band>.fits), from the per-band fits.
    #[arg(long, value_name = "DIR")]
    pub output_dir: Option<PathBuf>,
    /// Which fitted model the calibration files hold: wiersema or oxide.
    #[arg(long, default_value = "wiersema")]
    pub save_model: String,
    /// Put the telescope model beside this field calibration (instpol calibrate) in --output;
    /// it must be of the --instrument's instrument (a mismatch is refused, naming both).
    #[arg(long, value_name = "FIELD.fits")]
    pub field_cal: Option<PathBuf>,
    /// The instrument (built-in name or file): must sit at a Nasmyth focus (its [telescope]
    /// section); names the calibration. Without it the calibration says "unknown".
    #[arg(long)]
    pub instrument: Option<String>,
    /// Print JSON instead of tables (angles in degrees, polarization as fractions).
    #[arg(long)]
    pub json: bool,
}

#[derive(Serialize)]
struct ParamOut {
    name: String,
    value: f64,
    #[serde(rename = "sigma_value")]
    sigma: f64,
    unit: &'static str,
}

#[derive(Serialize)]
struct PointOut {
    star: String,
    band: String,
    source: String,
    parallactic_deg: f64,
    q: f64,
    u: f64,
    q_model: f64,
    u_model: f64,
    pull: f64,
    flagged: bool,
}

#[derive(Serialize)]
struct MinimumOut {
    thickness_nm: f64,
    chi2: f64,
    delta_chi2: f64,
}

#[derive(Serialize)]
struct FitOut {
    model: &'static str,
    /// The mirror's metal table, its fixed over-layer (nm) and where they came from
    /// (instrument, --metal or default).
    metal: String,
    overlayer_nm: f64,
    mirror_source: &'static str,
    /// The oxide model's local minima in the thickness within delta chi2 < 4, best first.
    #[serde(skip_serializing_if = "Vec::is_empty")]
    minima: Vec<MinimumOut>,
    bands: Vec<String>,
    joint: bool,
    params: Vec<ParamOut>,
    chi2: f64,
    #[serde(rename = "n_dof")]
    dof: usize,
    #[serde(rename = "chi2_dof")]
    chi2_reduced: f64,
    error_scaling: &'static str,
    error_factor: f64,
    rms_q: f64,
    rms_u: f64,
    n_used: usize,
    n_total: usize,
    flagged: Vec<String>,
    points: Vec<PointOut>,
    /// The calibration file this fit was written to (--output, --output-dir).
    #[serde(skip_serializing_if = "Option::is_none")]
    output: Option<PathBuf>,
}

fn out(f: &TelescopeFit, joint: bool, mirror: &Mirror) -> FitOut {
    FitOut {
        model: f.model.name(),
        metal: mirror.metal.clone(),
        overlayer_nm: mirror.overlayer_nm,
        mirror_source: mirror.source,
        minima: f
            .minima
            .iter()
            .map(|m| MinimumOut { thickness_nm: m.thickness_nm, chi2: m.chi2, delta_chi2: m.delta_chi2 })
            .collect(),
        bands: f.bands.iter().map(|b| b.0.clone()).collect(),
        joint,
        params: f
            .params
            .iter()
            .map(|p| {
                let angle = p.name.starts_with("offset");
                let unit = if angle {
                    "deg"
                } else if p.name == "thickness_nm" {
                    "nm"
                } else if p.name.starts_with('q') || p.name.starts_with('u') {
                    "fraction"
                } else {
                    ""
                };
                let s = if angle { 180.0 / std::f64::consts::PI } else { 1.0 };
                ParamOut { name: p.name.clone(), value: p.value * s, sigma: p.sigma * s, unit }
            })
            .collect(),
        chi2: f.chi2,
        dof: f.dof,
        chi2_reduced: f.chi2_reduced,
        error_scaling: f.error_scaling.name(),
        error_factor: f.error_factor,
        rms_q: f.rms_q,
        rms_u: f.rms_u,
        n_used: f.n_used(),
        n_total: f.points.len(),
        flagged: f
            .points
            .iter()
            .filter(|p| p.flagged)
            .map(|p| format!("{} ({}, pull {:.1})", p.obs.star, p.obs.source, p.pull))
            .collect(),
        points: f
            .points
            .iter()
            .map(|p| PointOut {
                star: p.obs.star.clone(),
                band: p.obs.band.clone(),
                source: p.obs.source.clone(),
                parallactic_deg: p.obs.parallactic.to_degrees(),
                q: p.obs.qu.q,
                u: p.obs.qu.u,
                q_model: p.q_model,
                u_model: p.u_model,
                pull: p.pull,
                flagged: p.flagged,
            })
            .collect(),
        output: None,
    }
}

fn print_fit(o: &FitOut) {
    let head = if o.joint { format!("joint ({})", o.bands.join(", ")) } else { o.bands.join(", ") };
    outln!("{head}: model {}", o.model);
    for p in &o.params {
        if p.unit == "fraction" {
            outln!("  {:<22} {:>10.4} +- {:.4} %", p.name, 100.0 * p.value, 100.0 * p.sigma);
        } else {
            outln!("  {:<22} {:>10.4} +- {:.4} {}", p.name, p.value, p.sigma, p.unit);
        }
    }
    outln!(
        "  chi2/dof = {:.2} / {} = {:.2}; errors x sqrt({:.2}) ({}); RMS q = {:.3} %, u = {:.3} %; {} of {} points used",
        o.chi2,
        o.dof,
        o.chi2_reduced,
        o.error_factor,
        o.error_scaling,
        100.0 * o.rms_q,
        100.0 * o.rms_u,
        o.n_used,
        o.n_total
    );
    if o.minima.len() > 1 {
        outln!(
            "  {} minima in the thickness within delta chi2 < 4 (the data do not choose between them):",
            o.minima.len()
        );
        for m in &o.minima {
            outln!("    {:>8.2} nm   chi2 = {:.2}   delta chi2 = {:.2}", m.thickness_nm, m.chi2, m.delta_chi2);
        }
    }
    for f in &o.flagged {
        outln!("  flagged: {f}");
    }
}

/// The mirror the models start from.
struct Mirror {
    table: MetalTable,
    metal: String,
    overlayer_nm: f64,
    source: &'static str,
}

/// --metal, else --instrument's oblique mirror (metal, alumina over-layer), else aluminium.
fn mirror(a: &Args, inst: Option<&instrument::Instrument>) -> Result<Mirror> {
    let table_of = |m: &str, base: Option<&Path>| -> Result<MetalTable> {
        if let Ok(t) = MetalTable::builtin(m) {
            return Ok(t);
        }
        let p = match base {
            Some(b) if Path::new(m).is_relative() && !Path::new(m).is_file() => b.join(m),
            _ => PathBuf::from(m),
        };
        Ok(MetalTable::read(&p)?)
    };
    let m3 = inst.and_then(|i| i.telescope.as_ref()).and_then(|t| t.oblique_mirror());
    if let (Some(i), Some(m)) = (inst, m3) {
        let thick = match m.overlayer.as_deref() {
            None => 0.0,
            Some(o) if o.eq_ignore_ascii_case("alumina") => m.overlayer_thickness_nm,
            Some(o) => bail!(
                "--instrument {}: mirror {} has over-layer '{o}': fit-standards models alumina over-layers only (give --metal to fit the bare metal)",
                i.name,
                m.name
            ),
        };
        if let Some(given) = &a.metal {
            if !given.eq_ignore_ascii_case(&m.metal) || thick > 0.0 {
                eprintln!(
                    "warning: --metal {given} OVERRIDES the instrument {}'s {} (metal {}, alumina over-layer {thick} nm): fitting {given}, bare",
                    i.name, m.name, m.metal
                );
            }
        } else {
            let base = a.instrument.as_deref().map(Path::new).filter(|p| p.is_file()).and_then(|p| p.parent());
            let table = table_of(&m.metal, base)
                .with_context(|| format!("--instrument {}: mirror {} metal {}", i.name, m.name, m.metal))?;
            return Ok(Mirror { table, metal: m.metal.clone(), overlayer_nm: thick, source: "instrument" });
        }
    }
    let (metal, source) = match &a.metal {
        Some(m) => (m.clone(), "--metal"),
        None => ("aluminium".to_string(), "default"),
    };
    let table = table_of(&metal, None).with_context(|| format!("--metal {metal}"))?;
    Ok(Mirror { table, metal, overlayer_nm: 0.0, source })
}

pub fn run(a: Args) -> Result<()> {
    let models: Vec<ModelKind> = match a.model.trim().to_ascii_lowercase().as_str() {
        "wiersema" => vec![ModelKind::Wiersema],
        "oxide" | "physical" => vec![ModelKind::Oxide],
        "both" => vec![ModelKind::Wiersema, ModelKind::Oxide],
        other => bail!("--model '{other}': use wiersema, oxide or both"),
    };
    if !(a.clip.is_finite() && a.clip >= 0.0) {
        bail!("--clip {} must be >= 0 (0: no flagging)", a.clip);
    }
    let error_scaling: ErrorScaling = a.error_scaling.parse().context("--error-scaling")?;
    let inst = match &a.instrument {
        Some(name) => Some(instrument::Instrument::load(name).with_context(|| format!("--instrument {name}"))?),
        None => None,
    };
    let mirror = mirror(&a, inst.as_ref())?;
    let opts = FitOptions {
        clip: if a.clip > 0.0 { Some(a.clip) } else { None },
        error_scaling,
        overlayer_nm: mirror.overlayer_nm,
    };
    let table = &mirror.table;
    let mut obs: Vec<Observation> = Vec::new();
    for f in &a.files {
        obs.extend(read_observations(f)?);
    }
    let mut bands: Vec<String> = Vec::new();
    for o in &obs {
        if !bands.contains(&o.band) {
            bands.push(o.band.clone());
        }
    }
    let mut fits: Vec<(TelescopeFit, bool)> = Vec::new();
    for b in &bands {
        let sel: Vec<Observation> = obs.iter().filter(|o| &o.band == b).cloned().collect();
        for &m in &models {
            let f = fit_band(m, &sel, table, &opts).with_context(|| format!("band {b}, model {}", m.name()))?;
            fits.push((f, false));
        }
    }
    if a.joint {
        for &m in &models {
            let f = fit_joint(m, &obs, table, &opts, true).with_context(|| format!("joint fit, model {}", m.name()))?;
            fits.push((f, true));
        }
    }
    let outputs = write_calibrations(&a, &fits, &obs, inst.as_ref(), &mirror.metal)?;
    let mut outs: Vec<FitOut> = fits.iter().map(|(f, j)| out(f, *j, &mirror)).collect();
    for (i, p) in &outputs {
        outs[*i].output = Some(p.clone());
    }
    if let Some(dir) = &a.plot_dir {
        std::fs::create_dir_all(dir).with_context(|| format!("--plot-dir {}", dir.display()))?;
        for (f, j) in &fits {
            for (bi, (b, _)) in f.bands.iter().enumerate() {
                let name =
                    format!("standards_{}_{}{}.png", f.model.name(), sanitize(b), if *j { "_joint" } else { "" });
                let path = dir.join(name);
                plot_band(&path, f, bi)?;
                if !a.json {
                    eprintln!("wrote {}", path.display());
                }
            }
        }
    }
    if a.json {
        return crate::util::print_json(&outs);
    }
    for o in &outs {
        print_fit(o);
        outln!();
    }
    for (_, p) in &outputs {
        outln!("wrote {}", p.display());
    }
    Ok(())
}

/// The calibration files asked for (--output, --output-dir), written atomically; their paths.
fn write_calibrations(
    a: &Args,
    fits: &[(TelescopeFit, bool)],
    obs: &[Observation],
    inst: Option<&instrument::Instrument>,
    metal: &str,
) -> Result<Vec<(usize, PathBuf)>> {
    if a.output.is_none() && a.output_dir.is_none() {
        if a.field_cal.is_some() {
            bail!("--field-cal needs --output (the file that gets the field and the telescope model)");
        }
        return Ok(vec![]);
    }
    crate::util::inputs(a.files.iter().map(|p| p.as_path()).chain(a.field_cal.as_deref()))?;
    let save = match a.save_model.trim().to_ascii_lowercase().as_str() {
        "wiersema" => ModelKind::Wiersema,
        "oxide" | "physical" => ModelKind::Oxide,
        other => bail!("--save-model '{other}': use wiersema or oxide"),
    };
    let instrument = match (&a.instrument, inst) {
        (Some(name), Some(inst)) => {
            match inst.telescope.as_ref().map(|t| t.focus) {
                Some(instrument::Focus::Nasmyth) => {}
                Some(instrument::Focus::Cassegrain) => bail!(
                    "--instrument {name}: {} sits at a Cassegrain focus (its [telescope] section): no 45 deg mirror, no telescope term of this kind to calibrate",
                    inst.name
                ),
                None => bail!(
                    "--instrument {name}: {} has no [telescope] section saying it sits at a Nasmyth focus",
                    inst.name
                ),
            }
            inst.name.clone()
        }
        _ => "unknown".to_string(),
    };
    let inputs: Vec<String> = a.files.iter().map(|f| f.display().to_string()).collect();
    let pick = |joint: bool, band: Option<&str>| {
        fits.iter().enumerate().find(|(_, (f, j))| {
            f.model == save && *j == joint && band.is_none_or(|b| f.bands.len() == 1 && f.bands[0].0 == b)
        })
    };
    let mut written = Vec::new();
    let mut bands: Vec<&str> = Vec::new();
    for o in obs {
        if !bands.contains(&o.band.as_str()) {
            bands.push(&o.band);
        }
    }
    if let Some(path) = &a.output {
        crate::util::check_output(path)?;
        let f = if a.joint {
            pick(true, None)
        } else if bands.len() == 1 {
            pick(false, Some(bands[0]))
        } else {
            bail!(
                "--output: {} bands ({}): write one calibration per band with --output-dir, or fit them jointly (--joint)",
                bands.len(),
                bands.join(", ")
            )
        };
        let (i, (f, _)) =
            f.ok_or_else(|| anyhow::anyhow!("--save-model {}: that model was not fitted (--model)", save.name()))?;
        match &a.field_cal {
            Some(fc) => {
                let cal = fit::Calibration::load(fc).with_context(|| format!("--field-cal {}", fc.display()))?;
                check_field_instrument(fc, &cal.instrument, a.instrument.as_deref(), inst)?;
                if f.band(&cal.filter).is_none() {
                    bail!(
                        "--field-cal {} is for filter {}, but the telescope model has band(s) {} (name the bands by a 'filter' column)",
                        fc.display(),
                        cal.filter,
                        f.bands.iter().map(|b| b.0.as_str()).collect::<Vec<_>>().join(", ")
                    );
                }
                fit::telescope_cal::save_with_field(path, &cal, f, metal)?;
            }
            None => fit::telescope_cal::save_alone(path, &instrument, f, metal, &inputs)?,
        }
        written.push((i, path.clone()));
    }
    if let Some(dir) = &a.output_dir {
        std::fs::create_dir_all(dir).with_context(|| format!("--output-dir {}", dir.display()))?;
        for b in &bands {
            let (i, (f, _)) = pick(false, Some(b))
                .ok_or_else(|| anyhow::anyhow!("--save-model {}: that model was not fitted", save.name()))?;
            let path = dir.join(format!("telescope_{}.fits", sanitize(b)));
            crate::util::check_output(&path)?;
            fit::telescope_cal::save_alone(&path, &instrument, f, metal, &inputs)?;
            written.push((i, path));
        }
    }
    Ok(written)
}

/// The field calibration and the telescope model go into one file for one instrument: a field
/// calibration of another instrument than --instrument is refused, naming both; one that does
/// not say its instrument is taken with a warning (nothing to compare).
fn check_field_instrument(
    fc: &Path,
    field_instrument: &str,
    name: Option<&str>,
    inst: Option<&instrument::Instrument>,
) -> Result<()> {
    let (Some(name), Some(inst)) = (name, inst) else { return Ok(()) };
    let fi = field_instrument.trim();
    if fi.is_empty() || fi.eq_ignore_ascii_case("unknown") {
        eprintln!(
            "warning: --field-cal {} does not say its instrument ('{fi}'): taken as {} (--instrument {name}) unchecked",
            fc.display(),
            inst.name
        );
        return Ok(());
    }
    if !fi.eq_ignore_ascii_case(inst.name.trim()) {
        bail!(
            "--field-cal {} is a calibration of instrument {fi}, but --instrument {name} is {}: the field and the telescope model must be of one instrument",
            fc.display(),
            inst.name
        );
    }
    Ok(())
}

fn sanitize(s: &str) -> String {
    s.chars().map(|c| if c.is_ascii_alphanumeric() || c == '.' { c } else { '_' }).collect()
}

/// One standard's point in the `--plot-dir` figure (fractions; angle in deg).
#[derive(Debug, Clone, Copy, PartialEq)]
struct PlotPoint {
    pa_deg: f64,
    /// What the upper panel draws: the measured `(q, u)`, or for a star the model gives its
    /// own polarization (a polarized standard, a rotator angle) the measurement with that
    /// removed as the fitted model has it, `q - (q_model - q_curve(pa))`.
    q: f64,
    u: f64,
    sigma_q: f64,
    sigma_u: f64,
    /// Data minus model (the lower panel).
    resid_q: f64,
    resid_u: f64,
    flagged: bool,
    /// The star's own polarization was removed (drawn as a triangle).
    shifted: bool,
}

/// The series of one band's figure: the model curve of an unpolarized star at rotator angle
/// 0, `(pa_deg, q, u)` every degree, and the points. Every point sits on the curve exactly
/// when its residual is zero: a polarized standard is not drawn at its raw `(q, u)`, which the
/// model puts on a curve of its own (its `p_true`, `chi_true` through the telescope).
struct BandPlot {
    curve: Vec<(f64, f64, f64)>,
    points: Vec<PlotPoint>,
}

fn band_plot(f: &TelescopeFit, bi: usize) -> Result<BandPlot> {
    let (band, m) = &f.bands[bi];
    let unpol = |pa_rad: f64| m.unpolarized(pa_rad).map_err(|e| anyhow::anyhow!("model: {e}"));
    let mut curve = Vec::with_capacity(361);
    for k in 0..=360 {
        let pa = -180.0 + k as f64;
        let (q, u) = unpol(f64::to_radians(pa))?;
        curve.push((pa, q, u));
    }
    let mut points = Vec::new();
    for p in f.points.iter().filter(|p| &p.obs.band == band) {
        let o = &p.obs;
        let shifted = o.sky != (0.0, 0.0) || o.rotator != 0.0;
        let (q, u) = if shifted {
            let (cq, cu) = unpol(o.parallactic)?;
            (o.qu.q - p.q_model + cq, o.qu.u - p.u_model + cu)
        } else {
            (o.qu.q, o.qu.u)
        };
        points.push(PlotPoint {
            pa_deg: o.parallactic.to_degrees(),
            q,
            u,
            sigma_q: o.qu.sigma_q(),
            sigma_u: o.qu.sigma_u(),
            resid_q: o.qu.q - p.q_model,
            resid_u: o.qu.u - p.u_model,
            flagged: p.flagged,
            shifted,
        });
    }
    Ok(BandPlot { curve, points })
}

/// The legend's key of the polarized standards' triangles.
const POL_KEY: &str = "polarized, own P removed";

/// q and u against the parallactic angle with the model curve (upper panel), residuals
/// (lower panel); flagged points hollow; polarized standards (triangles) with their own
/// polarization removed as the model has it, so that they sit on the same curve ([`band_plot`]).
fn plot_band(path: &Path, f: &TelescopeFit, bi: usize) -> Result<()> {
    let band = &f.bands[bi].0;
    let BandPlot { curve, points: pts } = band_plot(f, bi)?;
    let curve: Vec<(f64, f64, f64)> = curve.iter().map(|&(pa, q, u)| (pa, 100.0 * q, 100.0 * u)).collect();
    let ymax = curve
        .iter()
        .map(|c| c.1.abs().max(c.2.abs()))
        .chain(pts.iter().map(|p| 100.0 * (p.q.abs().max(p.u.abs()) + 2.0 * p.sigma_q.max(p.sigma_u))))
        .fold(0.5, f64::max)
        * 1.1;
    let rmax =
        pts.iter().map(|p| 100.0 * (p.resid_q.abs() + p.sigma_q).max(p.resid_u.abs() + p.sigma_u)).fold(0.05, f64::max)
            * 1.2;
    let title = format!("{band}: {} model, chi2/dof = {:.2}", f.model.name(), f.chi2_reduced);
    crate::plot::save_png(path, (900, 800), |root| {
        let (top, bottom) = root.split_vertically(520);
        let ax = crate::plot::Axes::new(title.clone(), "parallactic angle (deg)", "q, u (%)");
        let mut c = crate::plot::chart(&top, &ax, -180.0..180.0, -ymax..ymax)?;
        let mut keyed = false;
        for (col, idx, label) in [(RED, 0usize, "q"), (BLUE, 1, "u")] {
            c.draw_series(LineSeries::new(
                curve.iter().map(|p| (p.0, if idx == 0 { p.1 } else { p.2 })),
                col.stroke_width(2),
            ))
            .map_err(crate::plot::pe)?
            .label(format!("{label} model"))
            .legend(crate::plot::line_key(col.stroke_width(2)));
            for p in &pts {
                let (v, s) = if idx == 0 { (p.q, p.sigma_q) } else { (p.u, p.sigma_u) };
                let x = p.pa_deg;
                c.draw_series(std::iter::once(PathElement::new([(x, 100.0 * (v - s)), (x, 100.0 * (v + s))], col)))
                    .map_err(crate::plot::pe)?;
                let style = if p.flagged { col.stroke_width(2) } else { col.filled() };
                if p.shifted {
                    let a = c
                        .draw_series(std::iter::once(TriangleMarker::new((x, 100.0 * v), 6, style)))
                        .map_err(crate::plot::pe)?;
                    if !keyed && idx == 1 {
                        keyed = true;
                        a.label(POL_KEY).legend(|(x, y)| TriangleMarker::new((x + 10, y), 6, BLACK.filled()));
                    }
                } else {
                    c.draw_series(std::iter::once(Circle::new((x, 100.0 * v), 5, style))).map_err(crate::plot::pe)?;
                }
            }
        }
        let data: Vec<(f64, f64)> = curve
            .iter()
            .flat_map(|p| [(p.0, p.1), (p.0, p.2)])
            .chain(pts.iter().flat_map(|p| {
                let x = p.pa_deg;
                [
                    (x, 100.0 * (p.q + p.sigma_q)),
                    (x, 100.0 * (p.q - p.sigma_q)),
                    (x, 100.0 * (p.u + p.sigma_u)),
                    (x, 100.0 * (p.u - p.sigma_u)),
                ]
            }))
            .collect();
        let (entries, chars) = if keyed { (3, POL_KEY.len()) } else { (2, 7) };
        crate::plot::legend_off_data(&mut c, &data, entries, chars, crate::plot::CORNERS)?;
        let ax = crate::plot::Axes::new(
            "residuals (data - model; hollow: flagged)",
            "parallactic angle (deg)",
            "residual (%)",
        );
        let mut r = crate::plot::chart(&bottom, &ax, -180.0..180.0, -rmax..rmax)?;
        r.draw_series(LineSeries::new([(-180.0, 0.0), (180.0, 0.0)], BLACK)).map_err(crate::plot::pe)?;
        for p in &pts {
            let x = p.pa_deg;
            for (col, d, s, dx) in [(RED, p.resid_q, p.sigma_q, -1.5), (BLUE, p.resid_u, p.sigma_u, 1.5)] {
                r.draw_series(std::iter::once(PathElement::new(
                    [(x + dx, 100.0 * (d - s)), (x + dx, 100.0 * (d + s))],
                    col,
                )))
                .map_err(crate::plot::pe)?;
                let style = if p.flagged { col.stroke_width(2) } else { col.filled() };
                r.draw_series(std::iter::once(Circle::new((x + dx, 100.0 * d), 4, style))).map_err(crate::plot::pe)?;
            }
        }
        Ok(())
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use fit::telescope::{parse_observations, BandModel, Track};

    /// Two unpolarized and two polarized standards (5 % at 30 deg, 4 % at 120 deg) seen through
    /// an aluminium M3 (factor 0.86, offset 40 deg) at twelve parallactic angles each, made
    /// with the track-averaged chain (`BandModel::sky_through`, not the fit's residuals), with
    /// a fixed +-2e-4 pattern for noise; fitted with the Wiersema model.
    fn fitted() -> TelescopeFit {
        let table = MetalTable::builtin("aluminium").unwrap();
        let truth = BandModel {
            wavelength_um: 0.55,
            index: table.index(0.55).unwrap(),
            factor: 0.86,
            thickness_nm: 0.0,
            offset: 40f64.to_radians(),
            q0: 0.0,
            u0: 0.0,
        };
        let mut text =
            String::from("star,parallactic_deg,q,sigma_q,u,sigma_u,wavelength_um,filter,p_true,chi_true_deg\n");
        for (s, (star, p, chi)) in
            [("WD a", 0.0, 0.0), ("WD b", 0.0, 0.0), ("Pol a", 0.05f64, 30f64), ("Pol b", 0.04, 120.0)]
                .into_iter()
                .enumerate()
        {
            for k in 0..12 {
                let pa = -170.0 + 29.0 * k as f64 + 7.0 * s as f64;
                let (qs, us) = (p * (2.0 * chi.to_radians()).cos(), p * (2.0 * chi.to_radians()).sin());
                let (q, u) = truth.sky_through(qs, us, Track::at(pa.to_radians())).unwrap();
                let e = if (k + s) % 2 == 0 { 2e-4 } else { -2e-4 };
                let (pt, ct) = if p > 0.0 { (p.to_string(), chi.to_string()) } else { (String::new(), String::new()) };
                text += &format!("{star},{pa},{},3e-4,{},3e-4,0.55,V,{pt},{ct}\n", q + e, u - e);
            }
        }
        let obs = parse_observations(&text, Path::new("night.csv")).unwrap();
        fit_band(ModelKind::Wiersema, &obs, &table, &FitOptions { clip: None, ..Default::default() }).unwrap()
    }

    /// The upper panel once drew the curve of an unpolarized star only, so polarized
    /// standards sat off it by their own 4-5 %. Every point lies on the curve up to its
    /// residual (the lower panel's value, data minus model): the polarized standards with the
    /// residuals the fit leaves (~2e-4), far closer than their raw values (several %).
    #[test]
    fn polarized_standards_sit_on_the_curve_up_to_their_residual() {
        let f = fitted();
        let bp = band_plot(&f, 0).unwrap();
        assert_eq!(bp.points.len(), 48);
        assert_eq!(bp.curve.len(), 361);
        let (_, m) = &f.bands[0];
        for (p, fp) in bp.points.iter().zip(f.points.iter()) {
            // The curve at this angle, from the band model at the fitted parameters.
            let (cq, cu) = m.unpolarized(p.pa_deg.to_radians()).unwrap();
            assert!((p.q - cq - p.resid_q).abs() < 1e-12 && (p.u - cu - p.resid_u).abs() < 1e-12, "{p:?}");
            assert!(p.resid_q.abs() < 1e-3 && p.resid_u.abs() < 1e-3, "{p:?}");
            let polarized = fp.obs.sky != (0.0, 0.0);
            assert_eq!(p.shifted, polarized);
            if polarized {
                // The raw measurement is far off the unpolarized curve: what the old plot drew.
                assert!((fp.obs.qu.q - cq).hypot(fp.obs.qu.u - cu) > 0.02, "{:?}", fp.obs);
            } else {
                assert_eq!((p.q, p.u), (fp.obs.qu.q, fp.obs.qu.u), "unpolarized stars drawn as measured");
            }
        }
        let dir = tempfile::tempdir().unwrap();
        plot_band(&dir.path().join("v.png"), &f, 0).unwrap();
        assert!(dir.path().join("v.png").is_file());
    }
}
