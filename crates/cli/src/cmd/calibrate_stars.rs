//! `instpol calibrate-stars`: star catalogs of a dense field (one per dithered pointing) to a
//! calibration file, through `fit::models::stars_field`.

use anyhow::{bail, Context, Result};
use fit::models::stars_field::{read_catalogs, stars_field, stars_meta, Interstellar, StarsOptions, StarsSummary};
use std::path::PathBuf;

/// Measure the instrumental polarization over the field from many field stars, where no empty
/// field of known sky polarization is at hand: the catalogs written by `instpol catalog` of one
/// or several dithered pointings of a dense field. Each star's measured (q, u) is the
/// instrument's field at its detector position (the radial model of `instpol calibrate`, same
/// options) plus one interstellar (q, u) common to the stars (fitted, zero or given); a star
/// seen in several pointings is one star (matched by sky position: field position plus the
/// pointing's offset). Stars polarized in themselves are rejected by their residual chi^2 over
/// their measurements and named; the field is refitted without them. The calibration file is
/// the one `instpol calibrate` writes (IP SOURCE = field stars), with the same plots.
///
/// A separate command rather than `calibrate --stars`: its inputs are star tables, not frames
/// of an empty field, and it needs neither the sky polarization nor the bin size that
/// `calibrate` requires.
///
/// Example: instpol calibrate-stars p1.ecsv p2.ecsv p3.ecsv p4.ecsv --filter V
/// --offset 0,0 --offset 0.6,0.25 --offset -0.35,0.55 --offset 0.3,-0.6 --out cal_V.fits
#[derive(clap::Args)]
pub struct Args {
    /// Star catalogs (`instpol catalog --out`; CSV, ECSV, FITS or VOTable), one per pointing,
    /// each with the HWP zero-angle column (hwp_chi_offset_deg) its q, u carry.
    pub catalogs: Vec<PathBuf>,
    /// Built-in instrument name or instrument TOML file. Default: the built-in one the catalogs
    /// say they are of (their INSTRUME keyword, said on stderr); catalogs that do not say are
    /// taken as FORS1's, with a warning.
    #[arg(long)]
    pub instrument: Option<String>,
    /// Use catalogs whose keywords say another instrument or filter than --instrument,
    /// --filter (refused otherwise, naming both); the calibration records the ones given.
    #[arg(long)]
    pub allow_mismatch: bool,
    /// The filter of the catalogs (a name of the instrument's filter table, e.g. V).
    #[arg(long)]
    pub filter: String,
    /// Offset of each pointing in ARCMIN along the detector axes, "DX,DY", one per catalog in
    /// their order: a star at field position (x, y) in that catalog is at (x + DX, y + DY) in
    /// the first catalog's. Absent: measured from the stars the catalogs share.
    #[arg(long, value_name = "DX,DY", allow_hyphen_values = true)]
    pub offset: Vec<String>,
    /// The interstellar polarization common to the stars: free (fitted, the default), zero,
    /// or given as "P,CHI" (P in PERCENT, chi in degrees).
    #[arg(long, default_value = "free", value_name = "free|zero|P,CHI")]
    pub interstellar: String,
    /// A star whose residual chi^2 has an upper-tail probability below this (a probability,
    /// 0..1) is rejected as polarized: the expected false-rejection rate per unpolarized star.
    #[arg(long, default_value_t = 1e-3)]
    pub reject_alpha: f64,
    /// Two measurements closer than this on the sky (ARCSEC) are one star.
    #[arg(long, default_value_t = 1.0)]
    pub match_radius: f64,
    #[command(flatten)]
    pub fit: crate::cmd::calibrate::FitArgs,
    /// Output calibration file (FITS).
    #[arg(long)]
    pub out: PathBuf,
    /// Also draw the map, profile and residual plots (PNG and SVG) into this folder.
    #[arg(long)]
    pub plots: Option<PathBuf>,
    /// Print JSON instead of a table.
    #[arg(long)]
    pub json: bool,
}

fn pair(s: &str, what: &str) -> Result<[f64; 2]> {
    let v: Vec<&str> = s.split(',').map(str::trim).collect();
    let bad = || anyhow::anyhow!("{what} '{s}': expected two numbers separated by a comma");
    if v.len() != 2 {
        return Err(bad());
    }
    let a: f64 = v[0].parse().map_err(|_| bad())?;
    let b: f64 = v[1].parse().map_err(|_| bad())?;
    if !(a.is_finite() && b.is_finite()) {
        return Err(bad());
    }
    Ok([a, b])
}

fn interstellar(s: &str) -> Result<Interstellar> {
    Ok(match s.trim().to_ascii_lowercase().as_str() {
        "free" => Interstellar::Free,
        "zero" | "none" => Interstellar::Zero,
        _ => {
            let [p, chi] = pair(s, "--interstellar").context("use free, zero or P,CHI (percent, degrees)")?;
            Interstellar::from_percent_deg(p, chi).with_context(|| format!("--interstellar '{s}'"))?
        }
    })
}

pub fn run(a: Args) -> Result<()> {
    use fit::models::stars_field::InstrumentChoice;
    let (instrument, chosen) = fit::models::stars_field::catalogs_instrument(a.instrument.as_deref(), &a.catalogs)
        .map_err(|e| anyhow::anyhow!("{e} (--instrument)"))?;
    match chosen {
        InstrumentChoice::Given => {}
        InstrumentChoice::Recorded(i) => {
            eprintln!("note: instrument {instrument}, which the catalogs say they are of (INSTRUME = '{i}')")
        }
        InstrumentChoice::Assumed => eprintln!(
            "warning: the catalogs do not say which instrument they are of (no INSTRUME keyword): taken as {instrument}; give --instrument if they are another's"
        ),
    }
    crate::util::inputs(a.catalogs.iter().map(|p| p.as_path()).chain(crate::util::file_arg(&instrument)))?;
    crate::util::check_output(&a.out)?;
    if a.catalogs.is_empty() {
        bail!("no catalogs given: list the star catalogs of the pointings (instpol catalog --out)");
    }
    let offsets = match a.offset.len() {
        0 => None,
        n if n == a.catalogs.len() => Some(a.offset.iter().map(|o| pair(o, "--offset")).collect::<Result<Vec<_>>>()?),
        n => bail!("{n} --offset for {} catalogs: give one per catalog (0,0 for the first) or none", a.catalogs.len()),
    };
    if !(a.match_radius > 0.0 && a.match_radius.is_finite()) {
        bail!("--match-radius {} arcsec must be positive", a.match_radius);
    }
    let inst = instrument::Instrument::load(&instrument)?;
    let expect = (!a.allow_mismatch).then_some((inst.name.as_str(), a.filter.as_str()));
    let (rows, z, notes) = read_catalogs(&a.catalogs, expect)?;
    let meta = stars_meta(&inst, &a.filter, z, a.catalogs.iter().map(|p| p.display().to_string()).collect());
    let opts = StarsOptions {
        calibrate: a.fit.options()?,
        interstellar: interstellar(&a.interstellar)?,
        offsets,
        match_radius_arcmin: a.match_radius / 60.0,
        reject_alpha: a.reject_alpha,
    };
    let run = stars_field(&rows, a.catalogs.len(), meta, &opts)?;
    let mut s = StarsSummary::new(&run, &rows, a.reject_alpha);
    s.warnings.splice(0..0, notes);
    for w in &s.warnings {
        eprintln!("warning: {w}");
    }
    let (file, plots) = crate::cmd::calibrate::save_and_plot(&run.run, Some(&a.out), a.plots.as_deref())?;
    s.fit.calibration_file = file;
    s.fit.plot_outputs = plots;
    if a.json {
        return crate::util::print_json(&s);
    }
    crate::cmd::calibrate::print_table(&s.fit);
    let i = &s.interstellar;
    outln!(
        "interstellar ({}): q {:.4} +- {:.4} %, u {:.4} +- {:.4} %  (P {:.4} % at {:.1} deg)",
        i.mode,
        100.0 * i.q,
        100.0 * i.sigma_q,
        100.0 * i.u,
        100.0 * i.sigma_u,
        100.0 * i.p,
        i.chi_deg
    );
    outln!(
        "{} catalogs, {} measurements of {} stars ({} seen more than once); offsets {} (arcmin): {}",
        s.n_catalogs,
        s.n_measurements,
        s.n_stars,
        s.n_stars_repeated,
        if s.offsets_measured { "measured from the stars" } else { "as given" },
        s.offsets_arcmin.iter().map(|o| format!("({:.4}, {:.4})", o[0], o[1])).collect::<Vec<_>>().join(" ")
    );
    outln!(
        "rejected as polarized: {} stars (chi^2 tail below {}; {:.2} false rejections expected)",
        s.rejected.len(),
        s.reject_alpha,
        s.expected_false_rejections
    );
    if !s.rejected.is_empty() {
        // A star is named by its first measurement: catalog (1-based) and data row (1-based).
        outln!(
            "{:>12} {:>9} {:>9} {:>3} {:>9} {:>8} {:>7} {:>9}",
            "catalog:row",
            "x (')",
            "y (')",
            "n",
            "P (%)",
            "chi",
            "P/sig",
            "p-value"
        );
        for r in &s.rejected {
            let first = r.measurements.first().map_or(String::new(), |m| format!("{}:{}", m[0], m[1] + 1));
            outln!(
                "{:>12} {:>9.4} {:>9.4} {:>3} {:>9.4} {:>8.1} {:>7.1} {:>9.2e}",
                first,
                r.x_arcmin,
                r.y_arcmin,
                r.n_measurements,
                100.0 * r.residual_p,
                r.residual_chi_deg,
                r.residual_p_sigma,
                r.p_value
            );
        }
    }
    outln!("wrote {}", a.out.display());
    Ok(())
}
