//! `instpol trend` follows one instrument: plans of two instruments are refused naming both,
//! put together only with `--allow-mismatch` (a warning, and the table records it), and the
//! table says what its points are of (the instrument and the BLAKE3 of its definition, the
//! plans' BLAKE3), as every product does.

use crate::common;

fn plan(dir: &std::path::Path, name: &str, instrument: &str) -> std::path::PathBuf {
    let p = dir.join(name);
    let text = format!(
        "version = {}\ninstrument = \"{instrument}\"\nrecords = \"{}\"\nunits = []\n",
        workflow::night::plan::PLAN_VERSION,
        dir.join(format!(".records-{name}")).display()
    );
    std::fs::write(&p, text).unwrap();
    p
}

#[test]
fn plans_of_two_instruments_are_refused_or_recorded() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let (a, b, c) = (plan(d, "a.toml", "fors1"), plan(d, "b.toml", "fors1"), plan(d, "c.toml", "fors2"));
    let s = |p: &std::path::Path| p.display().to_string();
    let out = d.join("trend.ecsv");
    let (code, _, err) = common::run(&["trend", &s(&a), &s(&c), "--out", &s(&out)]);
    assert_eq!(code, 2, "{err}");
    assert!(
        err.contains("c.toml") && err.contains("FORS2") && err.contains("a.toml") && err.contains("FORS1"),
        "{err}"
    );
    assert!(!out.exists(), "nothing written");
    let (code, _, err) = common::run(&["trend", &s(&a), &s(&c), "--out", &s(&out), "--allow-mismatch"]);
    assert_eq!(code, 0, "{err}");
    assert!(err.contains("warning: --allow-mismatch"), "{err}");
    let t = skyfield::table::Table::read(&out, None).unwrap();
    assert_eq!(t.product.and_then(|p| p.mismatch_allowed).as_deref(), Some("plans of FORS1 and FORS2"));
    std::fs::remove_file(&out).unwrap();
    // One instrument: its name, its definition's BLAKE3 and the plans' BLAKE3, in order.
    let (code, _, err) = common::run(&["trend", &s(&a), &s(&b), "--out", &s(&out)]);
    assert_eq!(code, 0, "{err}");
    let p = skyfield::table::Table::read(&out, None).unwrap().product.expect("the trend's product");
    assert_eq!(p.instrument.as_deref(), Some("FORS1"));
    assert!(p.mismatch_allowed.is_none());
    let def = instrument::Instrument::load("fors1").unwrap().definition.expect("a built-in keeps its text");
    assert_eq!(p.instrument_hash, Some(skyfield::provenance::hash_hex(def.as_bytes())));
    if let Some(sums) = common::b3sum(&[&a, &b]) {
        assert_eq!(p.inputs, sums);
    }
}

/// Plans with no unit done give an empty trend, said as such (not "0 measurements of 0
/// series"), with what to do.
#[test]
fn an_empty_trend_says_why() {
    let dir = tempfile::tempdir().unwrap();
    let a = plan(dir.path(), "a.toml", "fors1");
    let out = dir.path().join("trend.ecsv");
    let (code, stdout, err) = common::run(&["trend", &a.display().to_string(), "--out", &out.display().to_string()]);
    assert_eq!(code, 0, "{err}");
    assert!(stdout.contains("no measurements") && stdout.contains("instpol run"), "{stdout}");
    assert!(!stdout.contains("of 0 series"), "{stdout}");
}
