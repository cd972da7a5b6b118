//! `instpol calibrate-mueller`: the instrument's Mueller field from several sky fields of known
//! polarization, fitted jointly by `fit::mueller_field`.

use anyhow::{anyhow, bail, Result};
use fit::mueller_field::cal::{MuellerCal, SkyField};
use fit::mueller_field::maps::{read_field_maps, FieldMap, MapFields};
use fit::mueller_field::smooth;
use fit::mueller_field::stars::{read_star_fields, FieldSummary};
use fit::mueller_field::{fit_mueller_field, fit_per_bin, Kind, MuellerField, MuellerFitOptions};
use std::path::{Path, PathBuf};

mod words;

use words::Report;

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

/// A map's instrument, filter and field coordinates.
fn kind_of(a: &Args) -> Result<Kind> {
    if a.general {
        return Ok(Kind::General);
    }
    Kind::parse_free(&a.free).map_err(|e| anyhow!("--free '{}': {e}", a.free))
}

pub fn run(a: Args) -> Result<()> {
    let kind = kind_of(&a)?;
    let specs: Vec<(PathBuf, f64, f64, f64)> = a.fields.iter().map(|s| parse_field(s)).collect::<Result<_>>()?;
    // The fields' maps are one role: a map under two names (a copy too) would be fitted twice.
    let maps: Vec<&Path> = specs.iter().map(|s| s.0.as_path()).collect();
    crate::util::refuse_duplicates(&maps, skyfield::same::By::Content)?;
    crate::util::inputs(specs.iter().map(|s| s.0.as_path()).chain(a.stars.as_deref()))?;
    crate::util::check_output(&a.out)?;
    let fits_out = match a.out.extension().and_then(|e| e.to_str()).map(|e| e.to_ascii_lowercase()).as_deref() {
        Some("fits" | "fit" | "fts") => true,
        Some("json") => false,
        _ => bail!("--out {}: the extension says the format: .fits (calibration file) or .json", a.out.display()),
    };
    let field_maps: Vec<FieldMap> = specs
        .iter()
        .map(|(path, p, chi_deg, sigma)| FieldMap { path: path.clone(), p: *p, chi_deg: *chi_deg, sigma: *sigma })
        .collect();
    let MapFields { mut fields, setup: product, coords, half_field_arcmin, zero_angle_deg } =
        read_field_maps(&field_maps).map_err(|e| anyhow!("{e}"))?;
    let n_maps = fields.len();
    if let Some(t) = &a.stars {
        fields.extend(read_star_fields(t, zero_angle_deg, Some(half_field_arcmin))?);
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
        ("radial", Some(b)) => smooth::radial_field(&b.0, a.deg).map_err(|e| anyhow!("--smooth radial: {e}"))?,
        ("interp", Some(b)) => smooth::interp_field(&b.0).map_err(|e| anyhow!("--smooth interp: {e}"))?,
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
    let (instrument, filter) = (product.instrument.clone(), product.filter.clone());
    if fits_out {
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
            provenance: fit::files::calfile::Provenance::now(
                "instpol calibrate-mueller",
                specs
                    .iter()
                    .map(|s| s.0.display().to_string())
                    .chain(a.stars.iter().map(|p| p.display().to_string()))
                    .collect(),
            )
            .with_product(product.product()),
        };
        cal.save(&a.out).map_err(|e| anyhow!("{e}"))?;
    } else {
        crate::util::write_atomic(&a.out, mf.to_json().as_bytes())?;
    }

    // Summaries over the observed positions.
    let pos: Vec<(f64, f64)> = fields[0].obs.iter().map(|o| (o.x_arcmin, o.y_arcmin)).collect();
    let FieldSummary { parameters, median_p, max_p, median_retardance_deg, max_retardance_deg } =
        FieldSummary::new(&mf, kind, &pos);
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
        product: product.product().with_run_inputs(),
    };
    if a.json {
        return crate::util::print_json(&rep);
    }
    words::print_report(&rep, mf.condition);
    Ok(())
}
