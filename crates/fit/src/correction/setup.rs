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

/// The Johnson-Cousins bands U, B, V, R, I and their effective wavelengths (nm) for a star
/// like Vega (Bessell, Castelli & Plez 1998, A&A 333, 231, table A2): the names a band given by
/// its wavelength alone is written with when no instrument names its filters.
pub const STANDARD_BANDS: [(&str, f64); 5] = [("U", 366.0), ("B", 438.0), ("V", 545.0), ("R", 641.0), ("I", 798.0)];

/// A band as astronomers write it: a band named by its wavelength ([`band_wavelength_nm`],
/// `0.550um`) as its filter and the wavelength in nm, `V (550 nm)`: the filter of `inst`
/// nearest that wavelength within [`BAND_WAVELENGTH_TOL`], else the standard band
/// ([`STANDARD_BANDS`]) there, else the wavelength alone (`1250 nm`). Other names unchanged.
pub fn band_label(band: &str, inst: Option<&Instrument>) -> String {
    let Some(w) = band_wavelength_nm(band) else { return band.to_string() };
    let near = |lambda: f64| (lambda - w).abs() <= BAND_WAVELENGTH_TOL * lambda;
    let of_inst = inst.and_then(|i| {
        i.filters.iter().min_by(|p, q| (p.lambda_eff_nm - w).abs().total_cmp(&(q.lambda_eff_nm - w).abs()))
    });
    let name = match of_inst {
        Some(f) => near(f.lambda_eff_nm).then(|| f.name.clone()),
        None => STANDARD_BANDS.iter().find(|(_, l)| near(*l)).map(|(n, _)| n.to_string()),
    };
    match name {
        Some(n) => format!("{n} ({w:.0} nm)"),
        None => format!("{w:.0} nm"),
    }
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

/// What a product (a catalog's rows, a map) or a calibration says it is: the one check of
/// every combination of data with a calibration ([`check_compatible`]). Each field but the
/// instrument and filter is `None` when the side does not say (a table written by other
/// software, a calibration file written before products were recorded).
#[derive(Debug, Clone, PartialEq, Default)]
pub struct Setup {
    pub instrument: String,
    pub filter: String,
    /// `half_wave` or `quarter_wave`, when known.
    pub plate: Option<String>,
    /// `blake3:<hex>` of the instrument file the side was made with.
    pub instrument_hash: Option<String>,
    /// The detector's size (unbinned pixels, x by y) and its pixel scale (arcsec per unbinned
    /// pixel): the geometry field positions are measured in.
    pub detector_px: Option<(usize, usize)>,
    pub pixel_scale_arcsec: Option<f64>,
}

impl Setup {
    /// The setup a product records (`None` when it records no instrument or filter: a table
    /// written by other software).
    pub fn of_product(p: &skyfield::provenance::Product) -> Option<Self> {
        Some(Setup::named(p.instrument.as_deref()?, p.filter.as_deref()?).with_product(Some(p)))
    }

    /// The setup of data read with `inst` in `filter`: its name, file, plate and detector
    /// ([`skyfield::provenance::Product::of_instrument`]), what frames reduced with it are.
    pub fn of_instrument(inst: &Instrument, filter: &str) -> Self {
        Setup::named(&inst.name, filter)
            .with_product(Some(&skyfield::provenance::Product::of_instrument(inst, filter, None)))
    }

    /// A setup of instrument `instrument` and filter `filter` that says nothing else.
    pub fn named(instrument: &str, filter: &str) -> Self {
        Setup { instrument: instrument.to_string(), filter: filter.to_string(), ..Default::default() }
    }

    /// `self` with what `p` records beside the instrument and filter (plate, instrument file,
    /// detector), where `self` does not say; `p` may be `None`.
    pub fn with_product(self, p: Option<&skyfield::provenance::Product>) -> Self {
        let Some(p) = p else { return self };
        Setup {
            plate: self.plate.or_else(|| p.plate.clone()),
            instrument_hash: self.instrument_hash.or_else(|| p.instrument_hash.clone()),
            detector_px: self.detector_px.or(p.detector_px),
            pixel_scale_arcsec: self.pixel_scale_arcsec.or(p.pixel_scale_arcsec),
            ..self
        }
    }

    /// The product keywords of a calibration made from data of this setup (its instrument,
    /// filter, plate, instrument file and detector; the inputs are the run's when written).
    pub fn product(&self) -> skyfield::provenance::Product {
        let known = |s: &str| is_known(s).then(|| s.to_string());
        skyfield::provenance::Product {
            instrument: known(&self.instrument),
            instrument_hash: self.instrument_hash.clone(),
            filter: known(&self.filter),
            plate: self.plate.clone(),
            detector_px: self.detector_px,
            pixel_scale_arcsec: self.pixel_scale_arcsec,
            ..Default::default()
        }
    }
}

/// Why data and a calibration do not fit together, naming both sides' values.
#[derive(Debug, Clone, PartialEq)]
pub enum Mismatch {
    /// Another instrument or filter ([`matches_setup`]).
    Setup { data: (String, String), calibration: (String, String) },
    /// Data of a quarter-wave plate (`V/I`): a calibration corrects linear `q, u`.
    Plate { plate: String },
    /// Data and calibration each say their plate, and they differ.
    PlateDiffers { data: String, calibration: String },
    /// Data and calibration each say their detector (size in pixels, pixel scale), and the
    /// field positions of one are not the other's.
    Geometry { data: String, calibration: String },
}

impl Mismatch {
    /// What differs, in a few words (a FITS keyword's value: at most 68 characters).
    pub fn short(&self) -> String {
        let s = match self {
            Mismatch::Setup { data, calibration } => {
                format!("data {} {}, calibration {} {}", data.0, data.1, calibration.0, calibration.1)
            }
            Mismatch::Plate { plate } => format!("data of a {plate} plate"),
            Mismatch::PlateDiffers { data, calibration } => format!("plate: data {data}, calibration {calibration}"),
            Mismatch::Geometry { data, calibration } => format!("detector: data {data}, calibration {calibration}"),
        };
        s.chars().filter(|c| (' '..='~').contains(c) && *c != '\'').take(68).collect()
    }
}

impl std::fmt::Display for Mismatch {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Mismatch::Setup { data, calibration } => {
                // A side compared without its filter (check_same_instrument) names none.
                let side = |(i, fl): &(String, String)| match fl.as_str() {
                    "" => format!("instrument {i}"),
                    fl => format!("instrument {i} in filter {fl}"),
                };
                write!(f, "the data are of {}, the calibration of {}", side(data), side(calibration))
            }
            Mismatch::Plate { plate } => write!(
                f,
                "the data were taken through a {} plate (V/I); a calibration corrects the linear q, u of a half-wave plate",
                plate.replace('_', "-")
            ),
            Mismatch::PlateDiffers { data, calibration } => write!(
                f,
                "the data were taken through a {} plate, the calibration through a {} plate",
                data.replace('_', "-"),
                calibration.replace('_', "-")
            ),
            Mismatch::Geometry { data, calibration } => write!(
                f,
                "the data's detector is {data}, the calibration's {calibration}: their field positions are not the same"
            ),
        }
    }
}

/// The one compatibility check of data (`data`, what the product says) and a calibration
/// (`cal`, what the file says: `CalibrationFile::setup`; `None`: nothing to compare): a
/// half-wave plate's data, of the same instrument and filter ([`matches_setup`]: names that
/// say nothing are not checked; a calibration of no filter, a telescope model alone, has its
/// band checked apart), through the same plate and on the same detector where both sides say.
pub fn check_compatible(data: &Setup, cal: Option<&Setup>) -> Result<(), Mismatch> {
    if let Some(p) = data.plate.as_deref().filter(|p| !p.eq_ignore_ascii_case("half_wave")) {
        return Err(Mismatch::Plate { plate: p.to_string() });
    }
    let Some(cal) = cal else { return Ok(()) };
    if !matches_setup(&data.instrument, &data.filter, &cal.instrument, &cal.filter) {
        return Err(Mismatch::Setup {
            data: (data.instrument.clone(), data.filter.clone()),
            calibration: (cal.instrument.clone(), cal.filter.clone()),
        });
    }
    if let (Some(d), Some(c)) = (&data.plate, &cal.plate) {
        if !d.trim().eq_ignore_ascii_case(c.trim()) {
            return Err(Mismatch::PlateDiffers { data: d.clone(), calibration: c.clone() });
        }
    }
    let words = |s: &Setup| {
        let size = s.detector_px.map_or("?".to_string(), |(x, y)| format!("{x}x{y} px"));
        let scale = s.pixel_scale_arcsec.map_or("?".to_string(), |a| format!("{a} arcsec/px"));
        format!("{size} at {scale}")
    };
    let size_differs = matches!((data.detector_px, cal.detector_px), (Some(a), Some(b)) if a != b);
    // The pixel scale as written round-trips ({:?}); a relative 1e-9 only forgives arithmetic.
    let scale_differs = matches!(
        (data.pixel_scale_arcsec, cal.pixel_scale_arcsec),
        (Some(a), Some(b)) if (a - b).abs() > 1e-9 * a.abs().max(b.abs())
    );
    if size_differs || scale_differs {
        return Err(Mismatch::Geometry { data: words(data), calibration: words(cal) });
    }
    Ok(())
}

/// [`check_compatible`] of two sides that must be of one instrument, plate and detector but
/// may be of different filters (calibrations of several filters for a wavelength law; frames
/// judged against a calibration of another filter, which `validate` shows failing).
pub fn check_same_instrument(a: &Setup, b: &Setup) -> Result<(), Mismatch> {
    let any_filter = |s: &Setup| Setup { filter: String::new(), ..s.clone() };
    check_compatible(&any_filter(a), Some(&any_filter(b)))
}

/// Whether data and a calibration of one instrument were made with two different instrument
/// files (both record the file's BLAKE3, and they differ): not refused (a file edited for a
/// comment is the same instrument), but said, with the two hashes.
pub fn definition_differs(data: &Setup, cal: &Setup) -> Option<(String, String)> {
    match (&data.instrument_hash, &cal.instrument_hash) {
        (Some(d), Some(c)) if d != c => Some((d.clone(), c.clone())),
        _ => None,
    }
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
        // Written as astronomers do: the filter there and nm, EFOSC2's own or the standard's.
        assert_eq!(band_label("0.550um", None), "V (550 nm)");
        assert_eq!(band_label("0.440um", Some(&e)), "B (440 nm)");
        assert_eq!(band_label("0.600um", None), "600 nm", "6 % from R, 10 % from V");
        assert_eq!(band_label("V#641", Some(&e)), "V#641");
        assert_eq!(band_wavelength_nm("-0.5um"), None);
        assert_eq!(band_wavelength_nm("Vum"), None);
    }
}
