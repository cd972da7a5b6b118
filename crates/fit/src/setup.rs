//! Whether data and a calibration belong to the same instrument and filter: the one place
//! that matches filter names (case-insensitively, through the instrument's aliases).

use instrument::Instrument;

/// Whether two filter names mean the same filter of `inst`: equal ignoring case and
/// surrounding blanks, or both names (or aliases) of one filter of the instrument. Without an
/// instrument only the names are compared.
pub fn same_filter(inst: Option<&Instrument>, a: &str, b: &str) -> bool {
    let (a, b) = (a.trim(), b.trim());
    if a.eq_ignore_ascii_case(b) {
        return true;
    }
    match inst {
        Some(i) => match (i.filter(a), i.filter(b)) {
            (Ok(x), Ok(y)) => x.name == y.name,
            _ => false,
        },
        None => false,
    }
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

/// [`matches_calibration`] for any calibration of instrument `cal_inst` and filter
/// `cal_filter` (e.g. a Mueller field, [`crate::mueller_cal`]).
pub fn matches_setup(inst: &str, filter: &str, cal_inst: &str, cal_filter: &str) -> bool {
    let same_inst = !is_known(inst) || !is_known(cal_inst) || inst.trim().eq_ignore_ascii_case(cal_inst.trim());
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
}
