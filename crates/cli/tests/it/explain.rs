//! `instpol explain` end to end: a stressed-lens Mueller field written by the fit library is
//! explained by a stressed lens (with the FORS1 ray trace among the candidates), and bad
//! inputs exit with code 2 naming the input.

use crate::common;

use fit::mueller_field::{fit_mueller_field, CalField, Kind, MuellerFitOptions, Observation};
use mueller::linear::{physical_block, retardance_vector};

/// Noise-free observations (small variances) of a field on three skies.
pub(crate) fn fields(ret_deg: f64) -> Vec<CalField> {
    [(0.0645, 68.4f64), (0.04, 10.0), (0.08, 130.0)]
        .iter()
        .map(|&(p, chi)| {
            let chi = chi.to_radians();
            let (q0, u0) = (p * (2.0 * chi).cos(), p * (2.0 * chi).sin());
            let mut obs = Vec::new();
            for j in 0..15 {
                for i in 0..15 {
                    let (x, y) = (-3.4 + 6.8 * (i as f64 + 0.5) / 15.0, -3.4 + 6.8 * (j as f64 + 0.5) / 15.0);
                    let (d, ax) = mueller::causes::stressed_lens(x, y, ret_deg.to_radians(), 3.4, [0.5, 0.3], 0.0);
                    let b = physical_block(2e-4 * (x * x - y * y), 4e-4 * x * y, retardance_vector(d, ax), 0.0, 0.0);
                    let (q, u) = b.forward(q0, u0).unwrap();
                    let v = 1e-8;
                    obs.push(Observation::new(x, y, q, u, v, v, 0.0));
                }
            }
            CalField::from_p_chi("f", p, chi, 0.0, obs)
        })
        .collect()
}

/// The Mueller field of `kind` fitted to the stressed lens's fields, written as `name` in `dir`
/// (the caller's temporary folder, removed with it).
pub(crate) fn write(dir: &std::path::Path, kind: Kind, name: &str) -> std::path::PathBuf {
    let mf =
        fit_mueller_field(&fields(18.0), &MuellerFitOptions { kind, deg: 4, scale_arcmin: 3.4, ..Default::default() })
            .unwrap();
    let p = dir.join(name);
    std::fs::write(&p, mf.to_json()).unwrap();
    p
}

#[test]
fn stressed_lens_file_is_explained_by_a_stressed_lens() {
    let tmp = tempfile::tempdir().unwrap();
    let f = write(tmp.path(), Kind::diattenuation_retardance(), "lens.json");
    let (code, out, err) =
        common::run(&["explain", f.to_str().unwrap(), "--instrument", "fors1", "--band", "B", "--json"]);
    assert_eq!(code, 0, "{err}");
    let v: serde_json::Value = serde_json::from_str(&out).unwrap();
    assert_eq!(v["best"], "stressed_lens", "{out}");
    let causes = v["causes"].as_array().unwrap();
    assert!(causes.iter().any(|c| c["cause"] == "raytrace"), "the FORS1 ray trace is a candidate: {out}");
    let lens = &causes[0]["params"][0];
    assert!((lens["value"].as_f64().unwrap().abs() - 18.0).abs() < 0.5, "{lens}");
    // The plot in the format its extension names (PNG bytes, or an SVG document).
    for (name, magic) in [("e.svg", &b"<svg"[..]), ("e.png", &b"\x89PNG"[..])] {
        let plot = f.with_file_name(name);
        let (code, _, err) = common::run(&[
            "explain",
            f.to_str().unwrap(),
            "--instrument",
            "fors1",
            "--band",
            "B",
            "--plot",
            plot.to_str().unwrap(),
        ]);
        assert_eq!(code, 0, "{err}");
        assert!(std::fs::read(&plot).unwrap().starts_with(magic), "{name}");
    }
}

#[test]
fn bad_inputs_exit_2_naming_the_input() {
    let tmp = tempfile::tempdir().unwrap();
    let diat =
        write(tmp.path(), Kind::Physical { retardance: false, rotation: false, depolarization: false }, "diat.json");
    let lens = write(tmp.path(), Kind::diattenuation_retardance(), "lens2.json");
    let d = diat.to_str().unwrap();
    let l = lens.to_str().unwrap();
    let cases: Vec<(Vec<&str>, &str)> = vec![
        (vec!["explain", d], "diat.json"),
        (vec!["explain", l, "--hwp-angles", "0,22.5,x"], "--hwp-angles"),
        (vec!["explain", l, "--hwp-angles", "0,0"], "--hwp-angles"),
        (vec!["explain", l, "--causes", "gremlins"], "gremlins"),
        (vec!["explain", l, "--magnification", "-1"], "magnification"),
        (vec!["explain", "/nonexistent/m.json"], "m.json"),
        (vec!["explain", l, "--grid", "2"], "--grid"),
    ];
    for (mut args, needle) in cases {
        // A JSON field records no instrument: it is named.
        args.extend(["--instrument", "fors1"]);
        let (code, _, err) = common::run(&args);
        assert_eq!(code, 2, "{args:?}: {err}");
        assert!(err.contains(needle), "{args:?}: {err}");
        assert!(!err.contains("panicked"), "{err}");
    }
}

/// A Mueller-field calibration records its instrument and filter: explaining a FORS1 B field as
/// EFOSC2 (another instrument's optics) or in V (another wavelength) is refused naming both;
/// its own instrument and band are accepted.
#[test]
fn a_field_is_explained_with_its_own_instrument_and_band() {
    let dir = tempfile::tempdir().unwrap();
    let mf = fit_mueller_field(
        &fields(18.0),
        &MuellerFitOptions { kind: Kind::diattenuation_retardance(), deg: 4, scale_arcmin: 3.4, ..Default::default() },
    )
    .unwrap();
    let cal = fit::mueller_field::cal::MuellerCal {
        instrument: "FORS1".into(),
        filter: "B".into(),
        field: mf,
        coords: None,
        skies: vec![],
        per_bin: vec![],
        provenance: fit::files::calfile::Provenance::now("test", vec![]),
        hwp_chi_offset_deg: 0.0,
    };
    let path = dir.path().join("fors1_B.fits");
    cal.save(&path).unwrap();
    let p = path.to_str().unwrap();
    for (inst, band, needle) in [("efosc2", "V", "instrument FORS1"), ("fors1", "V", "filter B")] {
        let (code, _, err) =
            common::run(&["explain", p, "--instrument", inst, "--band", band, "--causes", "stressed_lens"]);
        assert_eq!(code, 2, "{inst} {band}: {err}");
        assert!(err.contains("fors1_B.fits") && err.contains(needle), "{inst} {band}: {err}");
    }
    let (code, _, err) =
        common::run(&["explain", p, "--instrument", "fors1", "--band", "B", "--causes", "stressed_lens"]);
    assert_eq!(code, 0, "{err}");
}
