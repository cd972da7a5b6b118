//! `instpol zero-angle`: the HWP zero angle of a filter from a polarized standard in frames.

use anyhow::{bail, Result};
use fit::zeroangle::{read_measured, MeasuredStandard, Sense, ZeroAngleReport};
use skyfield::photometry::{layout_for, photometry_with, Aperture, PhotOptions};
use skyfield::reduce::FrameSet;
use std::path::PathBuf;

/// Measure polarized standard stars in frames and compare their chi with the catalogued ones:
/// the difference is the HWP zero angle of the filter (the angle to add to a measured chi,
/// paper section HWP), printed as the line to put in the instrument file's filter entry.
/// The chi measured here ignores any zero angle the instrument file already has, so the
/// result replaces it.
///
/// One standard: `--x --y` with `--star NAME` (from the built-in list or --standards FILE) or
/// `--chi-deg`. Several standards in the same frames (a standard field, or a cluster with
/// published angles): `--standard X,Y:NAME` or `--standard X,Y:CHI+-SIGMA`, repeated. Their
/// offsets are averaged on the circle of period 180 deg, weighted by their errors; the output
/// gives the propagated error and the scatter-based one (times sqrt(chi2/dof)), each star's
/// pull against the mean of the OTHER stars, the star that disagrees with the others (pull >
/// 3, three or more stars: named and left out of the mean while most stars remain), and the
/// sense of the angle (decided when the stars' chi differ: counter-clockwise as the IAU, or
/// mirrored). Beside it, when the stars' catalogued P is known (stars of the list, or a
/// p_catalogue column), the polarimetric efficiency: measured P over catalogued P, with its
/// error (the instrument's constant (q0, u0) is not taken off here; `instpol efficiency` does).
///
/// Standards measured in separate runs (other nights, other fields) are combined with
/// `--measured FILE`, repeated: the --json output of an earlier zero-angle run, or a table
/// (.csv, .fits, .ecsv, .vot) with columns label, chi_measured_deg, sigma_chi_measured_deg,
/// chi_catalogue_deg, sigma_chi_catalogue_deg (optional: filter, x, y, p_measured,
/// sigma_p_measured, p_catalogue, sigma_p_catalogue). Frames are then optional.
///
/// Examples:
///   instpol zero-angle std/*.fits --instrument fors1 --x 1024 --y 90 --star "Hiltner 652"
///   instpol zero-angle field/*.fits --instrument calcite \
///       --standard "150,200:136+-0.05" --standard "300,600:12+-0.1" --standard "500,300:70+-0.1"
///   instpol zero-angle --measured night1.json --measured night2.json --json
#[derive(clap::Args)]
pub struct Args {
    /// Frame files (FITS) of the standard(s).
    #[arg(required_unless_present = "measured")]
    pub frames: Vec<PathBuf>,
    /// Standards measured before: a zero-angle --json output or a table (see above), repeated.
    #[arg(long, value_name = "FILE")]
    pub measured: Vec<PathBuf>,
    /// The filter, when no frame or file names it (a table without a filter column).
    #[arg(long)]
    pub filter: Option<String>,
    /// Standard's x, y: 0-based pixel of its ordinary image (one standard).
    #[arg(long, allow_hyphen_values = true, requires = "y")]
    pub x: Option<f64>,
    /// Standard's y (0-based px, as --x).
    #[arg(long, allow_hyphen_values = true, requires = "x")]
    pub y: Option<f64>,
    /// The standard, by name, from the built-in list (or --standards FILE).
    #[arg(long)]
    pub star: Option<String>,
    /// Several standards: "X,Y:NAME" (a star of the list) or "X,Y:CHI_DEG+-SIGMA_DEG", repeated.
    #[arg(long = "standard", value_name = "X,Y:NAME|X,Y:CHI+-SIGMA", conflicts_with_all = ["x", "star", "chi_deg"])]
    pub standard: Vec<String>,
    /// A standards file (TOML, the format of instruments/standards.toml).
    #[arg(long)]
    pub standards: Option<PathBuf>,
    /// Or the catalogued angle (deg) and its error, when the star is not in the list.
    #[arg(long, allow_hyphen_values = true)]
    pub chi_deg: Option<f64>,
    /// The error of --chi-deg (deg).
    #[arg(long, default_value_t = 0.1)]
    pub sigma_chi_deg: f64,
    /// Aperture radius (px).
    #[arg(long, default_value_t = 8.0)]
    pub aperture: f64,
    /// Background annulus inner,outer radius (px).
    #[arg(long, default_value = "12,20")]
    pub annulus: String,
    /// Instrument: built-in name or path to an instrument TOML.
    /// Default: the built-in instrument the first file's INSTRUME keyword names (said on
    /// stderr); a file without one, or of no built-in instrument, is refused.
    #[arg(long)]
    pub instrument: Option<String>,
    /// Print JSON.
    #[arg(long)]
    pub json: bool,
    #[command(flatten)]
    pub frame: crate::cmd::frame_opts::FrameOpts,
}

/// A standard to measure: position and catalogued angle (deg) with its error.
struct Std {
    label: String,
    x: f64,
    y: f64,
    chi: f64,
    sigma: f64,
    /// The catalogued P and its error (fractions), for a star of the list.
    p: Option<(f64, f64)>,
}

/// The catalogued chi of a named star in `filter`, and its P.
fn catalogued(
    list: &fit::standards::Standards,
    name: &str,
    filter: &str,
) -> Result<(String, f64, f64, Option<(f64, f64)>)> {
    let star = list.star(name)?;
    let b = star.band(filter)?;
    match fit::response::Truth::of_star(star, filter)? {
        fit::response::Truth::Polarized { p, sigma_p, chi_deg, sigma_chi_deg } => {
            Ok((star.name.clone(), chi_deg, sigma_chi_deg, Some((p, sigma_p))))
        }
        _ => bail!(
            "{} has no catalogued chi in {} ({}): a zero angle needs a polarized standard",
            star.name,
            filter,
            b.source
        ),
    }
}

/// Parse `--standard X,Y:NAME` or `X,Y:CHI+-SIGMA`.
fn parse_standard(spec: &str, list: &dyn Fn() -> Result<fit::standards::Standards>, filter: &str) -> Result<Std> {
    let bad = || {
        anyhow::anyhow!("--standard '{spec}': expected X,Y:NAME or X,Y:CHI_DEG+-SIGMA_DEG, e.g. 150,200:Hiltner 652 or 150,200:136+-0.05")
    };
    let (pos, what) = spec.split_once(':').ok_or_else(bad)?;
    let xy: Option<Vec<f64>> = pos.split(',').map(|t| t.trim().parse().ok()).collect();
    let Some([x, y]) = xy.as_deref().and_then(|v| <[f64; 2]>::try_from(v).ok()) else { return Err(bad()) };
    let what = what.trim();
    let num = what.replace('±', "+-");
    let angle = match num.split_once("+-") {
        Some((c, s)) => {
            Some((c.trim().parse::<f64>().map_err(|_| bad())?, s.trim().parse::<f64>().map_err(|_| bad())?))
        }
        None => what.parse::<f64>().ok().map(|c| (c, f64::NAN)),
    };
    let (label, chi, sigma, p) = match angle {
        Some((_, s)) if s.is_nan() => {
            bail!("--standard '{spec}': give the catalogued angle with its error, CHI+-SIGMA")
        }
        Some((c, s)) => (format!("chi {c} deg at ({x}, {y})"), c, s, None),
        None if what.is_empty() => return Err(bad()),
        None => catalogued(&list()?, what, filter)?,
    };
    Ok(Std { label, x, y, chi, sigma, p })
}

/// Measure the standards given on the command line in the frames: their rows and the filter.
fn measure_frames(a: &Args, inst: &instrument::Instrument) -> Result<(String, Vec<MeasuredStandard>)> {
    let annulus = crate::util::parse_radii(&a.annulus)?;
    let frames = skyfield::reduce::read_frames_with(&a.frames, inst, &a.frame.read_options()?, &|| {})?;
    let set = FrameSet::from_frames(frames, inst, true)?;
    for w in &set.warnings {
        eprintln!("warning: {w}");
    }
    let list = || -> Result<fit::standards::Standards> {
        Ok(match &a.standards {
            Some(p) => fit::standards::Standards::load(p)?,
            None => fit::standards::Standards::builtin()?,
        })
    };
    let stds: Vec<Std> = if !a.standard.is_empty() {
        a.standard.iter().map(|s| parse_standard(s, &list, &set.filter)).collect::<Result<_>>()?
    } else {
        let (Some(x), Some(y)) = (a.x, a.y) else {
            bail!("give the standard's position by --x --y (one star) or --standard X,Y:NAME (repeated)")
        };
        let (label, chi, sigma, p) = match (&a.star, a.chi_deg) {
            (Some(name), None) => catalogued(&list()?, name, &set.filter)?,
            (None, Some(c)) => (format!("chi {c} deg at ({x}, {y})"), c, a.sigma_chi_deg, None),
            _ => bail!("give the standard either by --star NAME or by --chi-deg (not both)"),
        };
        vec![Std { label, x, y, chi, sigma, p }]
    };
    for s in &stds {
        if !(s.chi.is_finite() && s.sigma.is_finite() && s.sigma >= 0.0 && s.sigma < 90.0) {
            bail!(
                "standard {}: catalogued chi {} +- {} deg: need a finite angle and an error in [0, 90) deg",
                s.label,
                s.chi,
                s.sigma
            );
        }
    }
    let g = layout_for(&set, inst)?;
    let files: Vec<&std::path::Path> = a.frames.iter().map(|p| p.as_path()).collect();
    let sky_pa = skyfield::sky_angle::of_set(&files, inst)?;
    let ap = Aperture { radius_px: a.aperture, annulus: Some(annulus) };
    let mut rows = Vec::with_capacity(stds.len());
    for s in stds {
        let ph = photometry_with(&set, &g, s.x, s.y, &ap, &PhotOptions::default())
            .map_err(|e| anyhow::anyhow!("standard {}: {e}", s.label))?;
        let r = ph.reduction;
        let mut m = MeasuredStandard::from_frames(
            s.label,
            (s.x, s.y),
            (r.p, r.sigma_p),
            (r.chi, r.sigma_chi),
            s.chi,
            s.sigma,
            sky_pa,
        )?;
        (m.p_catalogue, m.sigma_p_catalogue) = (s.p.map(|p| p.0), s.p.map(|p| p.1));
        rows.push(m);
    }
    Ok((set.filter.clone(), rows))
}

pub fn run(a: Args) -> Result<()> {
    // The instrument reads frames; --measured tables alone need none.
    let instrument = match a.frames.first() {
        Some(first) => crate::util::instrument_of(&a.instrument, Some(first.as_path()))?,
        None => a.instrument.clone().unwrap_or_default(),
    };
    crate::util::inputs(
        a.frames
            .iter()
            .map(|p| p.as_path())
            .chain(a.measured.iter().map(|p| p.as_path()))
            .chain(crate::util::file_arg(&instrument))
            .chain(a.standards.as_deref()),
    )?;
    // A standards file given is read, and so checked, even when no star is looked up in it:
    // a damaged or mistaken file must not pass because this run did not need it.
    if let Some(p) = &a.standards {
        fit::standards::Standards::load(p)?;
    }
    // Options that read frames would be ignored without a word when only --measured files are
    // given (a broken --bias passed with exit 0).
    if a.frames.is_empty() {
        if let Some(opt) = a.frame.first_given() {
            bail!(
                "{opt} applies to frames, and none are given (only --measured files): leave it out or give the frames"
            );
        }
    }
    // Every filter named (frames, files, --filter) must be one: a zero angle is per filter.
    let mut filters: Vec<(String, String)> = a.filter.iter().map(|f| (f.clone(), "--filter".to_string())).collect();
    let mut rows: Vec<MeasuredStandard> = Vec::new();
    let mut frames_inst = None;
    if !a.frames.is_empty() {
        let inst = instrument::Instrument::load(&instrument)?;
        if inst.telescope.as_ref().is_some_and(|t| t.focus == instrument::telescope::Focus::Nasmyth) {
            // The M3's polarization and its turn of a polarized star's angle change with the
            // parallactic angle, and a Nasmyth telescope model's fitted offset already holds a
            // constant turn (fit::telescope::cal): the offset measured here mixes the two.
            eprintln!(
                "WARNING: instrument {} sits at a Nasmyth focus: the tertiary mirror adds polarization and turns a polarized star's angle by an amount that changes with the parallactic angle, so the offset measured here holds the mirror's turn at these frames' angles besides the plate's zero angle. Fit the mirror with instpol fit-standards (its offset then holds the constant turn) rather than put this value in the instrument file",
                inst.name
            );
        }
        let (f, r) = measure_frames(&a, &inst)?;
        filters.push((f, "the frames".into()));
        rows.extend(r);
        frames_inst = Some(inst);
    } else if a.x.is_some() || a.star.is_some() || !a.standard.is_empty() || a.chi_deg.is_some() {
        bail!("--x/--y, --star, --standard and --chi-deg name stars in frames: give the frames too (or only --measured files)");
    }
    for p in &a.measured {
        let (f, r) = read_measured(p).map_err(|e| anyhow::anyhow!("--measured {e}"))?;
        if let Some(f) = f {
            filters.push((f, format!("--measured {}", p.display())));
        }
        rows.extend(r);
    }
    let filter = fit::zeroangle::one_filter(&filters, frames_inst.as_ref()).map_err(|e| match e {
        fit::zeroangle::FilterError::None => {
            anyhow::anyhow!("no filter is named by the --measured files: give it with --filter NAME")
        }
        e => anyhow::anyhow!("{e}"),
    })?;
    let (o, z) = ZeroAngleReport::combine(filter, rows)?;
    let o = o.with_product(frames_inst.as_ref());
    let zd = o.zero_angle_deg;
    for &k in &z.excluded {
        eprintln!(
            "warning: standard {} disagrees with the others (pull {:.1} > {} against their mean): left out of the zero angle; check its identification and catalogue value",
            o.standards[k].measured.label,
            z.pulls[k],
            fit::zeroangle::OUTLIER_PULL
        );
    }
    if let Some(c) = o.chi2_dof {
        if c > 4.0 && o.outlier.is_none() {
            eprintln!(
                "warning: the standards scatter beyond their errors (chi2/dof = {c:.1}): quote the scatter-based error {:.2} deg",
                o.sigma_scatter_zero_angle_deg.unwrap_or(f64::NAN)
            );
        }
    }
    if a.json {
        crate::util::print_json(&o)?;
    } else {
        for star in &o.standards {
            let s = &star.measured;
            let p = match (s.p_measured, s.sigma_p_measured) {
                (Some(p), Some(sp)) => format!(" (P = {:.3} +- {:.3} %)", 100.0 * p, 100.0 * sp),
                _ => String::new(),
            };
            outln!(
                "{}: measured chi = {:.2} +- {:.2} deg{p}, catalogue {:.2} +- {:.2} deg, offset {:.2} deg (pull {:+.1}){}",
                s.label,
                s.chi_measured_deg,
                s.sigma_chi_measured_deg,
                s.chi_catalogue_deg,
                s.sigma_chi_catalogue_deg,
                star.offset_deg,
                star.pull,
                if star.excluded { "  LEFT OUT" } else { "" }
            );
        }
        out!(
            "filter {}: HWP zero angle {zd:.2} +- {:.2} deg (to add to a measured chi)",
            o.filter,
            o.sigma_zero_angle_deg
        );
        match (o.sigma_scatter_zero_angle_deg, o.chi2_dof) {
            (Some(s), Some(c)) => {
                outln!("; from the scatter +- {s:.2} deg (chi2/dof = {c:.2}, {} stars)", o.n_standards)
            }
            _ => outln!(),
        }
        match o.sense {
            Sense::Undetermined => outln!("sense of the angle: undetermined (one standard, or standards of one chi); assumed counter-clockwise (IAU)"),
            Sense::Iau => outln!("sense of the angle: counter-clockwise on the sky (IAU), as assumed"),
            Sense::Mirrored => outln!("sense of the angle: MIRRORED (chi_true = offset - chi_measured): the instrument's angles run clockwise"),
        }
        if let Some(e) = &o.efficiency {
            outln!(
                "polarimetric efficiency (measured P over catalogued P): {:.4} +- {:.4} ({} stars; (q0, u0) not taken off: see instpol efficiency)",
                e.efficiency,
                e.sigma_efficiency,
                e.n_standards
            );
        }
        outln!("in the instrument file, filter {}:  {}", o.filter, o.instrument_file_line);
    }
    Ok(())
}
