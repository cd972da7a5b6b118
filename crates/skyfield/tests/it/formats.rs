//! Frame formats against astropy: tiny files written by astropy
//! (`tests/data/formats/make_formats.py`) with what astropy reads from them
//! (`expected.json`: BSCALE/BZERO applied, BLANK pixels NaN). The reader must give the same
//! pixels for every BITPIX (8, 16, 32, 64, -32, -64) with the signed/unsigned conventions, a
//! scaled image, BLANK, an image in extension 1 found automatically, `file.fits[2]` and
//! `file.fits[CHIP2]`, a file whose own name has brackets, gzip and tile compression (RICE,
//! GZIP_2). Also: a table where an image is wanted, conflicting duplicate keywords, and
//! several images without a choice are errors that name the file and the HDU or keyword.

use instrument::Instrument;
use std::path::{Path, PathBuf};

fn data_dir() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/data/formats")
}

/// FORS1 shrunk to the 12 x 20 px of the astropy files.
fn tiny() -> Instrument {
    let text = include_str!("../../../../instruments/fors1.toml")
        .replace("nx = 2048", "nx = 12")
        .replace("ny = 2048", "ny = 20")
        .replace("throw_arcsec = 22.0", "throw_arcsec = 2.0")
        .replace("strip_count = 9", "strip_count = 1")
        .replace("first_strip_y_px = 34", "first_strip_y_px = 0");
    Instrument::from_toml_str(&text, Path::new("tiny12x20.toml")).unwrap()
}

#[derive(serde::Deserialize)]
struct Case {
    file: String,
    nx: usize,
    ny: usize,
    values: Vec<Option<f64>>,
}

#[test]
fn every_format_reads_the_pixels_astropy_reads() {
    let inst = tiny();
    let cases: Vec<Case> =
        serde_json::from_str(&std::fs::read_to_string(data_dir().join("expected.json")).unwrap()).unwrap();
    assert_eq!(cases.len(), 18);
    for c in &cases {
        let p = data_dir().join(&c.file);
        let fr = skyfield::io::read_frame(&p, &inst).unwrap_or_else(|e| panic!("{}: {e}", c.file));
        assert_eq!((fr.nx, fr.ny), (c.nx, c.ny), "{}", c.file);
        assert_eq!(fr.hwp_deg, 22.5, "{}: HWP angle from the primary header", c.file);
        assert_eq!(fr.filter, "V_BESS", "{}", c.file);
        let mut nan = 0;
        for (k, (got, want)) in fr.data.iter().zip(&c.values).enumerate() {
            match want {
                None => {
                    assert!(got.is_nan(), "{} pixel {k}: {got}, astropy: NaN (BLANK)", c.file);
                    nan += 1;
                }
                // serde_json's default float parser may be 1 ulp off the JSON's shortest decimal.
                Some(w) => {
                    assert!((got - w).abs() <= 2.0 * f64::EPSILON * w.abs(), "{} pixel {k}: {got} vs {w}", c.file)
                }
            }
        }
        if c.file == "prim_blank.fits" {
            assert_eq!(nan, 3, "the three BLANK pixels are masked, not data");
        }
    }
}

#[test]
fn a_table_where_an_image_is_wanted_is_named() {
    let inst = tiny();
    let p = data_dir().join("mef.fits[1]");
    let e = skyfield::io::read_frame(&p, &inst).unwrap_err().to_string();
    assert!(e.contains("mef.fits") && e.contains("HDU 1 (TAB)") && e.contains("binary table"), "{e}");
    let p = data_dir().join("mef.fits[TAB]");
    let e = skyfield::io::read_frame(&p, &inst).unwrap_err().to_string();
    assert!(e.contains("HDU 1 (TAB)") && e.contains("not an image"), "{e}");
}

#[test]
fn several_images_without_a_choice_are_refused_naming_them() {
    let inst = tiny();
    let e = skyfield::io::read_frame(&data_dir().join("mef.fits"), &inst).unwrap_err().to_string();
    assert!(e.contains("mef.fits") && e.contains("2 image HDUs") && e.contains("CHIP1") && e.contains("[2]"), "{e}");
}

/// A second BZERO card with another value: refused naming both values (CFITSIO would take
/// the first silently).
#[test]
fn conflicting_duplicate_keywords_are_refused() {
    let inst = tiny();
    let dir = tempfile::tempdir().unwrap();
    let mut bytes = std::fs::read(data_dir().join("prim_u16.fits")).unwrap();
    // Replace the END card with a second BZERO and move END one card on (same header block).
    let end = (0..bytes.len() / 80).map(|k| k * 80).find(|&o| bytes[o..o + 80].starts_with(b"END     ")).unwrap();
    let card = format!("{:<80}", "BZERO   =                  0.0 / a conflicting duplicate");
    bytes[end..end + 80].copy_from_slice(card.as_bytes());
    bytes[end + 80..end + 160].copy_from_slice(format!("{:<80}", "END").as_bytes());
    let p = dir.path().join("dup.fits");
    std::fs::write(&p, &bytes).unwrap();
    let e = skyfield::io::read_frame(&p, &inst).unwrap_err().to_string();
    assert!(e.contains("dup.fits") && e.contains("BZERO") && e.contains("32768") && e.contains("and 0"), "{e}");
}
