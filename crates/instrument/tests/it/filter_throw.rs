//! Per-filter o/e offsets (`[[filters]] throw_terms`): used for that filter only, and refused
//! with the filter named when they cannot be (a maskless layout, e lines on an o strip).

use instrument::Instrument;
use std::path::Path;

fn fors1_with_b_terms(terms: &str, margin_px: f64) -> Result<Instrument, instrument::Error> {
    let text = include_str!("../../../../instruments/fors1.toml")
        .replace("throw_arcsec = 22.0", &format!("throw_arcsec = 22.0\nstrip_margin_px = {margin_px:?}"))
        .replace("lambda_eff_nm = 429.0\n", &format!("lambda_eff_nm = 429.0\nthrow_terms = {terms}\n"));
    Instrument::from_toml_str(&text, Path::new("b.toml"))
}

#[test]
fn a_filter_throw_replaces_the_instruments_for_that_filter_only() {
    let inst = fors1_with_b_terms("[{ i = 0, j = 0, c = 2.0 }]", 3.0).unwrap();
    // FORS1's throw: 22" at 0.2"/px = 110 px, e above o; B moved 2 px further.
    assert_eq!(inst.for_filter("B").throw_variation_px(1000.0, 500.0), 2.0);
    assert_eq!(inst.for_filter("B_BESS").throw_variation_px(1000.0, 500.0), 2.0);
    assert_eq!(inst.for_filter("V").throw_variation_px(1000.0, 500.0), 0.0);
    assert!(inst.polarimetry.throw_terms.is_empty());
}

#[test]
fn a_filter_throw_that_cannot_be_is_refused_naming_the_filter() {
    // FORS1's strips touch (no margin): 2 px more throw puts the e image of strip 0's top lines
    // on strip 1's o lines.
    let e = fors1_with_b_terms("[{ i = 0, j = 0, c = 2.0 }]", 0.0).unwrap_err().to_string();
    assert!(e.contains("filters.B.throw_terms") && e.contains("o image of strip"), "{e}");
    let e = fors1_with_b_terms("[{ i = 0, j = 9, c = 1.0 }]", 3.0).unwrap_err().to_string();
    assert!(e.contains("filters.B.throw_terms") && e.contains("at most 8"), "{e}");
    let text = include_str!("../../../../instruments/calcite.toml").replace(
        "lambda_eff_nm = 530.0          # [example]\n",
        "lambda_eff_nm = 530.0\nthrow_terms = [{ i = 0, j = 0, c = 1.0 }]\n",
    );
    let e = Instrument::from_toml_str(&text, Path::new("c.toml")).unwrap_err().to_string();
    assert!(e.contains("filters.V.throw_terms") && e.contains("only a strip layout"), "{e}");
}
