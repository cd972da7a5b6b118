//! FORS2's chromatic HWP zero angles and HWP keywords, against their sources (the instrument
//! file's [ZA] note): the FORS2 User Manual's zero-angle table (Table 4.7 of the P114 issue) as
//! two independent FORS2 analyses transcribe it, Gonzalez-Gaitan et al. 2020's `eso_ipol.py`
//! (`chromatism_correction`) and Jassef's `zero_angle_corrections.dat`. Both subtract the
//! table's value from the polarization angle measured after Q and U; instpol's
//! `hwp_chi_offset_deg` is the angle *added* to a measured chi (`fit::models::pipeline` module docs), so
//! the file must hold minus the table.

use instrument::Instrument;

/// The manual's zero angles (deg), as printed in both sources.
const MANUAL_ZERO_ANGLE_DEG: [(&str, f64); 4] =
    [("b_HIGH", 1.54), ("v_HIGH", 1.80), ("R_SPECIAL", -1.19), ("I_BESS", -2.89)];

#[test]
fn fors2_chi_offsets_are_minus_the_manual_zero_angles() {
    let inst = Instrument::load("fors2").unwrap();
    for (name, theta0) in MANUAL_ZERO_ANGLE_DEG {
        let f = inst.filter(name).unwrap();
        // chi_sky = chi_measured - theta0 (the sources) = chi_measured + hwp_chi_offset_deg.
        assert_eq!(f.hwp_chi_offset_deg, Some(-theta0), "{name}");
    }
    // Every FORS2 filter has its table entry (none left at an assumed 0).
    assert_eq!(inst.filters.len(), MANUAL_ZERO_ANGLE_DEG.len());
}

#[test]
fn fors2_reads_the_plate_angle_under_either_eso_name() {
    let inst = Instrument::load("fors2").unwrap();
    let p = &inst.polarimetry;
    assert_eq!(p.hwp_angle_keyword, "HIERARCH ESO INS RETA2 POSANG");
    assert_eq!(p.hwp_angle_fallback_keywords, ["HIERARCH ESO INS RETA2 ROT"]);
    // Other instruments name no fallback unless their file says so.
    assert!(Instrument::load("fors1").unwrap().polarimetry.hwp_angle_fallback_keywords.is_empty());
}
