//! The units a column's name promises, and the declared units that can be honoured for it: the
//! one rule by which [`super::Table::numbers`] turns a column with a declared unit (ECSV, FITS
//! `TUNITn`, VOTable `unit=`) into the values its name says, for every reader of every command.
//!
//! | the name                                | its values        | declared units honoured         |
//! |-----------------------------------------|-------------------|---------------------------------|
//! | ends in `_deg`, `_rad`, `_arcmin`, `_arcsec` | that angle   | deg, rad, arcmin, arcsec        |
//! | ends in `_percent`                      | percent           | %, percent                      |
//! | q, u, p and their errors (`sigma_q`, ...), `p_true`, `sigma_true`, `p_measured` | fractions | '', dimensionless, %, percent |
//!
//! Any other declared unit on such a column is refused, naming the column and what it needs:
//! a fraction read from a percent column was 100 times too large, and an angle in radians read
//! as degrees was 57 times too small, both with exit 0. A fraction column that declares no unit
//! beside one that declares % is refused too (which of the two it is cannot be known). Columns
//! whose names promise nothing (x, y, fluxes, ...) are left to their readers.

/// What a column's name says it holds.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(super) enum Named {
    /// An angle in the unit of this many radians (1 deg = pi / 180).
    Angle(f64, &'static str),
    Percent,
    Fraction,
}

/// The names of fraction columns (normalized Stokes parameters, polarization degrees and their
/// errors).
const FRACTIONS: [&str; 13] = [
    "q",
    "u",
    "p",
    "sigma_q",
    "sigma_u",
    "sigma_p",
    "p_true",
    "sigma_true",
    "p_measured",
    "sigma_p_measured",
    "q_true",
    "u_true",
    "p_star",
];

/// Radians per unit of the angle units a table may declare (astropy's spellings).
fn angle_unit(u: &str) -> Option<f64> {
    let deg = std::f64::consts::PI / 180.0;
    match u {
        "deg" | "degree" | "degrees" => Some(deg),
        "rad" | "radian" | "radians" => Some(1.0),
        "arcmin" => Some(deg / 60.0),
        "arcsec" => Some(deg / 3600.0),
        _ => None,
    }
}

/// What the column name `name` promises, if anything.
pub(super) fn named(name: &str) -> Option<Named> {
    let n = name.trim().to_ascii_lowercase();
    if FRACTIONS.contains(&n.as_str()) {
        return Some(Named::Fraction);
    }
    if n.ends_with("_percent") {
        return Some(Named::Percent);
    }
    for suffix in ["deg", "rad", "arcmin", "arcsec"] {
        if n.len() > suffix.len() + 1 && n.ends_with(suffix) && n[..n.len() - suffix.len()].ends_with('_') {
            return Some(Named::Angle(angle_unit(suffix).unwrap(), suffix));
        }
    }
    None
}

fn is_percent(u: &str) -> bool {
    u == "%" || u.eq_ignore_ascii_case("percent")
}

fn is_dimensionless(u: &str) -> bool {
    u.is_empty() || u == "1" || u.eq_ignore_ascii_case("dimensionless")
}

/// The factor that turns column `name`'s values, declared in `unit` (None: no unit), into the
/// values its name promises; `percent_beside` says whether another fraction column of the table
/// declares %. An error is the message (without the file) naming the column and the fix.
pub(super) fn factor(name: &str, unit: Option<&str>, percent_beside: Option<&str>) -> Result<f64, String> {
    let Some(what) = named(name) else { return Ok(1.0) };
    match (what, unit) {
        (Named::Fraction, None) => match percent_beside {
            Some(other) => Err(format!(
                "column '{other}' is in %, but column '{name}' declares no unit: declare it (% or '') so that it is not read as a fraction"
            )),
            None => Ok(1.0),
        },
        (_, None) => Ok(1.0),
        (Named::Fraction, Some(u)) if is_dimensionless(u) => Ok(1.0),
        (Named::Fraction, Some(u)) if is_percent(u) => Ok(0.01),
        (Named::Fraction, Some(u)) => {
            Err(format!("column '{name}' has unit '{u}': a fraction needs none (or '') or '%'"))
        }
        (Named::Percent, Some(u)) if is_percent(u) => Ok(1.0),
        (Named::Percent, Some(u)) => {
            Err(format!("column '{name}' has unit '{u}': its name says percent, so it needs '%' or none"))
        }
        (Named::Angle(rad, own), Some(u)) => match angle_unit(u) {
            Some(r) => Ok(r / rad),
            None => Err(format!(
                "column '{name}' has unit '{u}': its name says an angle in {own}, so it needs deg, rad, arcmin, arcsec or none"
            )),
        },
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn names_promise_their_units() {
        assert_eq!(named("chi_measured_deg"), Some(Named::Angle(std::f64::consts::PI / 180.0, "deg")));
        assert_eq!(named("x_arcmin").map(|n| matches!(n, Named::Angle(_, "arcmin"))), Some(true));
        assert_eq!(named("p_percent"), Some(Named::Percent));
        assert_eq!(named("Sigma_Q"), Some(Named::Fraction));
        // A name that only ends in the letters of a unit promises nothing.
        for n in ["x", "y", "f_o", "wavelength_um", "cov_qu", "deg", "ideg", "_deg"] {
            assert_eq!(named(n), None, "{n}");
        }
    }

    #[test]
    fn declared_units_convert_or_are_refused() {
        // Against the closed forms: 1 rad = 180/pi deg, 1 deg = 60 arcmin, 1 arcsec = 1/60 arcmin.
        let close = |a: f64, b: f64| (a - b).abs() <= 1e-12 * b.abs();
        assert!(close(factor("chi_deg", Some("rad"), None).unwrap(), 180.0 / std::f64::consts::PI));
        assert!(close(factor("x_arcmin", Some("deg"), None).unwrap(), 60.0));
        assert!(close(factor("x_arcmin", Some("arcsec"), None).unwrap(), 1.0 / 60.0));
        assert_eq!(factor("chi_deg", Some("deg"), None), Ok(1.0));
        assert_eq!(factor("sigma_q", Some("%"), None), Ok(0.01));
        assert_eq!(factor("q", Some(""), None), Ok(1.0));
        assert_eq!(factor("p_percent", Some("%"), None), Ok(1.0));
        assert_eq!(factor("f_o", Some("deg"), None), Ok(1.0));
        for (name, unit) in [("q", "deg"), ("chi_deg", "%"), ("x_arcmin", "pix"), ("p_percent", "pix")] {
            let e = factor(name, Some(unit), None).unwrap_err();
            assert!(e.contains(&format!("column '{name}'")) && e.contains(unit), "{e}");
        }
        let e = factor("sigma_q", None, Some("q")).unwrap_err();
        assert!(e.contains("'q' is in %") && e.contains("'sigma_q'"), "{e}");
    }
}
