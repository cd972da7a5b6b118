//! The `[headers]` table: what FORS2's and EFOSC2's files say they are, and the refusals of a
//! table that could not classify anything.

use instrument::{Instrument, Role};
use std::path::Path;

#[test]
fn eso_role_strings_classify() {
    for name in ["fors2", "efosc2"] {
        let inst = Instrument::load(name).unwrap();
        let h = inst.headers.as_ref().expect("ESO instruments declare their headers");
        assert_eq!(h.role_of("CALIB/BIAS/IMAGE"), Some(Role::Bias));
        assert_eq!(h.role_of("CALIB/FLAT,SKY/IMAGE"), Some(Role::Flat));
        assert_eq!(h.role_of("SCIENCE/OBJECT/POLARIMETRY"), Some(Role::Polarimetry));
        assert_eq!(h.role_of("CALIB/STD/POLARIMETRY"), Some(Role::Standard));
        assert_eq!(h.role_of("SCIENCE/OBJECT/IMAGE"), None, "imaging without the Wollaston is no polarimetry");
        assert!(h.is_instrument(&inst.name));
        assert!(!h.is_instrument("HAWKI"));
    }
}

fn with_headers(table: &str) -> Result<Instrument, instrument::Error> {
    let text = include_str!("../../../../instruments/fors1.toml").to_string() + "\n[headers]\n" + table;
    Instrument::from_toml_str(&text, Path::new("h.toml"))
}

#[test]
fn bad_tables_are_refused_naming_file_and_key() {
    let e =
        with_headers("role_keywords = [\"IMAGETYP\"]\npolarimetry = [\"POL\"]\ncolour = 1\n").unwrap_err().to_string();
    assert!(e.contains("h.toml") && e.contains("colour"), "{e}");
    let e = with_headers("role_keywords = []\npolarimetry = [\"POL\"]\n").unwrap_err().to_string();
    assert!(e.contains("h.toml") && e.contains("headers.role_keywords"), "{e}");
    let e = with_headers("role_keywords = [\"A\", \"B\"]\npolarimetry = [\"POL\"]\n").unwrap_err().to_string();
    assert!(e.contains("headers.polarimetry") && e.contains("POL"), "{e}");
    let e = with_headers("role_keywords = [\"A\"]\n").unwrap_err().to_string();
    assert!(e.contains("headers.polarimetry"), "{e}");
    let ok = with_headers("role_keywords = [\"IMAGETYP\"]\nbias = [\"BIAS\", \"ZERO\"]\npolarimetry = [\"POL*\"]\n")
        .unwrap();
    let h = ok.headers.unwrap();
    assert_eq!(h.role_of("zero"), Some(Role::Bias));
    assert_eq!(h.role_of("POLARIMETRY"), Some(Role::Polarimetry));
    assert_eq!(h.target_keyword, "OBJECT");
}
