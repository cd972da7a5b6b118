//! The scene-file page (`docs/guide/scene-file.md`) documents every key the scene parser
//! accepts, and no key it does not.
//!
//! The keys are those of `sim::scene::Scene` as serde reads them: a scene is built here with
//! every field of every table set, written out through serde (the same field names the parser
//! reads, `deny_unknown_fields` everywhere) and its keys collected as dotted paths. The scene is
//! written as struct literals without `..`: a field added to any of the scene's tables stops
//! this file compiling until it is set here, and then the comparison asks for its row on the
//! page. Each key so found is parsed back by the scene parser (as TOML), so the list is one the
//! parser accepts.

use sim::scene::*;
use std::collections::BTreeSet;
use std::path::{Path, PathBuf};

fn page() -> String {
    std::fs::read_to_string(Path::new(env!("CARGO_MANIFEST_DIR")).join("../../docs/guide/scene-file.md")).unwrap()
}

/// The keys of the page's tables: every backticked name of a row's first cell (`a`, `b` in
/// "`a`, `b`"), in tables whose header starts with `| key |`.
fn page_keys(text: &str) -> BTreeSet<String> {
    let mut keys = BTreeSet::new();
    let mut in_table = false;
    for line in text.lines() {
        if line.starts_with("| key |") {
            in_table = true;
            continue;
        }
        if !line.starts_with('|') {
            in_table = false;
            continue;
        }
        if !in_table || line.starts_with("|---") {
            continue;
        }
        let first = line.split('|').nth(1).unwrap_or("");
        for k in first.split('`').skip(1).step_by(2) {
            keys.insert(k.to_string());
        }
    }
    keys
}

/// Every dotted key path of a JSON value's objects (arrays' elements under their array's name;
/// `free` paths are free-form tables, a key of their own).
fn key_paths(v: &serde_json::Value, prefix: &str, free: &[&str], out: &mut BTreeSet<String>) {
    match v {
        serde_json::Value::Object(m) if !free.contains(&prefix) => {
            for (k, x) in m {
                let p = if prefix.is_empty() { k.clone() } else { format!("{prefix}.{k}") };
                if matches!(x, serde_json::Value::Object(_) | serde_json::Value::Array(_)) {
                    let mut inner = BTreeSet::new();
                    key_paths(x, &p, free, &mut inner);
                    // A table or list of tables is documented by its keys; a list of numbers
                    // (or a free-form table) is a key itself.
                    if inner.is_empty() {
                        out.insert(p);
                    }
                    out.extend(inner);
                } else {
                    out.insert(p);
                }
            }
        }
        serde_json::Value::Array(a) => a.iter().for_each(|x| key_paths(x, prefix, free, out)),
        _ => {}
    }
}

/// A scene with every field of every table set (none at a value serde leaves out), with the
/// instrumental field of `instpol`.
fn full_scene(instpol: InstPolSpec) -> Scene {
    let harmonic = || HarmonicSpec { amplitude: 0.001, phase_deg: 10.0 };
    Scene {
        instrument: "fors1".into(),
        filter: "V".into(),
        hwp_angles_deg: default_angles(),
        exposure_s: 10.0,
        seed: 1,
        output: Output {
            bitpix: -32,
            prefix: "f".into(),
            raw_bias_adu: Some(200.0),
            raw_scan_px: Some([0, 0, 5, 5]),
            bias_frames: Some(5),
            archive: Some(Archive { start_mjd: 58000.0, cadence_s: 60.0 }),
            keywords: [("OBJECT".to_string(), Keyword::Text("x".into()))].into_iter().collect(),
            first_exposure_no: Some(1),
        },
        sky: Some(Sky {
            brightness_e: 100.0,
            p: 0.01,
            chi_deg: 5.0,
            v: 0.001,
            gradient_e_per_arcmin: Some([1.0, 0.0]),
        }),
        stars: vec![Star {
            x: 1.0,
            y: 1.0,
            coords: Coords::Arcmin,
            flux_e: 1e5,
            p: 0.01,
            chi_deg: 3.0,
            v: 0.001,
            fwhm_arcsec: 0.8,
            psf: Psf::Moffat,
            moffat_beta: 3.0,
        }],
        extended: vec![Extended {
            profile: Profile::Sersic,
            x: 0.0,
            y: 0.0,
            coords: Coords::Arcmin,
            r_e_arcsec: 5.0,
            sersic_n: 2.0,
            i_e: 10.0,
            axis_ratio: 0.5,
            pa_deg: 10.0,
            p: 0.01,
            chi_deg: 0.0,
            image: Some(PathBuf::from("x.fits")),
        }],
        effects: Effects {
            instpol: Some(instpol),
            stressed_lens: Some(sim::stress::StressedLensSpec {
                retardance_edge_deg: 10.0,
                radius_arcmin: 3.4,
                centre_arcmin: [0.0, 0.0],
                tangential: false,
                axis_offset_deg: 0.0,
                before_instpol: false,
            }),
            constant_response: Some(field::ConstantResponse { q0: 0.001, u0: 0.0, efficiency: 0.99, offset_deg: 1.0 }),
            tilted_hwp: Some(sim::hwp_causes::TiltedHwpSpec {
                tilt_deg: 1.0,
                tilt_azimuth_deg: 0.0,
                magnification: 10.0,
                order: 0,
            }),
            wedged_hwp: Some(sim::hwp_causes::WedgedHwpSpec {
                retardance_error_deg: 1.0,
                gradient_deg_per_arcmin: [0.1, 0.0],
            }),
            wollaston: Some(WollastonSpec { t: 0.51, s: Some(0.49), delta_alpha_deg: 0.0 }),
            hwp_retardance_error_deg: Some(1.0),
            hwp_chi_offset_deg: Some(1.0),
            hwp_chi_offset_from_filter: false,
            qwp_zero_angle_deg: Some(1.0),
            dust: Some(harmonic()),
            pleochroism: Some(harmonic()),
            post_analyzer: Some(PostAnalyzerSpec { b: 0.004, phi_deg: 30.0, a: 1.0, c: 1.0 }),
            flat: Some(FlatSpec { pixel_rms_o: 0.01, pixel_rms_e: 0.01, large_scale_o: 0.01, large_scale_e: 0.01 }),
            photon_noise: true,
            read_noise: true,
            read_noise_e: Some(4.0),
            gain_e_per_adu: Some(1.0),
            saturation: true,
            cosmic_rays: Some(CosmicSpec { rate_per_frame: 5.0, energy_e: 1e4, size_px: 2 }),
            transparency_rms: Some(0.01),
        },
        frame_shifts_px: vec![[0.0, 0.0]; 4],
        telescope: Some(TelescopeSpec {
            metal: "aluminium".into(),
            factor: 1.0,
            overlayer_thickness_nm: 0.0,
            offset_deg: 0.0,
            rotator_deg: 0.0,
            site_latitude_deg: Some(-29.0),
            dec_deg: -30.0,
            ha_start_deg: Some(10.0),
            overhead_s: 30.0,
            hour_angles_deg: vec![10.0, 11.0, 12.0, 13.0],
        }),
        hwp_motion: Some(HwpMotion { sweep_deg: 22.5, substeps: 0 }),
        sky_pa_deg: Some(10.0),
    }
}

/// The keys the scene parser accepts, from scenes of each kind of instrumental field.
fn parser_keys() -> BTreeSet<String> {
    let kinds = [
        InstPolSpec::Radial { coeffs_percent: vec![0.0, 0.01], centre_arcmin: [0.0, 0.0], phi_offset_deg: 0.0 },
        InstPolSpec::Map { q_file: "q.fits".into(), u_file: "u.fits".into(), bin_px: 10 },
        InstPolSpec::Raytrace { file: "f.json".into(), centre_arcmin: [0.0, 0.0] },
    ];
    let mut keys = BTreeSet::new();
    for k in kinds {
        let scene = full_scene(k);
        let v = serde_json::to_value(&scene).unwrap();
        // The parser reads what serde wrote (the keys are its own): TOML of the same scene is a
        // scene again, refused (if at all) by a value's rule, never by an unknown key.
        let text = toml::to_string(&scene).unwrap();
        if let Err(e) = Scene::from_toml_str(&text, Path::new("full.toml")) {
            assert!(!e.to_string().contains("unknown field"), "{e}\n{text}");
        }
        key_paths(&v, "", &["output.keywords"], &mut keys);
    }
    keys
}

#[test]
fn the_scene_file_page_documents_every_key_the_parser_accepts() {
    let parser = parser_keys();
    // The walk sees the nested tables and the list of stars.
    for k in
        ["stars.flux_e", "effects.instpol.kind", "effects.cosmic_rays.size_px", "telescope.dec_deg", "output.keywords"]
    {
        assert!(parser.contains(k), "{k} not in {parser:?}");
    }
    let page = page_keys(&page());
    let undocumented: Vec<&String> = parser.difference(&page).collect();
    let unknown: Vec<&String> = page.difference(&parser).collect();
    assert!(
        undocumented.is_empty() && unknown.is_empty(),
        "docs/guide/scene-file.md: keys the parser accepts but the page does not list: {undocumented:?}; keys \
         the page lists that the parser does not accept: {unknown:?}"
    );
}

/// The page's table reader finds keys in the first cell only, and several in one cell.
#[test]
fn the_page_reader_takes_the_first_cell_of_key_tables() {
    let text = "| key | unit |\n|---|---|\n| `a.b`, `a.c` | `px` |\n\n| other | x |\n|---|---|\n| `z` | - |\n";
    let keys = page_keys(text);
    assert_eq!(keys.into_iter().collect::<Vec<_>>(), ["a.b", "a.c"]);
}
