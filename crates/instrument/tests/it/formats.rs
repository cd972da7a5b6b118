//! The `[format]` section: the built-in FORS2 and EFOSC2 files load with the numbers their
//! manuals give (cited in the files), FORS1 needs no section, and bad sections are named.

use instrument::{Instrument, NumberOrKeyword};
use std::path::Path;

#[test]
fn builtins_load_with_their_formats() {
    let f1 = Instrument::load("fors1").unwrap();
    assert!(!f1.format.is_raw(), "FORS1's simulated frames are plain images");
    let f2 = Instrument::load("FORS2").unwrap();
    assert_eq!(f2.format.chips.len(), 2);
    assert_eq!(f2.format.binning, vec![2, 2]);
    // ESO QC: raw 2x2 chip files are 2048 x 1034 with 5-px prescan and overscan rows.
    for c in &f2.format.chips {
        assert_eq!(c.size_px, [2048, 1024]);
        assert!(matches!(&c.prescan_y, Some(NumberOrKeyword::Keyword(k)) if k == "HIERARCH ESO DET OUT1 PRSCY"));
    }
    assert_eq!(f2.detector.pixel_scale_arcsec, 0.25);
    let e2 = Instrument::load("efosc2").unwrap();
    assert_eq!(e2.format.raw_bias_adu, Some(220.0));
    assert!(!e2.format.chips[0].subtract_overscan);
}

#[test]
fn bad_format_sections_are_named() {
    let base = include_str!("../../../../instruments/fors2.toml");
    for (from, to, key) in [
        ("binning = [2, 2]", "binning = [2]", "format.binning"),
        ("origin_px = [0, 1040]", "origin_px = [0, 1100]", "format.chips.CHIP1.origin_px"),
        ("origin_px = [0, 1040]", "origin_px = [0, 1000]", "overlaps"),
        ("match_value = \"CHIP1\"\n", "", "match_keyword and match_value"),
        ("subtract_overscan = true", "subtract_overscan = 1", "subtract_overscan"),
        ("size_px = [2048, 1024]         # [QC] 2048", "size_pix = [2048, 1024]  # [QC] 2048", "size_pix"),
    ] {
        let text = base.replacen(from, to, 1);
        if text == base {
            continue;
        }
        let e = Instrument::from_toml_str(&text, Path::new("f2.toml")).unwrap_err().to_string();
        assert!(e.contains(key) && e.contains("f2.toml"), "{from} -> {to}: {e}");
    }
}
