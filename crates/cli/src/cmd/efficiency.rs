//! `instpol efficiency`: the instrument's constant response from standards in catalogs
//! (`fit::response`), written as a calibration file `instpol correct` applies
//! (`fit::response::cal`).

use anyhow::{anyhow, bail, Result};
use fit::response::{catalog_standard, one_setup, Standard, Truth};
use std::path::PathBuf;

/// The instrumental polarization (q0, u0) from unpolarized standards, then the polarimetric
/// efficiency (measured P over catalogued P) and the angle offset (the angle to add to a
/// measured chi, as `zero-angle` gives it) from polarized standards, (q0, u0) taken off first:
/// the constant response MOPTOP, RoboPol and SPARC4 calibrate on standards,
///
///   (q, u)_measured = (q0, u0) + efficiency R(-offset) (q, u)_true
///
/// in the instrument's frame (a catalog in the celestial frame is turned back by its position
/// angle on the sky, its star's catalogued angle too). Each standard is a row of a catalog of
/// `instpol catalog`, picked by its position: `--standard CATALOG:X,Y:WHAT`, repeated, where
/// WHAT is a star of the standards list (built-in, or --standards FILE: its kind and its
/// published P and chi in the catalog's filter), `unpolarized`, or `P+-SIGMA/CHI+-SIGMA` (P a
/// fraction, chi in degrees north through east). Give at least one unpolarized and one
/// polarized standard. With `--output CAL.fits` the result is a calibration file that
/// `instpol correct --cal CAL.fits` applies to catalogs and Stokes maps.
///
/// Examples:
///   instpol efficiency --standard hd14069.csv:512,480:"HD 14069" \
///       --standard bd64.csv:498,505:"BD+64 106" --output response_R.fits
///   instpol efficiency --standard a.fits:300,310:unpolarized \
///       --standard b.fits:200,220:0.0402+-0.0003/97.1+-0.2 --json
#[derive(clap::Args)]
pub struct Args {
    /// A standard: CATALOG:X,Y:NAME, CATALOG:X,Y:unpolarized or CATALOG:X,Y:P+-SIGMA/CHI+-SIGMA
    /// (X, Y: 0-based px of its o image), repeated.
    #[arg(long = "standard", required = true, value_name = "CATALOG:X,Y:WHAT")]
    pub standard: Vec<String>,
    /// A standards file (TOML, the format of instruments/standards.toml) for names.
    #[arg(long)]
    pub standards: Option<PathBuf>,
    /// How far (px) a catalog row may lie from the position given.
    #[arg(long, default_value_t = 3.0)]
    pub match_radius: f64,
    /// The instrument, for catalogs that do not record one.
    #[arg(long)]
    pub instrument: Option<String>,
    /// The filter, for catalogs that do not record one.
    #[arg(long)]
    pub filter: Option<String>,
    /// Write the calibration file (FITS) here.
    #[arg(long, value_name = "CAL.fits")]
    pub output: Option<PathBuf>,
    /// Print JSON.
    #[arg(long)]
    pub json: bool,
}

/// What a standard's WHAT says: a name, or the truth in numbers.
enum What {
    Name(String),
    Known(Truth),
}

/// Parse `CATALOG:X,Y:WHAT` (the catalog's path may hold ':' itself: split from the right).
fn parse(spec: &str) -> Result<(PathBuf, (f64, f64), What)> {
    let bad = || {
        anyhow!("--standard '{spec}': expected CATALOG:X,Y:NAME, CATALOG:X,Y:unpolarized or CATALOG:X,Y:P+-SIGMA/CHI+-SIGMA, e.g. std.csv:512,480:HD 14069")
    };
    let mut parts = spec.rsplitn(3, ':');
    let (Some(what), Some(pos), Some(path)) = (parts.next(), parts.next(), parts.next()) else { return Err(bad()) };
    let xy: Option<Vec<f64>> = pos.split(',').map(|t| t.trim().parse().ok()).collect();
    let Some([x, y]) = xy.as_deref().and_then(|v| <[f64; 2]>::try_from(v).ok()) else { return Err(bad()) };
    let what = what.trim();
    let pm = |t: &str| -> Option<(f64, f64)> {
        let (v, s) =
            t.replace('±', "+-").split_once("+-").map(|(a, b)| (a.trim().to_string(), b.trim().to_string()))?;
        Some((v.parse().ok()?, s.parse().ok()?))
    };
    let w = if what.eq_ignore_ascii_case("unpolarized") {
        What::Known(Truth::Unpolarized)
    } else if let Some((p, chi)) = what.split_once('/').filter(|_| what.contains("+-") || what.contains('±')) {
        let ((p, sigma_p), (chi_deg, sigma_chi_deg)) = (pm(p).ok_or_else(bad)?, pm(chi).ok_or_else(bad)?);
        What::Known(Truth::Polarized { p, sigma_p, chi_deg, sigma_chi_deg })
    } else if what.is_empty() {
        return Err(bad());
    } else {
        What::Name(what.to_string())
    };
    Ok((PathBuf::from(path), (x, y), w))
}

pub fn run(a: Args) -> Result<()> {
    if !(a.match_radius.is_finite() && a.match_radius > 0.0) {
        bail!("--match-radius {} must be a positive number of pixels", a.match_radius);
    }
    let specs = a.standard.iter().map(|s| parse(s)).collect::<Result<Vec<_>>>()?;
    // One catalog may hold several standards: each file is checked once.
    let mut files: Vec<&std::path::Path> = specs.iter().map(|s| s.0.as_path()).collect();
    files.sort();
    files.dedup();
    crate::util::inputs(files.into_iter().chain(a.standards.as_deref()))?;
    if let Some(o) = &a.output {
        crate::util::check_output(o)?;
    }
    let mut rows = Vec::with_capacity(specs.len());
    let mut setups = Vec::with_capacity(specs.len());
    for (path, xy, what) in specs {
        let (m, setup) = catalog_standard(&path, xy, a.match_radius)?;
        setups.push((path.display().to_string(), setup));
        rows.push((path, xy, what, m));
    }
    let setup = one_setup(&setups, a.instrument.as_deref(), a.filter.as_deref()).map_err(|e| anyhow!("{e}"))?;
    let list = match &a.standards {
        Some(p) => fit::standards::Standards::load(p)?,
        None => fit::standards::Standards::builtin()?,
    };
    let mut stds = Vec::with_capacity(rows.len());
    for (path, (x, y), what, measured) in rows {
        let (label, truth) = match what {
            What::Name(n) => {
                let star = list.star(&n)?;
                (star.name.clone(), Truth::of_star(star, &setup.filter)?)
            }
            What::Known(t) => (format!("{} at ({x}, {y})", path.display()), t),
        };
        stds.push(Standard { label, measured, truth });
    }
    let f = fit::response::fit(&setup.filter, &stds)?;
    if let Some(o) = &a.output {
        fit::response::cal::ResponseCal::of_fit(&f, &setup).save(o)?;
    }
    let s = f.summary(&setup, a.output.as_ref().map(|o| o.display().to_string()));
    for p in s.polarized.iter().filter(|p| p.excluded) {
        eprintln!(
            "warning: standard {} disagrees with the others in angle (pull {:.1}): left out; check its identification and catalogue value",
            p.label, p.pull
        );
    }
    if a.json {
        return crate::util::print_json(&s);
    }
    outln!(
        "{} {}: the constant response from {} unpolarized and {} polarized standards",
        s.instrument,
        s.filter,
        s.unpolarized.len(),
        s.polarized.len()
    );
    outln!(
        "  (q0, u0) = ({:.5} +- {:.5}, {:.5} +- {:.5})   (fractions; the instrument's sky frame, zero angle {:.2} deg)",
        s.q_inst,
        s.sigma_q_inst,
        s.u_inst,
        s.sigma_u_inst,
        s.hwp_chi_offset_deg
    );
    outln!("  efficiency = {:.4} +- {:.4}   (measured P over catalogued P)", s.efficiency, s.sigma_efficiency);
    outln!(
        "  offset = {:.2} +- {:.2} deg   (to add to a measured chi, as zero-angle gives it)",
        s.offset_deg,
        s.sigma_offset_deg
    );
    for p in &s.polarized {
        let pm = p.p_measured.map_or(String::new(), |v| format!("P = {:.3} %", 100.0 * v));
        let pc = p.p_catalogue.map_or(String::new(), |v| format!(" (catalogue {:.3} %)", 100.0 * v));
        outln!(
            "  {}: {pm}{pc}, chi {:.2} deg (catalogue {:.2}), offset {:.2} deg",
            p.label,
            p.chi_measured_deg,
            p.chi_catalogue_deg,
            p.offset_deg
        );
    }
    if let Some(o) = &s.output {
        outln!("wrote {o}: correct with instpol correct --cal {o} --in CATALOG_OR_MAP --out OUT");
    }
    Ok(())
}
