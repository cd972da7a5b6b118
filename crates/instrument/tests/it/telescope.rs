//! The `[telescope]` section: EFOSC2 loads as a Nasmyth instrument with the ESO keywords and an
//! aluminium M3 at 45 deg (cited in the file), FORS1/FORS2 as Cassegrain ones, and bad sections
//! are refused by key.

use instrument::{Focus, Instrument};
use std::path::Path;

#[test]
fn builtins_say_where_they_sit() {
    let e = Instrument::load("efosc2").unwrap();
    let t = e.telescope.as_ref().expect("EFOSC2 has a [telescope] section");
    assert_eq!(t.focus, Focus::Nasmyth);
    assert_eq!(t.parang_start_keyword, "HIERARCH ESO TEL PARANG START");
    assert_eq!(t.parang_end_keyword, "HIERARCH ESO TEL PARANG END");
    assert_eq!(t.rotator_keyword, "HIERARCH ESO ADA POSANG");
    let m3 = t.oblique_mirror().unwrap();
    assert_eq!((m3.name.as_str(), m3.metal.as_str(), m3.aoi_deg), ("M3", "aluminium", 45.0));
    // La Silla, 29 deg 15' S.
    assert!((t.site_latitude_deg.unwrap() + 29.25).abs() < 0.02);
    for f in ["fors1", "fors2"] {
        let i = Instrument::load(f).unwrap();
        assert_eq!(i.telescope.as_ref().map(|t| t.focus), Some(Focus::Cassegrain), "{f}");
    }
    assert!(Instrument::load("calcite").unwrap().telescope.is_none());
}

#[test]
fn bad_telescope_sections_are_named() {
    let base = include_str!("../../../../instruments/efosc2.toml");
    for (from, to, key) in [
        ("focus = \"nasmyth\"", "focus = \"prime\"", "focus"),
        ("site_latitude_deg = -29.26", "site_latitude_deg = -129.0", "telescope.site_latitude_deg"),
        ("parang_sense = 1 ", "parang_sense = 2 ", "telescope.parang_sense"),
        ("aoi_deg = 45.0", "aoi_deg = 95.0", "telescope.mirrors.M3.aoi_deg"),
        ("aoi_deg = 45.0", "aoi_deg = 0.0", "telescope.mirrors"),
        (
            "metal = \"aluminium\"                                 # [W18]",
            "metal = \"gold.txt\"",
            "telescope.mirrors.M3.metal",
        ),
        ("aoi_deg = 45.0", "aoi_deg = 45.0\noverlayer = \"glass\"", "telescope.mirrors.M3.overlayer"),
        (
            "aoi_deg = 45.0",
            "aoi_deg = 45.0\noverlayer_thickness_nm = 5.0",
            "telescope.mirrors.M3.overlayer_thickness_nm",
        ),
        ("focus = \"nasmyth\"", "focus = \"cassegrain\"", "telescope.mirrors.M3.aoi_deg"),
        ("rotator_sense = 1", "rotator_snse = 1", "rotator_snse"),
    ] {
        let text = base.replacen(from, to, 1);
        assert_ne!(text, base, "{from}");
        let e = Instrument::from_toml_str(&text, Path::new("e.toml")).unwrap_err().to_string();
        assert!(e.contains("e.toml") && e.contains(key), "{key}: {e}");
    }
    // An over-layer of alumina or a real index is fine.
    let ok =
        base.replacen("aoi_deg = 45.0", "aoi_deg = 45.0\noverlayer = \"alumina\"\noverlayer_thickness_nm = 8.0", 1);
    Instrument::from_toml_str(&ok, Path::new("e.toml")).unwrap();
    let ok = base.replacen("aoi_deg = 45.0", "aoi_deg = 45.0\noverlayer = \"1.38\"\noverlayer_thickness_nm = 100", 1);
    Instrument::from_toml_str(&ok, Path::new("e.toml")).unwrap();
}
