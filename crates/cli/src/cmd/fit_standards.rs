//! `instpol fit-standards`: fit a Mueller model of the telescope's M3 to standard stars
//! measured at many parallactic angles (library: `fit::telescope`).

use anyhow::{bail, Context, Result};
use fit::telescope::cal::{band_file_name, safe_name};
use fit::telescope::report::{choose_mirror, fit_all, FitReport, Mirror, MirrorError};
use fit::telescope::{read_observations, FitOptions, ModelKind, Observation, TelescopeFit};
use fit::ErrorScaling;
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
/// through the model; empty for unpolarized stars), or a .json file holding one measurement:
/// the output of `instpol photometry --star NAME --json` on the star's frames (its star,
/// filter, wavelength, catalogued polarization and the middle of the frames' parallactic
/// track, read from the headers). q, u are taken in the sky frame, with the
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
/// wiersema) is written as a TELESCOPE HDU (fit::telescope::cal): with --field-cal beside that
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

/// --metal, else --instrument's oblique mirror (metal, alumina over-layer), else aluminium
/// (fit::telescope::report::choose_mirror), with this command's words.
fn mirror(a: &Args, inst: Option<&instrument::Instrument>) -> Result<Mirror> {
    let base = a.instrument.as_deref().map(Path::new).filter(|p| p.is_file()).and_then(|p| p.parent());
    let c = choose_mirror(a.metal.as_deref(), inst, base).map_err(|e| match e {
        MirrorError::Overlayer { instrument, mirror, overlayer } => anyhow::anyhow!(
            "--instrument {instrument}: mirror {mirror} has over-layer '{overlayer}': fit-standards models alumina over-layers only (give --metal to fit the bare metal)"
        ),
        MirrorError::Table { metal, from_instrument: Some((i, m)), source } => {
            anyhow::Error::new(source).context(format!("--instrument {i}: mirror {m} metal {metal}"))
        }
        MirrorError::Table { metal, from_instrument: None, source } => {
            anyhow::Error::new(source).context(format!("--metal {metal}"))
        }
    })?;
    if let (Some(given), Some((i, m, metal, thick))) = (&a.metal, &c.overrides) {
        eprintln!(
            "warning: --metal {given} OVERRIDES the instrument {i}'s {m} (metal {metal}, alumina over-layer {thick} nm): fitting {given}, bare"
        );
    }
    Ok(c.mirror)
}

pub fn run(a: Args) -> Result<()> {
    let models: Vec<ModelKind> = match ModelKind::from_user_name(&a.model) {
        Some(m) => vec![m],
        None if a.model.trim().eq_ignore_ascii_case("both") => vec![ModelKind::Wiersema, ModelKind::Oxide],
        None => bail!("--model '{}': use wiersema, oxide or both", a.model.trim().to_ascii_lowercase()),
    };
    // A threshold below one sigma flags points within their errors: the fit would be made of
    // whatever few survive.
    if !(a.clip.is_finite() && (a.clip == 0.0 || a.clip >= 1.0)) {
        bail!("--clip {}: give 0 (no flagging) or a threshold of at least 1 sigma", a.clip);
    }
    // The model to save is checked whether or not a file is asked for: a misspelt name must
    // not pass because nothing is written this time.
    save_model(&a.save_model)?;
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
    let (obs, repeated) = fit::telescope::distinct_observations(obs);
    if let Some(note) = repeated {
        eprintln!("warning: {note}");
    }
    let fits =
        fit_all(&obs, &models, table, &opts, a.joint).map_err(|(what, e)| anyhow::Error::new(e).context(what))?;
    // What the fits are of: the JSON's and the calibration files' one product.
    let product = inst.as_ref().map(|i| skyfield::provenance::Product::of_instrument_alone(i).with_run_inputs());
    let outputs = write_calibrations(&a, &fits, &obs, inst.as_ref(), product.as_ref(), &mirror.metal)?;
    let mut outs: Vec<FitReport> = fits.iter().map(|(f, j)| FitReport::new(f, *j, &mirror, product.clone())).collect();
    for (i, p) in &outputs {
        outs[*i].output = Some(p.clone());
    }
    if let Some(dir) = &a.plot_dir {
        std::fs::create_dir_all(dir).with_context(|| format!("--plot-dir {}", dir.display()))?;
        for (f, j) in &fits {
            for (bi, (b, _)) in f.bands.iter().enumerate() {
                let name = format!("standards_{}_{}{}", f.model.name(), safe_name(b), if *j { "_joint" } else { "" });
                let label = fit::correction::setup::band_label(b, inst.as_ref());
                for path in super::fit_standards_plot::plot_band(&dir.join(name), f, bi, &label)? {
                    if !a.json {
                        eprintln!("wrote {}", path.display());
                    }
                }
            }
        }
    }
    if a.json {
        return crate::util::print_json(&outs);
    }
    for o in &outs {
        super::fit_standards_text::print_fit(o, inst.as_ref());
        outln!();
    }
    for (_, p) in &outputs {
        outln!("wrote {}", p.display());
    }
    Ok(())
}

/// The model `--save-model` names.
fn save_model(name: &str) -> Result<ModelKind> {
    ModelKind::from_user_name(name)
        .with_context(|| format!("--save-model '{}': use wiersema or oxide", name.trim().to_ascii_lowercase()))
}

/// The calibration files asked for (--output, --output-dir), written atomically; their paths.
fn write_calibrations(
    a: &Args,
    fits: &[(TelescopeFit, bool)],
    obs: &[Observation],
    inst: Option<&instrument::Instrument>,
    product: Option<&skyfield::provenance::Product>,
    metal: &str,
) -> Result<Vec<(usize, PathBuf)>> {
    if a.output.is_none() && a.output_dir.is_none() {
        if a.field_cal.is_some() {
            bail!("--field-cal needs --output (the file that gets the field and the telescope model)");
        }
        return Ok(vec![]);
    }
    crate::util::inputs(a.files.iter().map(|p| p.as_path()).chain(a.field_cal.as_deref()))?;
    let save = save_model(&a.save_model)?;
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
    let bands = fit::telescope::report::bands_of(obs);
    if let Some(path) = &a.output {
        crate::util::check_output(path)?;
        let f = if a.joint {
            pick(true, None)
        } else if bands.len() == 1 {
            pick(false, Some(bands[0].as_str()))
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
                let inst = a.instrument.as_deref().and(inst);
                match fit::telescope::cal::check_field_beside(&cal, f, inst) {
                    Ok(None) => {}
                    Ok(Some(w)) => eprintln!("warning: --field-cal {}: {w} (--instrument)", fc.display()),
                    Err(e) => bail!("--field-cal {}: {e}", fc.display()),
                }
                fit::telescope::cal::save_with_field(path, &cal, f, metal)?;
            }
            None => fit::telescope::cal::save_alone(path, &instrument, f, metal, &inputs, product)?,
        }
        written.push((i, path.clone()));
    }
    if let Some(dir) = &a.output_dir {
        std::fs::create_dir_all(dir).with_context(|| format!("--output-dir {}", dir.display()))?;
        for b in &bands {
            let (i, (f, _)) = pick(false, Some(b.as_str()))
                .ok_or_else(|| anyhow::anyhow!("--save-model {}: that model was not fitted", save.name()))?;
            let path = dir.join(band_file_name(b));
            crate::util::check_output(&path)?;
            fit::telescope::cal::save_alone(&path, &instrument, f, metal, &inputs, product)?;
            written.push((i, path));
        }
    }
    Ok(written)
}
