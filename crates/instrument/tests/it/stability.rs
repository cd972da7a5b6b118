//! Stability of the instrument loader at the edges of its numbers: pixel <-> arcmin
//! round trips across the detector, and absurd but syntactically valid values in the TOML that
//! must be refused with an error naming the key, never a panic or an arithmetic overflow.
//! (No proptest here: deterministic sweeps cover the ranges.)

use instrument::Instrument;
use std::path::Path;

const FORS1: &str = include_str!("../../../../instruments/fors1.toml");

/// Load with `from` replaced by `to`, catching panics: Ok(Ok) loaded, Ok(Err(msg)) refused,
/// Err(panic message) a panic.
fn load_patched(from: &str, to: &str) -> Result<Result<Instrument, String>, String> {
    assert!(FORS1.contains(from), "{from}");
    let text = FORS1.replacen(from, to, 1);
    std::panic::catch_unwind(|| Instrument::from_toml_str(&text, Path::new("patched.toml")).map_err(|e| e.to_string()))
        .map_err(|p| {
            p.downcast_ref::<String>()
                .cloned()
                .or_else(|| p.downcast_ref::<&str>().map(|s| s.to_string()))
                .unwrap_or_default()
        })
}

/// pixel -> arcmin -> pixel is the identity to rounding over the whole detector and beyond,
/// and the detector centre is (0, 0) arcmin (the field coordinates of `docs/architecture.md`,
/// Conventions).
#[test]
fn pixel_arcmin_round_trip() {
    let inst = Instrument::load("fors1").unwrap();
    let (cx, cy) = inst.pixel_to_arcmin(0.5 * (inst.detector.nx as f64 - 1.0), 0.5 * (inst.detector.ny as f64 - 1.0));
    assert_eq!((cx, cy), (0.0, 0.0));
    // 0.2 arcsec/px: the detector edge is 1024 px = 3.413 arcmin from the centre (6.8' field).
    let (ex, _) = inst.pixel_to_arcmin(-0.5, 0.0);
    assert!((ex + 1024.0 * 0.2 / 60.0).abs() < 1e-12);
    for i in -50..=50 {
        for j in -50..=50 {
            let (x, y) = (1023.5 + 60.0 * i as f64 + 0.37, 1023.5 + 60.0 * j as f64 - 0.11);
            let (a, b) = inst.pixel_to_arcmin(x, y);
            let (x2, y2) = inst.arcmin_to_pixel(a, b);
            assert!((x2 - x).abs() < 1e-9 && (y2 - y).abs() < 1e-9, "{x} {y} -> {x2} {y2}");
        }
    }
}

/// Sane edits load; small strips fit.
#[test]
fn control_edits_load() {
    assert!(load_patched("strip_count = 9", "strip_count = 8").unwrap().is_ok());
    assert!(load_patched("throw_arcsec = 22.0", "throw_arcsec = 21.0").unwrap().is_ok());
}

/// Values that make the strip arithmetic overflow must be refused with the key named.
///
/// Regression (a defect found by fuzz/run.sh, fuzz_instrument_toml; fixed in 833bbbb): `throw_arcsec = 1e308` (any throw of
/// more than ~2^63 px) is ACCEPTED: `throw_px()` saturates to `usize::MAX`, `h as i64` is -1 in
/// `validate`, so `hi = first + 2 * count * (-1)` comes out small and passes the detector check;
/// then `strips()` panics with "attempt to add with overflow" (debug) or wraps (release). Huge
/// `strip_count` / `first_strip_y_px` (up to 2^63 from TOML) overflow `2 * strip_count` the
/// same way. Fix (crates/instrument/src/lib.rs, `validate`): refuse a throw larger than the
/// detector (`throw_arcsec / pixel_scale_arcsec > extent`) before any integer arithmetic, and
/// compute `lo`/`hi` with checked (or i128) arithmetic. Also (minor, next test): a negative
/// `saturation_adu` is accepted (every pixel then counts as saturated).
#[test]
fn absurd_geometry_is_refused_not_overflowed() {
    for (from, to, key) in [
        ("throw_arcsec = 22.0", "throw_arcsec = 1e308", "throw"),
        ("throw_arcsec = 22.0", "throw_arcsec = 2e21", "throw"),
        ("strip_count = 9", "strip_count = 4611686018427387904", "strip_count"),
        ("first_strip_y_px = 34", "first_strip_y_px = 9223372036854775807", "first_strip_y_px"),
        ("pixel_scale_arcsec = 0.2", "pixel_scale_arcsec = 1e-300", "pixel_scale"),
    ] {
        match load_patched(from, to) {
            Err(panic) => panic!("{to}: panicked: {panic}"),
            Ok(Ok(_)) => panic!("{to}: accepted an instrument whose strips cannot exist"),
            Ok(Err(msg)) => assert!(msg.contains("patched.toml") && msg.contains(key), "{to}: {msg}"),
        }
    }
}

/// Non-finite and non-positive scales are refused by name.
#[test]
fn non_physical_numbers_are_refused() {
    for (from, to, key) in [
        ("pixel_scale_arcsec = 0.2", "pixel_scale_arcsec = nan", "pixel_scale_arcsec"),
        ("pixel_scale_arcsec = 0.2", "pixel_scale_arcsec = inf", "pixel_scale_arcsec"),
        ("pixel_scale_arcsec = 0.2", "pixel_scale_arcsec = 0.0", "pixel_scale_arcsec"),
        ("throw_arcsec = 22.0", "throw_arcsec = -22.0", "throw_arcsec"),
        ("throw_arcsec = 22.0", "throw_arcsec = nan", "throw_arcsec"),
        ("gain_e_per_adu = 1.25", "gain_e_per_adu = 0.0", "gain_e_per_adu"),
        ("saturation_adu = 65535.0", "saturation_adu = -1.0", "saturation_adu"),
    ] {
        match load_patched(from, to) {
            Err(panic) => panic!("{to}: panicked: {panic}"),
            Ok(Ok(_)) => panic!("{to}: accepted"),
            Ok(Err(msg)) => assert!(msg.contains(key), "{to}: {msg}"),
        }
    }
}

/// Beam layouts: an unknown layout, a maskless offset outside the detector or shorter than
/// 2 px, strip fields in a maskless file, overlapping explicit strips and a throw variation
/// larger than the strip margin are refused by name; the maskless example loads.
#[test]
fn beam_layout_errors_are_named() {
    let cases = [
        ("strip_axis = \"y\"", "layout = \"calcite\"\nstrip_axis = \"y\"", "calcite"),
        ("strip_axis = \"y\"", "strip_axis = \"y\"\nthrow_terms = [{ i = 1, j = 0, c = 2.0 }]", "strip_margin_px"),
        ("strip_axis = \"y\"", "strip_axis = \"y\"\nstrip_margin_px = 60", "strip_margin_px"),
        ("strip_axis = \"y\"", "strip_axis = \"y\"\nstrip_starts_px = [34.0, 100.0]", "overlap"),
        ("strip_axis = \"y\"", "strip_axis = \"y\"\nstrip_starts_px = [1990.0]", "outside the detector"),
        ("strip_axis = \"y\"", "strip_axis = \"y\"\noe_offset_px = [3.0, 0.0]", "maskless"),
    ];
    for (from, to, key) in cases {
        match load_patched(from, to) {
            Err(panic) => panic!("{to}: panicked: {panic}"),
            Ok(Ok(_)) => panic!("{to}: accepted"),
            Ok(Err(msg)) => assert!(msg.contains("patched.toml") && msg.contains(key), "{to}: {msg}"),
        }
    }
    let calcite = include_str!("../../../../instruments/calcite.toml");
    for (to, key) in [
        ("oe_offset_px = [900.0, 0.0]", "oe_offset_px"),
        ("oe_offset_px = [1.0, 0.5]", "oe_offset_px"),
        ("oe_offset_px = [70.2, 0.0]\nstrip_count = 3", "no strips"),
    ] {
        let text = calcite.replacen("oe_offset_px = [70.2, 0.0]", to, 1);
        let e = Instrument::from_toml_str(&text, Path::new("cal.toml")).unwrap_err().to_string();
        assert!(e.contains("cal.toml") && e.contains(key), "{to}: {e}");
    }
    let c = Instrument::load("calcite").unwrap();
    assert_eq!(c.polarimetry.layout, instrument::Layout::Maskless);
    assert!(c.strips().is_empty());
}

/// Strip positions as real numbers: a strip whose o image starts at 34.4 px uses the whole rows
/// 35..144 (109 rows: the partly covered row 34 is left out), e rows a whole throw (110 px)
/// above; a 2 px margin trims two rows at each edge.
#[test]
fn real_strip_edges_give_whole_rows_inside() {
    let i = load_patched("first_strip_y_px = 34", "first_strip_y_px = 34.4").unwrap().unwrap();
    let s = i.strips()[0];
    assert_eq!((s.o_start, s.height, s.e_start), (35, 109, 145));
    let i = load_patched("first_strip_y_px = 34", "first_strip_y_px = 34\nstrip_margin_px = 2").unwrap().unwrap();
    let s = i.strips()[1];
    assert_eq!((s.o_start, s.height, s.e_start), (34 + 220 + 2, 106, 34 + 220 + 2 + 110));
}

/// The built-in instruments load, their strips inside the detector and their images disjoint
/// (the loader refuses anything else), with the facts their files cite: FORS2 88 px throw at
/// 0.25"/px (22", PR06) and EFOSC2 83.3 px (20" at 0.24"/px).
#[test]
fn builtin_instruments_load_with_their_cited_facts() {
    for name in ["fors1", "fors2", "efosc2", "calcite"] {
        Instrument::load(name).unwrap_or_else(|e| panic!("{name}: {e}"));
    }
    let f2 = Instrument::load("fors2").unwrap();
    assert!((f2.throw_px_exact() - 88.0).abs() < 1e-12);
    assert_eq!(f2.strips().len(), 9);
    let e2 = Instrument::load("efosc2").unwrap();
    assert!((e2.throw_px_exact() - 20.0 / 0.24).abs() < 1e-12);
    let s = e2.strips();
    assert!(s.iter().all(|s| s.height >= 80 && s.e_start + s.height <= 1024), "{s:?}");
}

/// A detector too large to hold in memory (4e9 x 4e9, or 1e9 px in all) is refused by name
/// before anything allocates for it.
#[test]
fn absurd_detector_size_is_refused() {
    for (from, to) in [("nx = 2048", "nx = 4000000000"), ("ny = 2048", "ny = 300000")] {
        let r = load_patched(from, to).expect("no panic");
        let msg = r.err().unwrap_or_default();
        assert!(msg.contains("detector.nx/ny") && msg.contains("GB"), "{to}: {msg}");
    }
}
