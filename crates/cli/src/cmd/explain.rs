//! `instpol explain`: which physics explains a fitted Mueller field. All
//! numbers come from `fit::mueller_field::explain`; this file parses, prints and plots.

use anyhow::{anyhow, bail, Result};
use fit::mueller_field::explain::{explain, Cause, Context, Explanation, Target};
use fit::mueller_field::Smooth;
use std::path::PathBuf;

/// Compare a Mueller field fitted by `calibrate-mueller` with candidate physical causes and say
/// which explains it best, with the numbers: the collimator's polarization ray trace (its
/// amplitude free; chi^2 as computed too), a stressed lens (retardance at --radius-arcmin,
/// stress centre, axis), a tilted half-wave plate (tilt, azimuth), a wedged half-wave plate
/// (retardance error and its gradient) and a polarizing half-wave plate (diattenuation,
/// angle), against "nothing beyond the diattenuation".
///
/// The diattenuation (the paper's p, phi) is a nuisance every candidate may sit on: the
/// comparison uses what a diattenuation cannot make (retardance, rotation, depolarization, or
/// the Q, U block of a general fit) with its covariance. Each candidate is fitted by least
/// squares; the table gives its parameters with 1-sigma errors, chi^2/dof and delta BIC
/// (BIC = chi^2 + k ln n). Candidates within 10 of the best BIC are reported as not told
/// apart: no winner is picked then. The plate causes act on the modulation and are compared
/// through the demodulation at --hwp-angles. A fit with the diattenuation alone is refused
/// (exit code 2): there is nothing to compare. Runs in seconds (progress bar).
///
/// Example: instpol calibrate-mueller --field b1.fits:6.45:68.4 --field b2.fits:4:10
/// --field b3.fits:8:130 --out mueller_B.fits && instpol explain mueller_B.fits
/// --instrument fors1 --band B --plot explain_B.png
#[derive(clap::Args)]
pub struct Args {
    /// The Mueller field written by `calibrate-mueller --out`: the calibration file (FITS,
    /// MODEL = 'MUELLER') or the JSON (instpol-mueller-field-v1), told apart by content. A
    /// field in the radial or interp form is compared through the file's per-bin fits.
    pub mueller_cal: PathBuf,
    /// Instrument name (built-in: fors1) or path to an instrument TOML; its [optics] give the
    /// ray-trace candidate (left out, with a note, when it has none). Default: the built-in
    /// instrument the calibration file records (said on stderr); a field that records none, or
    /// an instrument that is no built-in one, needs it given.
    #[arg(long)]
    pub instrument: Option<String>,
    /// Filter whose effective wavelength the ray trace uses.
    #[arg(long, default_value = "B")]
    pub band: String,
    /// HWP angles of the data (deg, comma-separated); default the full turn 0, 22.5, ..., 337.5.
    #[arg(long)]
    pub hwp_angles: Option<String>,
    /// Angular magnification at the plate (telescope aperture over collimated beam diameter)
    /// for the tilted plate: a field angle becomes this times larger at the plate. 0: every
    /// field point sees the same tilt. Give your instrument's value.
    #[arg(long, default_value_t = 0.0)]
    pub magnification: f64,
    /// Radius (arcmin) at which the stressed lens's retardance is reported (the field radius).
    #[arg(long, default_value_t = 3.4)]
    pub radius_arcmin: f64,
    /// Candidates, comma-separated (diattenuation_only, raytrace, stressed_lens, tilted_hwp,
    /// wedged_hwp, polarizing_hwp) or all.
    #[arg(long, default_value = "all")]
    pub causes: String,
    /// Number of grid points per side (n x n) inside the field's bounds on which candidates
    /// are projected onto the field's polynomial basis.
    #[arg(long, default_value_t = 16)]
    pub grid: usize,
    /// Print JSON instead of a table.
    #[arg(long)]
    pub json: bool,
    /// Draw delta BIC per candidate into this image (.png or .svg, by the extension).
    #[arg(long)]
    pub plot: Option<PathBuf>,
}

#[derive(serde::Serialize)]
struct ParamOut {
    name: &'static str,
    value: Option<f64>,
    sigma_value: Option<f64>,
}

#[derive(serde::Serialize)]
struct CauseOut {
    cause: &'static str,
    params: Vec<ParamOut>,
    chi2: Option<f64>,
    dof: usize,
    chi2_dof: Option<f64>,
    delta_bic: Option<f64>,
    chi2_as_computed: Option<f64>,
    note: Option<String>,
}

#[derive(serde::Serialize)]
struct Report {
    input: PathBuf,
    instrument: String,
    band: String,
    hwp_angles_deg: Vec<f64>,
    n_data: usize,
    compared: Vec<&'static str>,
    causes: Vec<CauseOut>,
    best: &'static str,
    not_told_apart: Vec<&'static str>,
    adequate: bool,
    verdict: String,
    notes: Vec<String>,
    output: Option<PathBuf>,
    /// What was explained: the instrument file the candidates were built from, the band, the
    /// run's inputs.
    product: skyfield::provenance::Product,
}

fn finite(v: f64) -> Option<f64> {
    v.is_finite().then_some(v)
}

pub fn run(a: Args) -> Result<()> {
    crate::util::inputs(
        std::iter::once(a.mueller_cal.as_path()).chain(a.instrument.as_deref().and_then(crate::util::file_arg)),
    )?;
    if let Some(p) = &a.plot {
        crate::util::check_output(p)?;
        crate::plot::ImageFormat::of(p)?;
    }
    if !(4..=64).contains(&a.grid) {
        bail!("--grid {} must be in 4..=64", a.grid);
    }
    let which = Cause::parse_list(&a.causes).map_err(|e| anyhow!("--causes '{}': {e}", a.causes))?;
    let angles_deg = hwp_angles(a.hwp_angles.as_deref())?;
    let what = a.mueller_cal.display().to_string();
    let loaded = fit::mueller_field::cal::load_field(&a.mueller_cal).map_err(|e| anyhow!("{e}"))?;
    let name = match (&a.instrument, &loaded.of) {
        (Some(n), _) => n.clone(),
        (None, Some((recorded, _))) => {
            let b = instrument::builtin_for_keyword(recorded).ok_or_else(|| {
                anyhow!(
                    "{what} records instrument {recorded}, which is no built-in one: give its file with --instrument"
                )
            })?;
            eprintln!("note: instrument {b}, which {what} records; give --instrument to use another file");
            b.to_string()
        }
        (None, None) => bail!("{what} records no instrument (the JSON form): give it with --instrument"),
    };
    let inst = instrument::Instrument::load(&name)?;
    loaded.check_for(&inst, &a.band, &what).map_err(|e| anyhow!("{e}"))?;
    let (mf, per_bin) = (loaded.field, loaded.per_bin);
    let mut notes = Vec::new();
    let target = match &mf.smooth {
        Smooth::Poly => Target::smooth(&mf, a.grid, &what),
        form if !per_bin.is_empty() => {
            notes.push(format!(
                "the field is in the {} form: the candidates are compared with its {} per-bin fits",
                form.name(),
                per_bin.len()
            ));
            Target::per_bin(&per_bin, &what)
        }
        form => bail!(
            "{what}: the field is in the {} form and the file holds no per-bin fits to compare with: write the calibration as FITS (calibrate-mueller --out X.fits keeps them) or fit the poly form",
            form.name()
        ),
    }
    .map_err(|e| anyhow!("{e}"))?;
    let rad: Vec<f64> = angles_deg.iter().map(|d| d.to_radians()).collect();
    let mut ctx = Context::new(&rad, a.magnification, a.radius_arcmin)
        .map_err(|e| anyhow!("--hwp-angles / --magnification / --radius-arcmin: {e}"))?;
    let lam = inst.filter(&a.band)?.lambda_eff_nm;
    if which.contains(&Cause::Raytrace) {
        match inst.optics.as_ref() {
            Some(presc) => {
                let c = presc.compile(lam)?;
                let sampling = mueller::raytrace::Sampling::from_rays(64);
                ctx.raytrace = Some(Box::new(move |x, y| {
                    c.field_point(x, y, &sampling, None)
                        .ok()
                        .map(|fp| mueller::linear::LinearBlock::of_mueller(&fp.mueller))
                }));
            }
            None => {
                notes.push(format!("instrument {} has no [optics]: the ray-trace candidate is left out", inst.name))
            }
        }
    }
    let bar = (!a.json).then(|| {
        let b = indicatif::ProgressBar::new_spinner();
        b.set_message(format!("fitting {} candidates", which.len()));
        b.enable_steady_tick(std::time::Duration::from_millis(200));
        b
    });
    let e: Explanation = explain(&target, &ctx, &which).map_err(|e| anyhow!("{e}"))?;
    if let Some(b) = bar {
        b.finish_and_clear();
    }
    let rep = Report {
        input: a.mueller_cal.clone(),
        instrument: inst.name.clone(),
        band: a.band.clone(),
        hwp_angles_deg: angles_deg,
        n_data: e.n_data,
        compared: e.compared.clone(),
        causes: e
            .fits
            .iter()
            .map(|f| CauseOut {
                cause: f.cause.name(),
                params: f
                    .params
                    .iter()
                    .map(|p| ParamOut { name: p.name, value: finite(p.value), sigma_value: finite(p.sigma) })
                    .collect(),
                chi2: finite(f.chi2),
                dof: f.dof,
                chi2_dof: finite(f.chi2_dof),
                delta_bic: finite(f.delta_bic),
                chi2_as_computed: f.chi2_as_computed,
                note: f.note.clone(),
            })
            .collect(),
        best: e.best.name(),
        not_told_apart: e.not_told_apart.iter().map(|c| c.name()).collect(),
        adequate: e.adequate,
        verdict: e.verdict.clone(),
        notes,
        output: a.plot.clone(),
        product: skyfield::provenance::Product::of_instrument(&inst, &a.band, None).with_run_inputs(),
    };
    if let Some(p) = &a.plot {
        super::explain_plot::draw(p, &e)?;
    }
    if a.json {
        return crate::util::print_json(&rep);
    }
    print_explanation(&rep, &what);
    Ok(())
}

/// The plate angles the candidates are computed at (deg): the given list, else 16 over a turn.
fn hwp_angles(given: Option<&str>) -> Result<Vec<f64>> {
    let angles_deg: Vec<f64> = match given {
        None => (0..16).map(|k| 22.5 * k as f64).collect(),
        Some(s) => s
            .split(',')
            .map(|w| w.trim().parse::<f64>().ok().filter(|v| v.is_finite()))
            .collect::<Option<Vec<_>>>()
            .ok_or_else(|| anyhow!("--hwp-angles '{s}': not a comma-separated list of numbers (deg)"))?,
    };
    if angles_deg.len() > 1024 {
        bail!("--hwp-angles: {} angles, at most 1024", angles_deg.len());
    }
    stokes::check_degrees(&angles_deg).map_err(|e| anyhow!("--hwp-angles holds {e}: give them in degrees"))?;
    Ok(angles_deg)
}

/// The report as text (`what`: the calibration's name).
fn print_explanation(rep: &Report, what: &str) {
    outln!("{}: {} numbers compared ({})", what, rep.n_data, rep.compared.join(", "));
    outln!("{:<20} {:>10} {:>5} {:>9} {:>10}  parameters", "cause", "chi2", "dof", "chi2/dof", "dBIC");
    for c in &rep.causes {
        let ps: Vec<String> = c
            .params
            .iter()
            .map(|p| match (p.value, p.sigma_value) {
                (Some(v), Some(s)) => format!("{} = {v:.4} +- {s:.4}", p.name),
                (Some(v), None) => format!("{} = {v:.4} (unconstrained)", p.name),
                (None, _) => format!("{} = none", p.name),
            })
            .collect();
        outln!(
            "{:<20} {:>10.2} {:>5} {:>9.3} {:>10.1}  {}",
            c.cause,
            c.chi2.unwrap_or(f64::INFINITY),
            c.dof,
            c.chi2_dof.unwrap_or(f64::NAN),
            c.delta_bic.unwrap_or(f64::INFINITY),
            ps.join(", ")
        );
        if let Some(x) = c.chi2_as_computed {
            outln!("{:<20} chi2 of the ray trace as computed (amplitude 1): {x:.2}", "");
        }
        if let Some(n) = &c.note {
            outln!("{:<20} note: {n}", "");
        }
    }
    for n in &rep.notes {
        outln!("note: {n}");
    }
    outln!("verdict: {}", rep.verdict);
    if let Some(p) = &rep.output {
        outln!("wrote {}", p.display());
    }
}
