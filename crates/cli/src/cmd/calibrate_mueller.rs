//! `instpol calibrate-mueller`: the instrument's Mueller field from several sky fields of known
//! polarization, fitted jointly by `fit::mueller_field`.

use anyhow::{anyhow, bail, Context, Result};
use fit::mueller_cal::{MuellerCal, SkyField};
use fit::mueller_field::{
    fit_mueller_field, fit_per_bin, observations_of_map, CalField, Kind, MuellerField, MuellerFitOptions, Observation,
};
use std::path::PathBuf;
use stokes::stats::robust::{finite_median, Middle};

/// Fit the linear block of the pre-analyzer Mueller matrix over the field jointly to two or
/// more Stokes maps of empty fields whose sky polarization is known: the diattenuation p, phi
/// of the paper's M_I (eq:instpol) and, with --free, a linear retardance (stress
/// birefringence), a rotation of the polarization plane and a depolarization; or --general,
/// the whole 3 x 3 block. Each free parameter is a 2-D polynomial of degree --deg in the field
/// position (--smooth poly, the joint fit); --per-bin also fits every bin on its own. The
/// other smooth forms are built from the per-bin fits: --smooth radial (the paper's radial
/// family about the field origin: the diattenuation p(r) with a radial axis and the retardance
/// with a radial or tangential axis, powers 1..--deg of r; its chi2_dof says whether the field
/// is radial) and --smooth interp (natural-neighbour interpolation of the per-bin fits, no
/// value outside their hull). `instpol correct` inverts every form the same way.
///
/// Polarized standards (--stars TABLE) join the fit as points of their own known
/// polarization: stars at other angles than the sky's separate a retardance too.
///
/// One sky field gives two numbers per position: it fixes p, phi and nothing else. A
/// retardance needs >= 2 fields of different sky polarization, rotation and depolarization too
/// need >= 3 whose sky (q, u) are not on one line. The command refuses (exit code 2), naming
/// the parameters and the reason, what its inputs cannot separate, instead of printing
/// numbers. It runs in well under a second (no progress bar).
///
/// The output is a calibration file (--out CAL.fits: primary MODEL = 'MUELLER', tables MUELLER
/// and MUELLER_BINS, image MUELLER_COV; docs/calibration-file.md) that `instpol correct --cal`
/// inverts exactly for polarized targets, or the same field as JSON (--out X.json, format
/// instpol-mueller-field-v1, what `instpol plan --expected` reads).
///
/// Example: instpol calibrate-mueller --field b_sky1.fits:6.45:68.4 --field b_sky2.fits:4.0:10
/// --field b_sky3.fits:8.0:130 --free retardance --deg 4 --out mueller_B.fits
///
/// Radial form (the field's chi2_dof says whether it is radial): instpol calibrate-mueller
/// --field b_sky1.fits:6.45:68.4 --field b_sky2.fits:4.0:10 --field b_sky3.fits:8.0:130
/// --smooth radial --deg 4 --out mueller_B_radial.fits
#[derive(clap::Args)]
pub struct Args {
    /// A Stokes map (FITS written by `instpol reduce`) with its sky polarization:
    /// MAP:P_PERCENT:CHI_DEG[:SIGMA_P_PERCENT] (P in percent, chi in degrees; the optional
    /// 1-sigma uncertainty of the sky's q and u, in percent). Repeat for every field.
    #[arg(long = "field", required = true, allow_hyphen_values = true)]
    pub fields: Vec<String>,
    /// Effects fitted besides the diattenuation, comma-separated: retardance, rotation,
    /// depolarization (or "none": the paper's p, phi only).
    #[arg(long, default_value = "retardance")]
    pub free: String,
    /// Fit the general 3 x 3 block (8 parameters; needs >= 3 fields not on one line).
    #[arg(long, conflicts_with = "free")]
    pub general: bool,
    /// Degree of the smooth form: of the 2-D polynomials (poly), the highest power of r
    /// (radial); not used by interp.
    #[arg(long, default_value_t = 4)]
    pub deg: usize,
    /// Smooth form of the field: poly (joint fit of 2-D polynomials), radial or interp (both
    /// built from the per-bin fits, which the FITS output then holds).
    #[arg(long, default_value = "poly", value_parser = ["poly", "radial", "interp"])]
    pub smooth: String,
    /// Field scale (arcmin) the positions are divided by: about the field radius.
    #[arg(long, default_value_t = 3.4)]
    pub scale_arcmin: f64,
    /// Polarized standards as further inputs: a table (.csv, .ecsv, .vot or FITS) with columns
    /// x, y (or x_arcmin, y_arcmin; arcmin from the detector centre), q, u, sigma_q, sigma_u
    /// (measured, fractions), p_true (fraction) and chi_true_deg (or chi_true, deg), and
    /// optionally sigma_true (1-sigma of the true q, u, fraction). Each star is a point with its
    /// own known input polarization: stars at other angles than the sky's constrain a
    /// retardance that one sky field alone cannot.
    #[arg(long, value_name = "TABLE")]
    pub stars: Option<PathBuf>,
    /// Also fit every bin on its own and report how many bins constrain the model.
    #[arg(long)]
    pub per_bin: bool,
    /// Output: a calibration file (.fits, for `instpol correct`) or the Mueller field as JSON
    /// (.json, format instpol-mueller-field-v1).
    #[arg(long)]
    pub out: PathBuf,
    /// Print JSON instead of a table.
    #[arg(long)]
    pub json: bool,
}

fn parse_field(spec: &str) -> Result<(PathBuf, f64, f64, f64)> {
    let parts: Vec<&str> = spec.rsplitn(4, ':').collect();
    // rsplitn: the path (which may hold ':') comes last.
    let num = |s: &str, what: &str| -> Result<f64> {
        s.trim()
            .parse::<f64>()
            .ok()
            .filter(|v| v.is_finite())
            .ok_or_else(|| anyhow!("--field '{spec}': {what} '{s}' is not a number"))
    };
    let (path, p, chi, sig) = match parts.as_slice() {
        [chi, p, path] => (*path, num(p, "P_PERCENT")?, num(chi, "CHI_DEG")?, 0.0),
        [sig, chi, p, path] => match num(p, "P_PERCENT") {
            Ok(pv) => (*path, pv, num(chi, "CHI_DEG")?, num(sig, "SIGMA_P_PERCENT")?),
            // A path with a ':' and no sigma.
            Err(_) => {
                let joined = format!("{path}:{p}");
                return Ok((PathBuf::from(joined), num(chi, "P_PERCENT")?, num(sig, "CHI_DEG")?, 0.0));
            }
        },
        _ => bail!("--field '{spec}': expected MAP:P_PERCENT:CHI_DEG[:SIGMA_P_PERCENT], e.g. sky.fits:6.45:68.4"),
    };
    if !(0.0..100.0).contains(&p) || sig < 0.0 {
        bail!("--field '{spec}': P = {p} % must be in [0, 100) and the sigma >= 0");
    }
    Ok((PathBuf::from(path), p / 100.0, chi.to_radians(), sig / 100.0))
}

/// One instrument, filter and field-coordinate system (names compared case-insensitively).
fn same_setup(a: &(String, String, field::FieldCoords), b: &(String, String, field::FieldCoords)) -> bool {
    a.0.eq_ignore_ascii_case(&b.0) && a.1.eq_ignore_ascii_case(&b.1) && a.2 == b.2
}

/// The polarized standards of a `--stars` table, each a calibration "field" of one position
/// whose known input polarization is the star's (rows named in errors), in the maps' sky frame:
/// turned by the maps' zero angle `zero_angle_deg` less the one the table's q, u carry (its
/// column `hwp_chi_offset_deg`, as `instpol catalog` writes it; q, u at the plate without it).
fn star_fields(path: &std::path::Path, zero_angle_deg: f64) -> Result<Vec<CalField>> {
    let t = skyfield::table::Table::read(path, None)?;
    let (turn, _) = fit::correct::row_zero_angles(Some(zero_angle_deg), t.carried_zero_angle(path)?);
    let turn = turn.to_radians();
    let pick = |names: &[&str]| -> Result<Vec<f64>> {
        for n in names {
            if t.column(n).is_some() {
                return Ok(t.numbers(n, path)?);
            }
        }
        bail!(
            "{}: no column {} (columns: {}); need x, y (or x_arcmin, y_arcmin), q, u, sigma_q, sigma_u, p_true, chi_true_deg",
            path.display(),
            names.join(" or "),
            t.names().join(", ")
        )
    };
    let (x, y) = (pick(&["x_arcmin", "x"])?, pick(&["y_arcmin", "y"])?);
    let (q, u, sq, su) = (pick(&["q"])?, pick(&["u"])?, pick(&["sigma_q"])?, pick(&["sigma_u"])?);
    let (pt, ct) = (pick(&["p_true"])?, pick(&["chi_true_deg", "chi_true"])?);
    let st = if t.column("sigma_true").is_some() { t.numbers("sigma_true", path)? } else { vec![0.0; x.len()] };
    if x.is_empty() {
        bail!("{}: the star table has no data rows", path.display());
    }
    let mut out = Vec::with_capacity(x.len());
    for i in 0..x.len() {
        let what = format!("{} {}", path.display(), t.row_label(i));
        let vals = [x[i], y[i], q[i], u[i], sq[i], su[i], pt[i], ct[i], st[i]];
        if !(vals.iter().all(|v| v.is_finite()) && sq[i] > 0.0 && su[i] > 0.0) || st[i] < 0.0 {
            bail!("{what}: x, y, q, u, sigma_q, sigma_u, p_true, chi_true_deg, sigma_true = {vals:?}: need finite values and errors > 0");
        }
        if !(0.0..1.0).contains(&pt[i]) || q[i].hypot(u[i]) >= 1.0 {
            bail!(
                "{what}: p_true = {} and the measured P = {} must be fractions in [0, 1) (not percent)",
                pt[i],
                q[i].hypot(u[i])
            );
        }
        let m = fit::correct::to_sky_frame(
            &fit::correct::Measurement::new(x[i], y[i], q[i], u[i], sq[i], su[i], 0.0),
            turn,
        );
        let obs = Observation::new(x[i], y[i], m.qu.q, m.qu.u, m.qu.var_q, m.qu.var_u, m.qu.cov_qu);
        out.push(CalField::from_p_chi(&what, pt[i], ct[i].to_radians(), st[i], vec![obs]));
    }
    Ok(out)
}

fn kind_of(a: &Args) -> Result<Kind> {
    if a.general {
        return Ok(Kind::General);
    }
    Kind::parse_free(&a.free).map_err(|e| anyhow!("--free '{}': {e}", a.free))
}

#[derive(serde::Serialize)]
struct Param {
    name: &'static str,
    median_value: f64,
    rms_value: f64,
    median_sigma: f64,
}

#[derive(serde::Serialize)]
struct Report {
    output: PathBuf,
    n_fields: usize,
    n_stars: usize,
    n_obs: usize,
    deg: usize,
    smooth: &'static str,
    model: &'static str,
    free: Vec<&'static str>,
    chi2_dof: f64,
    condition: Option<f64>,
    parameters: Vec<Param>,
    median_p: Option<f64>,
    max_p: Option<f64>,
    median_retardance_deg: Option<f64>,
    max_retardance_deg: Option<f64>,
    n_bins_fitted: Option<usize>,
    n_bins_unconstrained: Option<usize>,
    warnings: Vec<String>,
}

/// A summary's typical value: the upper middle of the finite values, NaN when there are none.
fn typical(v: Vec<f64>) -> f64 {
    finite_median(v, Middle::Upper).unwrap_or(f64::NAN)
}

pub fn run(a: Args) -> Result<()> {
    let kind = kind_of(&a)?;
    let specs: Vec<(PathBuf, f64, f64, f64)> = a.fields.iter().map(|s| parse_field(s)).collect::<Result<_>>()?;
    crate::util::inputs(specs.iter().map(|s| s.0.as_path()).chain(a.stars.as_deref()))?;
    crate::util::check_output(&a.out)?;
    let fits_out = match a.out.extension().and_then(|e| e.to_str()).map(|e| e.to_ascii_lowercase()).as_deref() {
        Some("fits" | "fit" | "fts") => true,
        Some("json") => false,
        _ => bail!("--out {}: the extension says the format: .fits (calibration file) or .json", a.out.display()),
    };
    let mut fields = Vec::new();
    // The first map's instrument, filter and field coordinates: every field must share them.
    let mut setup: Option<(String, String, field::FieldCoords)> = None;
    // The HWP zero angle the maps record (HWPZERO): each is turned by it into the sky frame of
    // its known polarization (fit::mueller_cal module docs); one value for all of them.
    let mut zero: Option<(Option<f64>, &PathBuf)> = None;
    let says = |z: Option<f64>| z.map_or("none (taken as 0 deg)".to_string(), |z| format!("{z} deg"));
    for (path, p, chi, sig) in &specs {
        let map =
            skyfield::maps::StokesMap::read_uncorrected(path).with_context(|| format!("reading {}", path.display()))?;
        let z = map.hwp_zero_angle_deg.unwrap_or(0.0);
        match zero {
            None => zero = Some((map.hwp_zero_angle_deg, path)),
            Some((z0, first)) if z0.unwrap_or(0.0) != z => bail!(
                "{}: records an HWP zero angle of {} (HWPZERO), but {} records {}: fit the maps of one instrument and filter together",
                path.display(),
                says(map.hwp_zero_angle_deg),
                first.display(),
                says(z0)
            ),
            Some(_) => {}
        }
        let map = fit::pipeline::map_to_sky_frame(&map, z.to_radians());
        let obs = observations_of_map(&map);
        if obs.is_empty() {
            bail!("{}: the Stokes map has no valid bin", path.display());
        }
        let this = (map.instrument.clone(), map.filter.clone(), map.geometry.field_coords());
        match &setup {
            None => setup = Some(this),
            Some(s) if !same_setup(s, &this) => bail!(
                "{}: a {} {} map, but {} is {} {}: fit the fields of one instrument and filter together",
                path.display(),
                this.0,
                this.1,
                specs[0].0.display(),
                s.0,
                s.1
            ),
            Some(_) => {}
        }
        fields.push(CalField::from_p_chi(&path.display().to_string(), *p, *chi, *sig, obs));
    }
    let n_maps = fields.len();
    let zero_angle_deg = zero.and_then(|z| z.0).unwrap_or(0.0);
    if let Some(t) = &a.stars {
        fields.extend(star_fields(t, zero_angle_deg)?);
    }
    let opts = MuellerFitOptions { kind, deg: a.deg, scale_arcmin: a.scale_arcmin, ..Default::default() };
    if a.deg > 8 {
        bail!("--deg {}: at most 8", a.deg);
    }
    let per_bin = if a.per_bin || a.smooth != "poly" {
        Some(fit_per_bin(&fields, &opts).map_err(|e| anyhow!("{e}"))?)
    } else {
        None
    };
    let mf: MuellerField = match (a.smooth.as_str(), &per_bin) {
        ("radial", Some(b)) => {
            fit::mueller_smooth::radial_field(&b.0, a.deg).map_err(|e| anyhow!("--smooth radial: {e}"))?
        }
        ("interp", Some(b)) => fit::mueller_smooth::interp_field(&b.0).map_err(|e| anyhow!("--smooth interp: {e}"))?,
        _ => fit_mueller_field(&fields, &opts).map_err(|e| anyhow!("{e}"))?,
    };
    let mut mf = mf;
    if a.smooth != "poly" && fields.len() > n_maps {
        // Each star is a position of its own, which no per-bin fit constrains.
        mf.warnings.push(format!(
            "the {} form is built from the per-bin fits of the sky maps: the {} polarized standards of --stars do not enter it (use --smooth poly to fit them with the maps)",
            a.smooth,
            fields.len() - n_maps
        ));
    }
    if fits_out {
        let (instrument, filter, coords) = setup.expect("at least one field (clap requires one)");
        let cal = MuellerCal {
            instrument,
            filter,
            field: mf.clone(),
            coords: Some(coords),
            skies: fields
                .iter()
                .map(|f| {
                    let (p, chi) = stokes::polarization(f.sky_q, f.sky_u);
                    SkyField { name: f.name.clone(), p, chi_deg: chi.to_degrees(), sigma: f.sigma_sky }
                })
                .collect(),
            per_bin: per_bin.as_ref().map(|b| b.0.clone()).unwrap_or_default(),
            hwp_chi_offset_deg: zero_angle_deg,
            provenance: fit::calfile::Provenance::now(
                "instpol calibrate-mueller",
                specs
                    .iter()
                    .map(|s| s.0.display().to_string())
                    .chain(a.stars.iter().map(|p| p.display().to_string()))
                    .collect(),
            ),
        };
        cal.save(&a.out).map_err(|e| anyhow!("{e}"))?;
    } else {
        crate::util::write_atomic(&a.out, mf.to_json().as_bytes())?;
    }

    // Summaries over the observed positions.
    let pos: Vec<(f64, f64)> = fields[0].obs.iter().map(|o| (o.x_arcmin, o.y_arcmin)).collect();
    let nf = mf.free.len();
    let mut parameters = Vec::new();
    for (k, &i) in mf.free.iter().enumerate() {
        let (mut vals, mut sig) = (Vec::new(), Vec::new());
        for &(x, y) in &pos {
            let (v, c) = mf.params_at(x, y);
            vals.push(v[k]);
            sig.push(c[k * nf + k].max(0.0).sqrt());
        }
        let rms = (vals.iter().map(|v| v * v).sum::<f64>() / vals.len() as f64).sqrt();
        parameters.push(Param {
            name: kind.name(i),
            median_value: typical(vals),
            rms_value: rms,
            median_sigma: typical(sig),
        });
    }
    let phys: Vec<_> = pos.iter().filter_map(|&(x, y)| mf.physical_at(x, y)).collect();
    let has_ret = mf.free.contains(&2);
    let (median_p, max_p) = if phys.is_empty() {
        (None, None)
    } else {
        (Some(typical(phys.iter().map(|p| p.p).collect())), Some(phys.iter().map(|p| p.p).fold(0.0, f64::max)))
    };
    let (median_retardance_deg, max_retardance_deg) = if has_ret && !phys.is_empty() {
        let d: Vec<f64> = phys.iter().map(|p| p.retardance.to_degrees()).collect();
        (Some(typical(d.clone())), Some(d.iter().cloned().fold(0.0, f64::max)))
    } else {
        (None, None)
    };
    let rep = Report {
        output: a.out.clone(),
        n_fields: n_maps,
        n_stars: fields.len() - n_maps,
        n_obs: mf.n_obs,
        deg: mf.deg,
        smooth: mf.smooth.name(),
        model: kind.model_name(),
        free: kind.free_words(),
        chi2_dof: mf.chi2_dof,
        condition: mf.condition.is_finite().then_some(mf.condition),
        parameters,
        median_p,
        max_p,
        median_retardance_deg,
        max_retardance_deg,
        n_bins_fitted: per_bin.as_ref().map(|b| b.0.len()),
        n_bins_unconstrained: per_bin.as_ref().map(|b| b.1),
        warnings: mf.warnings.clone(),
    };
    if a.json {
        return crate::util::print_json(&rep);
    }
    outln!(
        "Mueller field from {} fields and {} stars, {} observations: {} model, free {}",
        rep.n_fields,
        rep.n_stars,
        rep.n_obs,
        rep.model,
        rep.free.join(", ")
    );
    let form = match rep.smooth {
        "poly" => format!("degree {} polynomials", rep.deg),
        "radial" => format!("radial patterns, powers 1..{} of r", rep.deg),
        _ => "interpolated per-bin fits".into(),
    };
    outln!("  {form}, chi2/dof {:.3}, Fisher condition number {:.3e}", rep.chi2_dof, mf.condition);
    outln!("  {:<16} {:>12} {:>12} {:>12}", "parameter", "median", "rms", "median sigma");
    for p in &rep.parameters {
        outln!("  {:<16} {:>12.3e} {:>12.3e} {:>12.3e}", p.name, p.median_value, p.rms_value, p.median_sigma);
    }
    if let (Some(m), Some(x)) = (rep.median_p, rep.max_p) {
        outln!("  diattenuation p: median {:.4} %, largest {:.4} %", 100.0 * m, 100.0 * x);
    }
    if let (Some(m), Some(x)) = (rep.median_retardance_deg, rep.max_retardance_deg) {
        outln!("  retardance: median {m:.2} deg, largest {x:.2} deg");
    }
    if let (Some(n), Some(s)) = (rep.n_bins_fitted, rep.n_bins_unconstrained) {
        outln!("  per bin: {n} bins fitted, {s} not constrained on their own");
    }
    for w in &rep.warnings {
        eprintln!("WARNING: {w}");
    }
    outln!("  written: {}", rep.output.display());
    Ok(())
}
