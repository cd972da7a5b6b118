//! A calibration file says what it is, as every table and map does: the product keywords
//! (the instrument file's BLAKE3, the filter, the plate, the detector, the inputs' BLAKE3) in
//! its primary header, given back by the one reader of calibration files; and the one
//! compatibility check reads them, so that data measured on another detector are refused by
//! name, and data made with another version of the instrument's file are said.
//!
//! The hashes are checked against `b3sum` (or Python's `blake3`), an implementation apart.

use crate::common::{self, run};
use std::path::{Path, PathBuf};

fn s(p: &Path) -> String {
    p.to_str().unwrap().to_string()
}

/// The built-in FORS1 file as shipped (its text is the definition the binary hashes).
fn fors1_toml() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../../instruments/fors1.toml")
}

/// A FORS1 V map (no product of its own) and its calibration by `instpol calibrate --map`.
fn map_and_calibration(dir: &Path) -> (PathBuf, PathBuf) {
    let map = dir.join("map_v_sky_of_fors1.fits");
    common::write_v_sky_map(&map, |_| true);
    let cal = dir.join("cal.fits");
    let (code, _, err) =
        run(&["calibrate", "--map", &s(&map), "--sky-p", "1.74", "--sky-chi", "-53.8", "--out", &s(&cal)]);
    assert_eq!(code, 0, "calibrate: {err}");
    (map, cal)
}

/// The map at `from` written again at `to` with the product `edit` makes of FORS1's, and
/// photometric errors.
fn map_with_product(from: &Path, to: &Path, edit: impl Fn(&mut skyfield::provenance::Product)) -> PathBuf {
    let mut m = skyfield::StokesMap::read_fits(from).unwrap();
    // The photometric errors a reduction gives (the test map has only the scatter's).
    m.sigma_q_phot = m.sigma_q.clone();
    m.sigma_u_phot = m.sigma_u.clone();
    let inst = instrument::Instrument::load("fors1").unwrap();
    let mut p = skyfield::provenance::Product::of_instrument(&inst, "V", None);
    edit(&mut p);
    // A map's pixel scale is its geometry's (PIXSCALE), as a reduction on that detector makes it.
    m.geometry.pixel_scale_arcsec = p.pixel_scale_arcsec.unwrap();
    m.product = Some(p);
    m.write_fits(to).unwrap();
    to.to_path_buf()
}

#[test]
fn a_calibration_file_records_what_it_is() {
    let dir = tempfile::tempdir().unwrap();
    let (map, cal) = map_and_calibration(dir.path());
    let file = fit::files::calibration::load(&cal).unwrap();
    let p = file.product.as_ref().expect("the calibration's product");
    assert_eq!(p.instrument.as_deref(), Some("FORS1"));
    assert_eq!(p.filter.as_deref(), Some("V"));
    assert_eq!(p.plate.as_deref(), Some("half_wave"));
    // FORS1's detector as its file gives it: 2048 x 2048 px of 0.2 arcsec (the file cites the
    // FORS user manual).
    assert_eq!(p.detector_px, Some((2048, 2048)));
    assert_eq!(p.pixel_scale_arcsec, Some(0.2));
    // The field calibration's own provenance holds the same product.
    assert_eq!(
        file.field.as_ref().unwrap().provenance.product.as_ref().map(|q| &q.instrument_hash),
        Some(&p.instrument_hash)
    );
    if let Some(sums) = common::b3sum(&[fors1_toml(), map.clone()]) {
        assert_eq!(p.instrument_hash.as_deref(), Some(sums[0].as_str()), "the instrument file's BLAKE3");
        assert!(p.inputs.contains(&sums[1]), "the map's BLAKE3 {} among the inputs {:?}", sums[1], p.inputs);
    }
    // Each product keyword once in the primary header.
    let bytes = std::fs::read(&cal).unwrap();
    let end = bytes.chunks(80).position(|c| c.starts_with(b"END     ")).unwrap();
    let head = &bytes[..end * 80];
    for key in ["INSTRUME", "INSTHASH", "FILTER", "PLATE", "DETSIZE", "PIXSCALE", "INHASH1"] {
        let cards = head.chunks(80).filter(|c| c.starts_with(format!("{key:<8}=").as_bytes())).count();
        assert_eq!(cards, 1, "{key} written {cards} times");
    }
}

#[test]
fn a_telescope_model_file_records_its_instrument_file() {
    let Some(data) =
        common::shared_data::shared_data("efosc2-standards", &["pv_standards.txt"], "the EFOSC2 standards")
    else {
        return;
    };
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("tel.fits");
    let table = data.join("pv_standards.txt");
    let (code, _, err) = run(&["fit-standards", &s(&table), "--instrument", "efosc2", "--output", &s(&out)]);
    assert_eq!(code, 0, "fit-standards: {err}");
    let file = fit::files::calibration::load(&out).unwrap();
    let p = file.product.clone().expect("the telescope model's product");
    assert_eq!(p.instrument.as_deref(), Some("EFOSC2"));
    // A telescope model is the same at every field position: its detector is recorded but not
    // compared (data of any detector of the instrument are corrected with it).
    assert!(p.detector_px.is_some() && file.setup().detector_px.is_none() && file.setup().pixel_scale_arcsec.is_none());
    assert_eq!(p.filter, None, "a telescope model is of bands, not one filter");
    let toml = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../instruments/efosc2.toml");
    if let Some(sums) = common::b3sum(&[toml, table]) {
        assert_eq!(p.instrument_hash.as_deref(), Some(sums[0].as_str()));
        assert!(p.inputs.contains(&sums[1]), "the standards table among the inputs {:?}", p.inputs);
    }
}

#[test]
fn a_map_of_another_detector_is_refused_naming_both() {
    let dir = tempfile::tempdir().unwrap();
    let (map, cal) = map_and_calibration(dir.path());
    let out = dir.path().join("corr.fits");
    for (name, edit, words) in [
        (
            "size",
            Box::new(|p: &mut skyfield::provenance::Product| p.detector_px = Some((1024, 1024)))
                as Box<dyn Fn(&mut skyfield::provenance::Product)>,
            ["1024x1024 px", "2048x2048 px"],
        ),
        (
            "scale",
            Box::new(|p: &mut skyfield::provenance::Product| p.pixel_scale_arcsec = Some(0.25)),
            ["0.25 arcsec/px", "0.2 arcsec/px"],
        ),
    ] {
        let other = map_with_product(&map, &dir.path().join(format!("other_{name}.fits")), edit);
        let (code, _, err) = run(&["correct", "--cal", &s(&cal), "--in", &s(&other), "--out", &s(&out)]);
        assert_ne!(code, 0, "{name}: a map of another detector was corrected: {err}");
        assert!(err.contains("detector") && words.iter().all(|w| err.contains(w)), "{name}: {err}");
        assert!(!out.exists(), "{name}: a refused correction wrote {}", out.display());
        // Allowed: corrected, said, and recorded in the output.
        let (code, _, err) = run(&[
            "correct",
            "--cal",
            &s(&cal),
            "--in",
            &s(&other),
            "--out",
            &s(&out),
            "--allow-mismatch",
            "--allow-extrapolation",
        ]);
        assert_eq!(code, 0, "{name}: {err}");
        assert!(err.contains("warning") && err.contains("detector"), "{name}: {err}");
        let corrected = skyfield::StokesMap::read_fits(&out).unwrap();
        let mismatch = corrected.product.and_then(|p| p.mismatch_allowed).unwrap_or_default();
        assert!(mismatch.contains("detector"), "{name}: MISMATCH = {mismatch:?}");
        std::fs::remove_file(&out).unwrap();
    }
}

#[test]
fn a_map_made_with_another_instrument_file_is_corrected_and_said() {
    let dir = tempfile::tempdir().unwrap();
    let (map, cal) = map_and_calibration(dir.path());
    let edited = "blake3:".to_string() + &"ab".repeat(32);
    let other = map_with_product(&map, &dir.path().join("edited.fits"), |p| p.instrument_hash = Some(edited.clone()));
    let out = dir.path().join("corr.fits");
    let (code, _, err) = run(&["correct", "--cal", &s(&cal), "--in", &s(&other), "--out", &s(&out)]);
    assert_eq!(code, 0, "{err}");
    assert!(err.contains("two different instrument files") && err.contains(&edited), "{err}");
    // The same map with the calibration's own instrument file: nothing said.
    let same = map_with_product(&map, &dir.path().join("same.fits"), |_| {});
    let (code, _, err) = run(&["correct", "--cal", &s(&cal), "--in", &s(&same), "--out", &s(&out)]);
    assert_eq!(code, 0, "{err}");
    assert!(!err.contains("instrument files"), "{err}");
}

/// The rule itself on setups written here: a plate both sides name and that differs is
/// refused, and sides that do not say are not compared.
#[test]
fn plates_and_detectors_are_compared_only_where_both_sides_say() {
    use fit::correction::setup::{check_compatible, Mismatch, Setup};
    let data = Setup { plate: Some("half_wave".into()), ..Setup::named("FORS1", "V") };
    let cal = Setup { plate: Some("quarter_wave".into()), ..Setup::named("FORS1", "V") };
    assert!(matches!(check_compatible(&data, Some(&cal)), Err(Mismatch::PlateDiffers { .. })));
    let silent = Setup::named("FORS1", "V");
    assert_eq!(check_compatible(&data, Some(&silent)), Ok(()));
    let d = Setup { detector_px: Some((2048, 2048)), ..silent.clone() };
    let c = Setup { detector_px: Some((4096, 2048)), ..silent.clone() };
    assert!(matches!(check_compatible(&d, Some(&c)), Err(Mismatch::Geometry { .. })));
    assert_eq!(check_compatible(&d, Some(&silent)), Ok(()));
}
