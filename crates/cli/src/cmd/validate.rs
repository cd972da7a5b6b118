//! `instpol validate`: check a calibration on a standard star (`fit::validate` measures and
//! judges it; this module parses the arguments and prints the report).

use anyhow::{anyhow, bail, Context, Result};
use fit::standards::{Expected, Standards};
use fit::Calibration;
use instrument::Instrument;
use skyfield::photometry::Aperture;
use std::path::PathBuf;

/// Validate a calibration on a standard star, as the paper checks its V map with an
/// unpolarized star in the lower-right corner of FORS1 (section sec:fors1: measured
/// 0.92 +- 0.04 % at -48 +- 1.4 deg, predicted 0.96 % at -51.9 deg).
///
/// The star is measured in the frames (aperture photometry in both beams at every HWP angle,
/// local background subtracted before F_i), its chi corrected for the HWP zero angle of the
/// calibration's filter, and compared with what the calibration predicts at its position: the
/// instrumental M_I(x, y) applied to the star's intrinsic polarization (0 for an unpolarized
/// standard; a named standard's published P, chi in the calibration's band otherwise, from
/// instruments/standards.toml or --standards). The star is also corrected and compared with
/// its intrinsic polarization. Each difference is in units of the combined error (measurement,
/// calibration, published value), as the Mahalanobis distance in (Q/I, U/I) (a 2-D residual:
/// 3 sigma is exceeded by chance with probability exp(-9/2) = 1.1%). The star passes when both
/// are within --threshold.
///
/// The calibration's error at one position is its coefficient covariance plus, by default
/// (--model-error auto), the RMS scatter of its own data about the model (the paper's ~0.05%):
/// the model predicts a single new position no better than that.
///
/// JSON (--json): measured_p, measured_chi_deg, sigma_p, sigma_chi_deg, predicted_p,
/// predicted_chi_deg, residual_sigma, pass (polarization as fractions, angles in deg in
/// [0, 180)), plus corrected_p, corrected_chi_deg, sigma_corrected_p, expected_p,
/// corrected_residual_sigma, sigma_predicted_p, threshold, extrapolated, star, band, x_px,
/// y_px, x_arcmin, y_arcmin, model_error, hwp_chi_offset_deg, n_frames.
///
/// Example: instpol validate --cal V.fits frames/*.fits --x 1782 --y 56 --threshold 3
///
/// A calibration holding a telescope model (instpol fit-standards: a Nasmyth M3, alone or
/// beside a field model) is applied through the whole chain (fit::telescope::validate::validate_chain:
/// the field first, then the telescope as each exposure saw it). The angles come from the
/// frames' headers, under the keywords of the instrument's [telescope] section (parallactic
/// angle at start and end, rotator angle): each exposure is undone over its own track, the
/// exposures demodulated together (JSON exposures: their number); or one track for all from
/// --parang START[,END] (deg, the convention of fit-standards). Both models live in the sky
/// frame, where chi carries the HWP zero angle (the telescope's standards are quoted there):
/// the star, measured at the plate, is turned there by the field calibration's zero angle, or
/// without one by the instrument's for the frames' filter. The star passes when, corrected, it
/// is within --threshold sigma of its expected polarization. JSON: measured_q, measured_u, sigma_q, sigma_u, telescope_q,
/// telescope_u (what the telescope makes of an unpolarized star there), corrected_q,
/// corrected_u, their sigma_, corrected_p, corrected_chi_deg, expected_q, expected_u,
/// corrected_pull, uncorrected_pull, pass, parallactic_start_deg, parallactic_end_deg (the
/// set's first start and last end), rotator_deg, hwp_chi_offset_deg (the zero angle the star
/// was turned by), exposures
/// (schemas/validate-telescope.schema.json).
///
/// Example (EFOSC2 standard, telescope model from fit-standards):
///
///   instpol validate --cal tel_V.fits --instrument efosc2 std/*.fits --x 512 --y 300
#[derive(clap::Args)]
#[command(verbatim_doc_comment)]
pub struct Args {
    /// Calibration file (FITS).
    #[arg(long, value_name = "CAL.fits")]
    pub cal: PathBuf,
    /// Frames of the star (FITS, one per exposure, all HWP angles of one filter).
    #[arg(required = true, value_name = "FRAMES")]
    pub frames: Vec<PathBuf>,
    /// Star position, x: 0-based px, or arcmin with --coords arcmin.
    #[arg(long, allow_negative_numbers = true)]
    pub x: f64,
    /// Star position, y: 0-based px, or arcmin with --coords arcmin.
    #[arg(long, allow_negative_numbers = true)]
    pub y: f64,
    /// Units of --x/--y: 0-based pixels of the ordinary image on the detector, or arcmin from
    /// the detector centre.
    #[arg(long, value_enum, default_value = "pixel")]
    pub coords: crate::cmd::correct::Coords,
    /// Pass threshold, in units of the combined error (sigma).
    #[arg(long, default_value_t = 3.0)]
    pub threshold: f64,
    /// Standard star name (see instruments/standards.toml); default: an unpolarized star.
    #[arg(long)]
    pub star: Option<String>,
    /// Standard-star list to use instead of the built-in one (TOML).
    #[arg(long, value_name = "FILE")]
    pub standards: Option<PathBuf>,
    /// Instrument (built-in name or TOML file) the frames come from.
    /// Default: the built-in instrument the first file's INSTRUME keyword names (said on
    /// stderr); a file without one, or of no built-in instrument, is refused.
    #[arg(long)]
    pub instrument: Option<String>,
    /// Aperture radius (px).
    #[arg(long, default_value_t = 10.0)]
    pub aperture: f64,
    /// Background annulus "R_IN,R_OUT" (px); "none" for no background subtraction.
    #[arg(long, default_value = "14,24")]
    pub annulus: String,
    /// Extra calibration error per component: "auto" (the calibration's RMS residual, or 0 for
    /// models that already carry their residual interpolation error), "none", or a fraction.
    #[arg(long, default_value = "auto")]
    pub model_error: String,
    /// Validate at a position outside the calibrated field (errors inflated, flagged).
    #[arg(long)]
    pub allow_extrapolation: bool,
    /// With a telescope calibration: the parallactic angle (deg) at the start and optionally
    /// the end of the exposures, instead of the frames' headers.
    #[arg(long, value_name = "START[,END]", allow_hyphen_values = true)]
    pub parang: Option<String>,
    /// With a telescope calibration: its band to use (default: the field model's filter, the
    /// model's only band, or the frames' filter).
    #[arg(long)]
    pub band: Option<String>,
    /// Print JSON.
    #[arg(long)]
    pub json: bool,
    #[command(flatten)]
    pub frame: crate::cmd::frame_opts::FrameOpts,
}

pub use fit::validate::{ValidateOptions, ValidationReport};

/// Measure a star at 0-based ordinary-image pixel `(x_px, y_px)` in `frames` and validate
/// `cal` on it (`fit::validate::validate_frames`), printing its warnings.
fn validate_star(
    cal: &Calibration,
    inst: &Instrument,
    frames: &[PathBuf],
    x_px: f64,
    y_px: f64,
    star: (&str, Expected),
    opts: &ValidateOptions,
) -> Result<ValidationReport> {
    let r = fit::validate::validate_frames(cal, inst, frames, x_px, y_px, star, opts)?;
    for w in &r.warnings {
        eprintln!("warning: {w}");
    }
    Ok(r)
}

fn parse_annulus(s: &str) -> Result<Option<(f64, f64)>> {
    if s.eq_ignore_ascii_case("none") {
        return Ok(None);
    }
    let v: Vec<&str> = s.split(',').collect();
    if v.len() != 2 {
        bail!("--annulus '{s}': expected R_IN,R_OUT in px or none");
    }
    let p = |t: &str| t.trim().parse::<f64>().map_err(|_| anyhow!("--annulus '{s}': '{t}' is not a number"));
    Ok(Some((p(v[0])?, p(v[1])?)))
}

fn parse_model_error(s: &str) -> Result<Option<f64>> {
    match s.to_ascii_lowercase().as_str() {
        "auto" => Ok(None),
        "none" => Ok(Some(0.0)),
        t => {
            let v: f64 = t.parse().map_err(|_| anyhow!("--model-error '{s}': expected auto, none or a fraction"))?;
            if !(v.is_finite() && v >= 0.0) {
                bail!("--model-error {v} must be a non-negative fraction");
            }
            Ok(Some(v))
        }
    }
}

pub fn run(a: Args) -> Result<()> {
    let instrument = crate::util::instrument_of(&a.instrument, a.frames.first().map(|p| p.as_path()))?;
    crate::util::inputs(
        [a.cal.as_path()]
            .into_iter()
            .chain(a.frames.iter().map(|p| p.as_path()))
            .chain(a.standards.as_deref())
            .chain(crate::util::file_arg(&instrument)),
    )?;
    if !(a.threshold.is_finite() && a.threshold > 0.0) {
        bail!("--threshold {} must be a positive number of sigma", a.threshold);
    }
    let loaded = fit::files::calibration::load(&a.cal)
        .with_context(|| format!("cannot load calibration {}", a.cal.display()))?;
    // A telescope model (alone or beside a field model) goes through the whole chain.
    if loaded.telescope.is_some() {
        return run_telescope(&a, &instrument, &loaded);
    }
    if a.parang.is_some() || a.band.is_some() {
        bail!("--parang / --band: {} holds no telescope model (instpol fit-standards writes one)", a.cal.display());
    }
    let (Some(cal), _) = loaded.p_phi_models_alone()? else {
        bail!("{}: holds no field model", a.cal.display());
    };
    let inst = Instrument::load(&instrument)?;
    let (x_px, y_px) = match a.coords {
        crate::cmd::correct::Coords::Pixel => (a.x, a.y),
        crate::cmd::correct::Coords::Arcmin => inst.arcmin_to_pixel(a.x, a.y),
    };
    let (name, expected) = expected_star(&a, &cal.filter)?;
    let opts = validate_options(&a)?;
    let r = validate_star(cal, &inst, &a.frames, x_px, y_px, (&name, expected), &opts)?;
    if r.validation.extrapolated {
        eprintln!(
            "warning: the star lies outside the calibrated field; the prediction is extrapolated (errors inflated)"
        );
    }
    if a.json {
        crate::util::print_json(&r)?;
    } else {
        super::validate_text::print_report(&r, &a.cal);
    }
    // A check that ran and failed exits 1 (not 0, not 2): a script can trust the code alone.
    let v = &r.validation;
    if !v.pass {
        return Err(crate::util::CheckFailed(format!(
            "FAIL: {} differs from the calibration's prediction by {:.2} sigma (corrected: {:.2} sigma; threshold {} sigma)",
            r.star, v.residual_sigma, v.corrected_residual_sigma, v.threshold
        ))
        .into());
    }
    Ok(())
}

/// The measuring and judging options of the arguments.
fn validate_options(a: &Args) -> Result<ValidateOptions> {
    Ok(ValidateOptions {
        aperture: Aperture { radius_px: a.aperture, annulus: parse_annulus(&a.annulus)? },
        threshold: a.threshold,
        model_error: parse_model_error(&a.model_error)?,
        allow_extrapolation: a.allow_extrapolation,
        read: a.frame.read_options()?,
    })
}

/// The named standard's expected polarization in `band` (unpolarized when none is named). A
/// --standards file is read (and so checked) even when no --star is named.
fn expected_star(a: &Args, band: &str) -> Result<(String, Expected)> {
    let list = match &a.standards {
        Some(p) => Some(Standards::load(p)?),
        None => None,
    };
    Ok(match &a.star {
        None => ("unpolarized".to_string(), Expected::ZERO),
        Some(n) => {
            let list = match list {
                Some(l) => l,
                None => Standards::builtin()?,
            };
            let s = list.star(n)?;
            (s.name.clone(), s.expected(band)?)
        }
    })
}

/// `validate` with a telescope calibration: the track from the headers (or --parang), the
/// star measured, corrected through the chain and judged
/// (fit::telescope::validate::validate_telescope).
fn run_telescope(a: &Args, instrument: &str, loaded: &fit::files::calibration::CalibrationFile) -> Result<()> {
    use fit::telescope::validate::ValidateError;
    let inst = Instrument::load(instrument)?;
    let given = a.parang.as_deref().map(crate::util::parse_parang).transpose()?;
    let px = match a.coords {
        crate::cmd::correct::Coords::Pixel => (a.x, a.y),
        crate::cmd::correct::Coords::Arcmin => inst.arcmin_to_pixel(a.x, a.y),
    };
    let opts = validate_options(a)?;
    let expected = |band: &str| expected_star(a, band).map_err(|e| fit::Error::Input(format!("{e:#}")));
    let v = fit::telescope::validate::validate_telescope(
        loaded,
        &inst,
        &a.frames,
        px,
        given,
        a.band.as_deref(),
        expected,
        &opts,
    )
    .map_err(|e| match e {
        ValidateError::Instrument { calibration, frames } => anyhow::anyhow!(
            "{} is for instrument {calibration} but the frames are read as instrument {frames} (--instrument)",
            a.cal.display()
        ),
        ValidateError::NoAngleKeywords(name) => anyhow::anyhow!(
            "instrument {name} has no [telescope] section naming the header keywords of the parallactic angle: give --parang START[,END] (deg)"
        ),
        ValidateError::Headers(e) => anyhow::Error::new(e).context(
            "the parallactic angle of the frames (the telescope model needs it): fix the headers or give --parang START[,END] (deg)",
        ),
        ValidateError::Band(e, filter) => crate::util::band_choice_error(e, &a.cal, Some(&filter)),
        ValidateError::Other(fit::Error::Input(m)) => anyhow::anyhow!(m),
        e => anyhow::Error::new(e),
    })?;
    let (r, filter) = (&v.result, &v.filter);
    let (name, band) = (&r.star, &r.band);
    if !v.band_is_filter {
        eprintln!("warning: the frames are in filter {filter} but the telescope model's band is {band}");
    }
    for w in &r.warnings {
        eprintln!("warning: {w}");
    }
    if a.json {
        crate::util::print_json(r)?;
    } else {
        super::validate_text::print_chain(r, name, band, px, a.frames.len(), &a.cal);
    }
    if !r.pass {
        return Err(crate::util::CheckFailed(format!(
            "FAIL: {name} corrected through the telescope model is {:.2} sigma from its expected polarization (threshold {} sigma)",
            r.corrected_residual_sigma, r.threshold
        ))
        .into());
    }
    Ok(())
}
