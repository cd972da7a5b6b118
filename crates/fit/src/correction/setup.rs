//! Whether data and a calibration belong to the same instrument and filter: the one place
//! that matches filter names (case-insensitively, through the instrument's aliases).

use instrument::Instrument;

/// Whether two filter names mean the same filter of `inst`: equal ignoring case and
/// surrounding blanks, or both names (or aliases) of one filter of the instrument, or one of
/// them a filter of the instrument and the other a band named by its wavelength (`0.550um`,
/// what a telescope model fitted from standards without a filter column calls its band) that
/// is that filter's ([`band_is_filter`]). Without an instrument only the names are compared.
pub fn same_filter(inst: Option<&Instrument>, a: &str, b: &str) -> bool {
    let (a, b) = (a.trim(), b.trim());
    if a.eq_ignore_ascii_case(b) {
        return true;
    }
    match inst {
        Some(i) if i.same_filter(a, b) => true,
        Some(i) => match (i.filter(a), i.filter(b)) {
            (Ok(x), Err(_)) => band_is_filter(i, &x.name, b),
            (Err(_), Ok(y)) => band_is_filter(i, &y.name, a),
            _ => false,
        },
        None => false,
    }
}

/// Whether data of instrument `inst` (a name) in `filter` may be corrected with a telescope
/// model's band `band` on its own ([`same_filter`] through that instrument when it is a known
/// one): the check of the CLI's and the Python package's map corrections.
pub fn band_fits_data(inst: &str, filter: &str, band: &str) -> bool {
    same_filter(Instrument::load(inst).ok().as_ref(), filter, band)
}

/// The HWP zero angle (deg) a Stokes map's q, u lack to be in the sky frame: the one it
/// records (`HWPZERO`), else that of the built-in instrument its `INSTRUME` names in its
/// filter (maps made before `HWPZERO` was recorded); when neither is known, 0 and what to
/// say about it. The one rule of the CLI's and the Python package's map corrections with a
/// telescope model alone.
pub fn map_zero_angle(map: &skyfield::StokesMap) -> (f64, Option<String>) {
    let known = map
        .hwp_zero_angle_deg
        .or_else(|| Instrument::load(&map.instrument).ok()?.filter(&map.filter).ok().map(|f| f.chi_offset_deg()));
    match known {
        Some(z) => (z, None),
        None => (
            0.0,
            Some(format!(
                "the map records no HWP zero angle (HWPZERO) and instrument {} is not a built-in one, so its zero angle in filter {} is not known here and is taken as 0: chi would be off by it (see {})",
                map.instrument,
                map.filter,
                instrument::ZERO_ANGLE_GUIDE
            )),
        ),
    }
}

/// What to say when a Stokes map records an HWP zero angle (`HWPZERO`, from the instrument file
/// it was reduced with) other than the one `inst` gives its filter now: the calibration takes
/// `inst`'s. `None` when they agree or the map records none.
pub fn zero_angle_disagreement(map: &skyfield::StokesMap, inst: &Instrument) -> Option<String> {
    let recorded = map.hwp_zero_angle_deg?;
    let now = inst.filter(&map.filter).ok()?.chi_offset_deg();
    (recorded != now).then(|| {
        format!(
            "the map records an HWP zero angle of {recorded} deg for filter {} (HWPZERO: the instrument file it was reduced with), instrument {} gives {now} deg now: {now} deg is used (see {})",
            map.filter,
            inst.name,
            instrument::ZERO_ANGLE_GUIDE
        )
    })
}

/// The wavelength (nm) of a band named by it in micrometres (`0.550um`, as
/// `telescope::StandardObs` names a band without a filter); `None` for other names.
pub fn band_wavelength_nm(band: &str) -> Option<f64> {
    let um: f64 = band.trim().strip_suffix("um")?.trim().parse().ok()?;
    (um.is_finite() && um > 0.0).then_some(1000.0 * um)
}

/// How far (as a fraction of the filter's effective wavelength) a band named by its wavelength
/// may lie from a filter and still be that filter's: 2.5 %, well inside a broad-band filter's
/// width (about 15-20 % of its wavelength for Bessell B, V, R, I) and less than half the
/// spacing of neighbouring ones (V and R: 16 %), so that a band is never two filters'.
pub const BAND_WAVELENGTH_TOL: f64 = 0.025;

/// Whether the band `band`, named by its wavelength ([`band_wavelength_nm`]), is filter
/// `filter` of `inst`: the instrument's filter nearest that wavelength, within
/// [`BAND_WAVELENGTH_TOL`] of its effective wavelength.
pub fn band_is_filter(inst: &Instrument, filter: &str, band: &str) -> bool {
    let Some(w) = band_wavelength_nm(band) else { return false };
    let nearest =
        inst.filters.iter().min_by(|p, q| (p.lambda_eff_nm - w).abs().total_cmp(&(q.lambda_eff_nm - w).abs()));
    nearest.is_some_and(|f| f.name == filter && (f.lambda_eff_nm - w).abs() <= BAND_WAVELENGTH_TOL * f.lambda_eff_nm)
}

/// A name that says something: not empty and not "unknown" (maps of unknown origin are not
/// checked against a calibration).
pub fn is_known(name: &str) -> bool {
    !name.trim().is_empty() && !name.trim().eq_ignore_ascii_case("unknown")
}

/// Whether data of instrument `inst` in `filter` may be corrected with `cal`: same instrument
/// (ignoring case) and same filter ([`same_filter`] through the calibration's instrument when
/// it is a known one). Unknown names ([`is_known`]) are not checked.
pub fn matches_calibration(inst: &str, filter: &str, cal: &crate::Calibration) -> bool {
    matches_setup(inst, filter, &cal.instrument, &cal.filter)
}

/// What a product (a catalog's rows, a map) says it is, beside what a calibration is for: the
/// one check of every combination of data with a calibration ([`check_compatible`]).
#[derive(Debug, Clone, PartialEq)]
pub struct Setup {
    pub instrument: String,
    pub filter: String,
    /// `half_wave` or `quarter_wave`, when known.
    pub plate: Option<String>,
}

impl Setup {
    /// The setup a product records (`None` when it records no instrument or filter: a table
    /// written by other software).
    pub fn of_product(p: &skyfield::provenance::Product) -> Option<Self> {
        Some(Setup { instrument: p.instrument.clone()?, filter: p.filter.clone()?, plate: p.plate.clone() })
    }
}

/// Why data and a calibration do not fit together, naming both sides' values.
#[derive(Debug, Clone, PartialEq)]
pub enum Mismatch {
    /// Another instrument or filter ([`matches_setup`]).
    Setup { data: (String, String), calibration: (String, String) },
    /// Data of a quarter-wave plate (`V/I`): a calibration corrects linear `q, u`.
    Plate { plate: String },
}

impl Mismatch {
    /// What differs, in a few words (a FITS keyword's value: at most 68 characters).
    pub fn short(&self) -> String {
        let s = match self {
            Mismatch::Setup { data, calibration } => {
                format!("data {} {}, calibration {} {}", data.0, data.1, calibration.0, calibration.1)
            }
            Mismatch::Plate { plate } => format!("data of a {plate} plate"),
        };
        s.chars().filter(|c| (' '..='~').contains(c) && *c != '\'').take(68).collect()
    }
}

impl std::fmt::Display for Mismatch {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Mismatch::Setup { data, calibration } => write!(
                f,
                "the data are of instrument {} in filter {}, the calibration of instrument {} in filter {}",
                data.0, data.1, calibration.0, calibration.1
            ),
            Mismatch::Plate { plate } => write!(
                f,
                "the data were taken through a {} plate (V/I); a calibration corrects the linear q, u of a half-wave plate",
                plate.replace('_', "-")
            ),
        }
    }
}

/// The one compatibility check of data (`data`, what the product says) and a calibration of
/// instrument and filter `cal` (`None`: a telescope model alone, whose band is checked apart):
/// a half-wave plate's data, of the same instrument and filter ([`matches_setup`]: names that
/// say nothing are not checked).
pub fn check_compatible(data: &Setup, cal: Option<(&str, &str)>) -> Result<(), Mismatch> {
    if let Some(p) = data.plate.as_deref().filter(|p| !p.eq_ignore_ascii_case("half_wave")) {
        return Err(Mismatch::Plate { plate: p.to_string() });
    }
    let Some((cal_inst, cal_filter)) = cal else { return Ok(()) };
    if !matches_setup(&data.instrument, &data.filter, cal_inst, cal_filter) {
        return Err(Mismatch::Setup {
            data: (data.instrument.clone(), data.filter.clone()),
            calibration: (cal_inst.to_string(), cal_filter.to_string()),
        });
    }
    Ok(())
}

/// Whether two instrument names a product or calibration records are one instrument (any
/// case, surrounding blanks ignored); names that say nothing ([`is_known`]) are not compared
/// here: the callers decide what an unknown name means.
pub fn same_instrument(a: &str, b: &str) -> bool {
    a.trim().eq_ignore_ascii_case(b.trim())
}

/// [`matches_calibration`] for any calibration of instrument `cal_inst` and filter
/// `cal_filter` (e.g. a Mueller field, [`crate::mueller_field::cal`]).
pub fn matches_setup(inst: &str, filter: &str, cal_inst: &str, cal_filter: &str) -> bool {
    let same_inst = !is_known(inst) || !is_known(cal_inst) || same_instrument(inst, cal_inst);
    let same_filter = !is_known(filter)
        || !is_known(cal_filter)
        || same_filter(Instrument::load(cal_inst).ok().as_ref(), filter, cal_filter);
    same_inst && same_filter
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn filter_names_and_aliases() {
        let f = Instrument::load("fors1").unwrap();
        assert!(same_filter(Some(&f), "V", " v "));
        assert!(same_filter(Some(&f), "v_bess", "V"), "an alias of V");
        assert!(!same_filter(Some(&f), "V", "I"));
        assert!(!same_filter(None, "v_bess", "V"), "aliases need the instrument");
        assert!(!same_filter(Some(&f), "Z", "V"));
    }

    /// A band named by its wavelength is the instrument's filter at that wavelength (EFOSC2's
    /// B, V, R at 440, 550, 640 nm), within 2.5 % and only the nearest one; never without the
    /// instrument.
    #[test]
    fn wavelength_bands_are_the_filters_there() {
        let e = Instrument::load("efosc2").unwrap();
        assert!(same_filter(Some(&e), "V", "0.550um"));
        assert!(same_filter(Some(&e), "0.550um", "V#641"), "either order, aliases too");
        assert!(same_filter(Some(&e), "V", "0.562um"), "12 nm off: 2.2 %");
        assert!(!same_filter(Some(&e), "V", "0.565um"), "15 nm off: 2.7 %");
        assert!(!same_filter(Some(&e), "B", "0.550um"));
        assert!(same_filter(Some(&e), "R", "0.640um"));
        assert!(!same_filter(Some(&e), "R", "0.600um"), "nearer R than V, but 6 % from R");
        assert!(!same_filter(None, "V", "0.550um"));
        assert!(!same_filter(Some(&e), "V", "550nm"), "micrometres only, as the models name bands");
        assert_eq!(band_wavelength_nm(" 0.550um "), Some(550.0));
        assert_eq!(band_wavelength_nm("-0.5um"), None);
        assert_eq!(band_wavelength_nm("Vum"), None);
    }
}
