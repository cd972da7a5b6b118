//! The JSON contract of every command: each command's `--json` output is
//! validated against its schema `schemas/<command>.schema.json` (JSON Schema draft 2020-12,
//! every key listed, `additionalProperties: false`), so a key that is added, dropped or renamed
//! fails here until the schema (and the JSON vocabulary of docs/guide/formats.md) says so.
//! `--json` errors are checked against `schemas/error.schema.json`.
//!
//! The validator is a strict, small one for the subset of draft 2020-12 the schemas use (type,
//! properties, required, additionalProperties, items, prefixItems, minItems, maxItems, enum,
//! const, $ref to #/$defs): a schema keyword it does not know is an error, never silently
//! ignored. It is tested on hand-made failing documents below (`validator_*`).
//!
//! Adding a command: its schema file plus one line in [`CASES`].

use crate::common;

use serde_json::{json, Value};
use std::path::{Path, PathBuf};
use std::sync::OnceLock;

// ---------------------------------------------------------------------------------------------
// The validator.

/// Every error of `doc` against `schema` (empty: valid), each naming the JSON path.
fn validate(schema: &Value, doc: &Value) -> Vec<String> {
    let mut errs = vec![];
    check(schema, schema, doc, "$", &mut errs);
    errs
}

const KNOWN: [&str; 17] = [
    "$schema",
    "$id",
    "$defs",
    "$ref",
    "title",
    "description",
    "type",
    "properties",
    "required",
    "additionalProperties",
    "items",
    "prefixItems",
    "minItems",
    "maxItems",
    "enum",
    "const",
    "examples",
];

fn type_ok(t: &str, v: &Value) -> Option<bool> {
    Some(match t {
        "object" => v.is_object(),
        "array" => v.is_array(),
        "string" => v.is_string(),
        "boolean" => v.is_boolean(),
        "null" => v.is_null(),
        "number" => v.is_number(),
        // An integer is a number with no fraction (2.0 is not written by serde for a count).
        "integer" => v.is_i64() || v.is_u64(),
        _ => return None,
    })
}

fn check(root: &Value, s: &Value, v: &Value, path: &str, errs: &mut Vec<String>) {
    let Some(s) = s.as_object() else {
        if s == &Value::Bool(false) {
            errs.push(format!("{path}: no value is allowed here"));
        } else if s != &Value::Bool(true) {
            errs.push(format!("{path}: schema is not an object or a boolean"));
        }
        return;
    };
    for k in s.keys() {
        if !KNOWN.contains(&k.as_str()) {
            errs.push(format!("{path}: schema keyword '{k}' is not supported by this validator"));
        }
    }
    if let Some(r) = s.get("$ref") {
        // `#/$defs/<name>` in this schema, or another schema file of the folder by its name
        // (`product.schema.json`: what a product is, shared by the outputs that carry one).
        let file = r.as_str().filter(|r| r.ends_with(".schema.json") && !r.contains('/'));
        if let Some(f) = file {
            let other = schema(f.trim_end_matches(".schema.json"));
            check(&other, &other, v, path, errs);
        } else {
            let target = r.as_str().and_then(|r| r.strip_prefix("#/$defs/")).and_then(|n| root["$defs"].get(n));
            match target {
                Some(t) => check(root, t, v, path, errs),
                None => errs.push(format!("{path}: unresolved $ref {r}")),
            }
        }
    }
    if let Some(t) = s.get("type") {
        let types: Vec<&str> = match t {
            Value::String(x) => vec![x.as_str()],
            Value::Array(a) => a.iter().filter_map(Value::as_str).collect(),
            _ => vec![],
        };
        let mut any = false;
        for ty in &types {
            match type_ok(ty, v) {
                Some(ok) => any |= ok,
                None => errs.push(format!("{path}: unknown type '{ty}' in schema")),
            }
        }
        if !any {
            errs.push(format!("{path}: {v} is not of type {t}"));
            return;
        }
    }
    if let Some(e) = s.get("enum").and_then(Value::as_array) {
        if !e.contains(v) {
            errs.push(format!("{path}: {v} is not one of {}", Value::Array(e.clone())));
        }
    }
    if let Some(c) = s.get("const") {
        if c != v {
            errs.push(format!("{path}: {v} is not {c}"));
        }
    }
    if let Some(o) = v.as_object() {
        let props = s.get("properties").and_then(Value::as_object);
        for r in s.get("required").and_then(Value::as_array).into_iter().flatten() {
            if let Some(r) = r.as_str() {
                if !o.contains_key(r) {
                    errs.push(format!("{path}: required key '{r}' is missing"));
                }
            }
        }
        for (k, x) in o {
            let sub = format!("{path}.{k}");
            match props.and_then(|p| p.get(k)) {
                Some(ps) => check(root, ps, x, &sub, errs),
                None => match s.get("additionalProperties") {
                    Some(Value::Bool(false)) => errs.push(format!("{path}: key '{k}' is not in the schema")),
                    Some(a) => check(root, a, x, &sub, errs),
                    None => {}
                },
            }
        }
    }
    if let Some(a) = v.as_array() {
        let prefix = s.get("prefixItems").and_then(Value::as_array);
        for (i, x) in a.iter().enumerate() {
            let sub = format!("{path}[{i}]");
            match prefix.and_then(|p| p.get(i)) {
                Some(ps) => check(root, ps, x, &sub, errs),
                None => {
                    if let Some(it) = s.get("items") {
                        check(root, it, x, &sub, errs);
                    }
                }
            }
        }
        if let Some(m) = s.get("minItems").and_then(Value::as_u64) {
            if (a.len() as u64) < m {
                errs.push(format!("{path}: {} items, fewer than {m}", a.len()));
            }
        }
        if let Some(m) = s.get("maxItems").and_then(Value::as_u64) {
            if (a.len() as u64) > m {
                errs.push(format!("{path}: {} items, more than {m}", a.len()));
            }
        }
    }
}

/// The repository's schema folder.
fn schema_dir() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../../schemas")
}

fn schema(name: &str) -> Value {
    let p = schema_dir().join(format!("{name}.schema.json"));
    let text = std::fs::read_to_string(&p).unwrap_or_else(|e| panic!("{}: {e}", p.display()));
    serde_json::from_str(&text).unwrap_or_else(|e| panic!("{}: {e}", p.display()))
}

/// Every object in `s` (the schema and its sub-schemas) must close its keys: a schema that
/// forgot `additionalProperties: false` would let an added key through unnoticed.
fn closed_objects(s: &Value, path: &str, errs: &mut Vec<String>) {
    if let Some(o) = s.as_object() {
        if o.get("type").is_some_and(|t| t == "object" || t.as_array().is_some_and(|a| a.contains(&json!("object")))) {
            if o.get("additionalProperties") != Some(&Value::Bool(false)) {
                errs.push(format!("{path}: an object schema without additionalProperties: false"));
            }
            let props: Vec<&String> =
                o.get("properties").and_then(Value::as_object).map_or(vec![], |p| p.keys().collect());
            for p in &props {
                let d = &o["properties"][p.as_str()]["description"];
                if d.as_str().is_none_or(|d| d.trim().is_empty()) && o["properties"][p.as_str()].get("$ref").is_none() {
                    errs.push(format!("{path}.{p}: no description (meaning and unit)"));
                }
            }
        }
        for (k, x) in o {
            closed_objects(x, &format!("{path}/{k}"), errs);
        }
    } else if let Some(a) = s.as_array() {
        for (i, x) in a.iter().enumerate() {
            closed_objects(x, &format!("{path}[{i}]"), errs);
        }
    }
}

/// Every schema keyword anywhere in `s` must be one the validator implements.
fn keywords(s: &Value, path: &str, errs: &mut Vec<String>) {
    let Some(o) = s.as_object() else { return };
    for (k, x) in o {
        if !KNOWN.contains(&k.as_str()) {
            errs.push(format!("{path}: keyword '{k}' is not supported by the test's validator"));
        }
        match k.as_str() {
            "properties" | "$defs" => {
                for (n, sub) in x.as_object().into_iter().flatten() {
                    keywords(sub, &format!("{path}.{n}"), errs);
                }
            }
            "items" | "additionalProperties" => keywords(x, &format!("{path}[]"), errs),
            "prefixItems" => {
                for (i, sub) in x.as_array().into_iter().flatten().enumerate() {
                    keywords(sub, &format!("{path}[{i}]"), errs);
                }
            }
            _ => {}
        }
    }
}

// ---------------------------------------------------------------------------------------------
// The validator on hand-made documents: each must fail for the reason given.

fn small_schema() -> Value {
    json!({
        "$schema": "https://json-schema.org/draft/2020-12/schema",
        "type": "object",
        "additionalProperties": false,
        "required": ["q", "sigma_q", "n_bins", "centre_px", "kind"],
        "properties": {
            "q": {"type": "number", "description": "Stokes q (fraction)"},
            "sigma_q": {"type": "number", "description": "1-sigma error of q (fraction)"},
            "n_bins": {"type": "integer", "description": "count"},
            "centre_px": {"type": "array", "prefixItems": [{"type": "number"}, {"type": "number"}], "items": false, "minItems": 2, "description": "x, y (px)"},
            "kind": {"enum": ["input", "io"], "description": "what failed"},
            "note": {"type": ["string", "null"], "description": "optional note"},
            "rows": {"type": "array", "items": {"$ref": "#/$defs/row"}, "description": "rows"}
        },
        "$defs": {"row": {"type": "object", "additionalProperties": false, "required": ["id"], "properties": {"id": {"type": "integer", "description": "row id"}}}}
    })
}

fn good_doc() -> Value {
    json!({"q": 0.01, "sigma_q": 1e-4, "n_bins": 3, "centre_px": [1.0, 2.5], "kind": "io", "note": null, "rows": [{"id": 1}]})
}

#[test]
fn validator_accepts_a_valid_document() {
    assert_eq!(validate(&small_schema(), &good_doc()), Vec::<String>::new());
}

#[test]
fn validator_refuses_a_renamed_key() {
    // The contract this file exists for: `sigma_q` renamed to `q_err` fails twice over (the
    // old name is missing, the new one is not in the schema).
    let mut d = good_doc();
    let o = d.as_object_mut().unwrap();
    let v = o.remove("sigma_q").unwrap();
    o.insert("q_err".into(), v);
    let e = validate(&small_schema(), &d);
    assert!(e.iter().any(|m| m.contains("required key 'sigma_q' is missing")), "{e:?}");
    assert!(e.iter().any(|m| m.contains("key 'q_err' is not in the schema")), "{e:?}");
}

#[test]
fn validator_refuses_added_dropped_and_mistyped_values() {
    let cases: Vec<(Value, &str)> = vec![
        (json!({"extra": 1}), "key 'extra' is not in the schema"),
        (json!({"n_bins": 2.5}), "is not of type \"integer\""),
        (json!({"q": "0.01"}), "is not of type \"number\""),
        (json!({"q": null}), "is not of type \"number\""),
        (json!({"centre_px": [1.0]}), "fewer than 2"),
        (json!({"centre_px": [1.0, 2.0, 3.0]}), "no value is allowed here"),
        (json!({"kind": "check"}), "is not one of"),
        (json!({"note": 3}), "is not of type"),
        (json!({"rows": [{"id": 1, "x": 2}]}), "$.rows[0]: key 'x' is not in the schema"),
        (json!({"rows": [{}]}), "$.rows[0]: required key 'id' is missing"),
    ];
    for (patch, want) in cases {
        let mut d = good_doc();
        for (k, v) in patch.as_object().unwrap() {
            d[k] = v.clone();
        }
        let e = validate(&small_schema(), &d);
        assert!(e.iter().any(|m| m.contains(want)), "{patch}: want '{want}', got {e:?}");
    }
    let mut d = good_doc();
    d.as_object_mut().unwrap().remove("n_bins");
    assert!(validate(&small_schema(), &d).iter().any(|m| m.contains("'n_bins' is missing")));
    // Not an object at all.
    assert!(!validate(&small_schema(), &json!([1, 2])).is_empty());
}

/// A `$ref` to another schema file is followed: a product (`product.schema.json`, shared by the
/// catalog, the plan and the trend) with an unknown key or a mistyped value fails through it.
#[test]
fn validator_follows_a_ref_to_another_schema_file() {
    let sc = json!({"type": "object", "additionalProperties": false, "properties": {"product": {"$ref": "product.schema.json"}}});
    assert!(validate(&sc, &json!({"product": {"instrument": "FORS1", "plate": "half_wave"}})).is_empty());
    let e = validate(&sc, &json!({"product": {"instrument": "FORS1", "colour": "red"}}));
    assert!(e.iter().any(|m| m.contains("colour")), "{e:?}");
    let e = validate(&sc, &json!({"product": {"instrument": 3}}));
    assert!(e.iter().any(|m| m.contains("$.product.instrument")), "{e:?}");
}

#[test]
fn validator_refuses_keywords_it_does_not_implement() {
    // A schema using `pattern` would otherwise pass documents the author meant to refuse.
    let s = json!({"type": "string", "pattern": "^a"});
    let e = validate(&s, &json!("b"));
    assert!(e.iter().any(|m| m.contains("'pattern' is not supported")), "{e:?}");
    let e = validate(&json!({"$ref": "#/$defs/missing"}), &json!(1));
    assert!(e.iter().any(|m| m.contains("unresolved $ref")), "{e:?}");
}

// ---------------------------------------------------------------------------------------------
// Inputs: small, made once for all the commands.

struct Fix {
    _dir: tempfile::TempDir,
    d: PathBuf,
    /// calcite frames of three stars, the instrument, and the first star's position.
    calcite: PathBuf,
    star_frames: Vec<String>,
    star: (f64, f64),
    /// A tiny FORS1 and its sky frames (for reduce and the map).
    tiny: PathBuf,
    sky_frames: Vec<String>,
    /// The paper's V field as a binned map, its calibration, a catalog CSV, the demo folder.
    vmap: PathBuf,
    cal: PathBuf,
    /// The V polynomial as a calibration of the calcite imager (for validate).
    calcite_cal: PathBuf,
    catalog: PathBuf,
    demo: PathBuf,
    /// FORS2-format raw bias and flat chips.
    bias: Vec<String>,
    flats: Vec<String>,
    fors2: PathBuf,
}

fn s(p: &Path) -> String {
    p.to_str().unwrap().to_string()
}

fn fix() -> &'static Fix {
    static F: OnceLock<Fix> = OnceLock::new();
    F.get_or_init(|| {
        let dir = tempfile::tempdir().unwrap();
        let d = dir.path().to_path_buf();
        let ok = |args: &[String]| {
            let (code, out, err) = common::run(args);
            assert_eq!(code, 0, "{args:?}: {err}");
            out
        };
        // Three stars on the maskless calcite imager (the catalog test's scene).
        let text = include_str!("../../../../instruments/calcite.toml")
            .replace("hwp_angle_keyword = \"\"", "hwp_angle_keyword = \"HWPANG\"");
        let calcite = d.join("calcite.toml");
        std::fs::write(&calcite, text).unwrap();
        let scene = include_str!("../../../../instruments/scenes/calcite_stars.toml")
            .replace("instrument = \"calcite\"", &format!("instrument = \"{}\"", calcite.display()));
        std::fs::write(d.join("stars.toml"), scene).unwrap();
        ok(&["simulate".into(), s(&d.join("stars.toml")), "--out".into(), s(&d.join("stars"))]);
        let star_frames: Vec<String> = common::fits_in(&d.join("stars")).iter().map(|p| s(p)).collect();
        // A uniformly polarized sky on a tiny FORS1.
        let tiny = common::tiny_fors1(&d, 8.0, 20);
        std::fs::write(
            d.join("sky.toml"),
            format!(
                "instrument = \"{}\"\nfilter = \"V\"\nhwp_angles_deg = [0, 22.5, 45, 67.5]\n[sky]\nbrightness_e = 3000\np = 0.0645\nchi_deg = 68.4\n",
                tiny.display()
            ),
        )
        .unwrap();
        ok(&["simulate".into(), s(&d.join("sky.toml")), "--out".into(), s(&d.join("sky"))]);
        let sky_frames: Vec<String> = common::fits_in(&d.join("sky")).iter().map(|p| s(p)).collect();
        // The V field, its calibration, a catalog of three positions in FORS1 pixels.
        let vmap = d.join("vmap.fits");
        common::write_v_sky_map(&vmap, |_| true);
        let cal = d.join("cal_V.fits");
        common::fors1_radial_calibration("V", common::V_COEFFS).save(&cal).unwrap();
        // calcite: 700 px of 0.2138" (instruments/calcite.toml), field origin at its centre.
        let h = 350.0 * 0.2138 / 60.0;
        let cc = fit::Calibration {
            instrument: "CALCITE".into(),
            pixel: Some(fit::files::calfile::PixelGrid { scale_arcsec: 0.2138, origin_px: [349.5, 349.5] }),
            region: fit::FieldRegion { x_min: -h, x_max: h, y_min: -h, y_max: h },
            ..common::fors1_radial_calibration("V", common::V_COEFFS)
        };
        let calcite_cal = d.join("cal_calcite.fits");
        cc.save(&calcite_cal).unwrap();
        let catalog = d.join("cat.csv");
        std::fs::write(&catalog, "x,y,q,u,sigma_q,sigma_u\n300,400,0.01,0.002,0.001,0.001\n1024,1024,0.0,0.0,0.001,0.001\n1800,90,-0.02,0.01,0.002,0.002\n").unwrap();
        let demo = d.join("demo");
        ok(&["demo".into(), "--no-frames".into(), "--out".into(), s(&demo)]);
        let fors2 = d.join("fors2_tiny.toml");
        std::fs::write(&fors2, common::raw::fors2_tiny_text()).unwrap();
        let raw = common::raw::write_raw_set(&d, &common::raw::fors2_tiny());
        let (star, _) = {
            let out = ok(&[
                "catalog".into(),
                star_frames[0].clone(),
                star_frames[1].clone(),
                star_frames[2].clone(),
                star_frames[3].clone(),
                "--instrument".into(),
                s(&calcite),
                "--fwhm".into(),
                "4.7".into(),
                "--aperture".into(),
                "9".into(),
                "--annulus".into(),
                "14,24".into(),
                "--json".into(),
            ]);
            let j: Value = serde_json::from_str(&out).unwrap();
            ((j["rows"][0]["x"].as_f64().unwrap(), j["rows"][0]["y"].as_f64().unwrap()), ())
        };
        Fix {
            _dir: dir,
            calcite,
            star_frames,
            star,
            tiny,
            sky_frames,
            vmap,
            cal,
            calcite_cal,
            catalog,
            demo,
            bias: raw.bias.iter().map(|p| s(p)).collect(),
            flats: raw.flats.iter().map(|p| s(p)).collect(),
            fors2,
            d,
        }
    })
}

fn v(x: &[&str]) -> Vec<String> {
    x.iter().map(|s| s.to_string()).collect()
}

fn star_args(f: &Fix, sub: &str) -> Vec<String> {
    let mut a = v(&[sub]);
    a.extend(f.star_frames.iter().cloned());
    a.extend(v(&["--instrument", &s(&f.calcite), "--aperture", "9", "--annulus", "14,24"]));
    a
}

/// A night of five bias exposures (two chip files each) of the tiny FORS2 of instruments/tiny_fors2.toml,
/// with ESO DPR keywords, simulated once; and the plan `instpol scan` makes of it.
fn night(f: &Fix) -> (String, String) {
    static NIGHT: OnceLock<(String, String)> = OnceLock::new();
    NIGHT
        .get_or_init(|| {
            let inst = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../instruments/tiny_fors2.toml");
            let scene = f.d.join("night_bias.toml");
            std::fs::write(
                &scene,
                format!(
                    "instrument = {:?}\nfilter = \"v_HIGH\"\nhwp_angles_deg = [0, 22.5, 45, 67.5, 90]\nexposure_s = 1\nseed = 5\n\
                     [output]\narchive = {{ start_mjd = 58546.9, cadence_s = 20 }}\n\
                     keywords = {{ \"HIERARCH ESO DPR CATG\" = \"CALIB\", \"HIERARCH ESO DPR TYPE\" = \"BIAS\", \"HIERARCH ESO DPR TECH\" = \"IMAGE\" }}\n\
                     [effects]\nread_noise = true\n",
                    inst.display().to_string()
                ),
            )
            .unwrap();
            let raw = f.d.join("night_raw");
            let (code, _, err) = common::run(&v(&["simulate", &s(&scene), "--out", &s(&raw)]));
            assert_eq!(code, 0, "{err}");
            let plan = f.d.join("night_plan.toml");
            let (code, _, err) = common::run(&v(&["scan", &s(&raw), "--instrument", &s(&inst), "--out", &s(&plan)]));
            assert_eq!(code, 0, "{err}");
            (s(&raw), s(&plan))
        })
        .clone()
}

/// Frames of the example quarter-wave instrument (instruments/calcite_qwp.toml) at -45 and 45
/// deg, one star of V/I = 1 %, simulated once: (the instrument, the frames).
fn qwp_frames(f: &Fix) -> (String, Vec<String>) {
    static QWP: OnceLock<(String, Vec<String>)> = OnceLock::new();
    QWP.get_or_init(|| {
        let inst = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../instruments/calcite_qwp.toml");
        let scene = f.d.join("qwp.toml");
        std::fs::write(
            &scene,
            format!(
                "instrument = {:?}\nfilter = \"V\"\nhwp_angles_deg = [-45, 45]\nseed = 3\n[output]\nbitpix = -32\n\
                 [[stars]]\nx = 200\ny = 300\ncoords = \"pixel\"\nflux_e = 1e6\nv = 0.01\nfwhm_arcsec = 0.9\n\
                 [effects]\nphoton_noise = true\n",
                s(&inst)
            ),
        )
        .unwrap();
        let dir = f.d.join("qwp_frames");
        let (code, _, err) = common::run(&v(&["simulate", &s(&scene), "--out", &s(&dir)]));
        assert_eq!(code, 0, "{err}");
        (s(&inst), common::fits_in(&dir).iter().map(|p| s(p)).collect())
    })
    .clone()
}

/// The tiny FORS1 with a quarter-wave plate and its frames of a sky with V/I = 1 % at -45 and
/// 45 deg, simulated once: (the instrument, the frames).
fn qwp_sky_frames(f: &Fix) -> (String, Vec<String>) {
    static QWP: OnceLock<(String, Vec<String>)> = OnceLock::new();
    QWP.get_or_init(|| {
        let text = std::fs::read_to_string(&f.tiny).unwrap();
        let inst = f.d.join("tiny_qwp.toml");
        std::fs::write(&inst, text.replace("[polarimetry]\n", "[polarimetry]\nplate = \"quarter_wave\"\n")).unwrap();
        let scene = f.d.join("qwp_sky.toml");
        std::fs::write(
            &scene,
            format!(
                "instrument = {:?}\nfilter = \"V\"\nhwp_angles_deg = [-45, 45]\n[sky]\nbrightness_e = 3000\nv = 0.01\n",
                s(&inst)
            ),
        )
        .unwrap();
        let dir = f.d.join("qwp_sky");
        let (code, _, err) = common::run(&v(&["simulate", &s(&scene), "--out", &s(&dir)]));
        assert_eq!(code, 0, "{err}");
        (s(&inst), common::fits_in(&dir).iter().map(|p| s(p)).collect())
    })
    .clone()
}

fn out(f: &Fix, name: &str) -> String {
    s(&f.d.join(format!("{}_{name}", std::process::id())))
}

// ---------------------------------------------------------------------------------------------
// The commands: (schema name, the arguments without --json). Adding a command is one line here
// plus its schema file.

type Args = fn(&Fix) -> Vec<String>;

/// A copy of the map `src` at `dst` that is another file's bytes (its file date changed): the
/// same bytes twice are one input, refused where two fields are meant.
fn distinct_copy(src: impl AsRef<Path>, dst: impl AsRef<Path>) {
    std::fs::copy(src.as_ref(), dst.as_ref()).unwrap();
    common::invocations::patch_card(dst.as_ref(), "DATE    =", "'2000-01-01T00:00:00'");
}

const CASES: &[(&str, Args)] = &[
    ("calibrate-mueller", |f| {
        // The V map and a copy under two declared skies: the shape of the output, not physics.
        let m = s(&f.d.join("vmap.fits"));
        let m2 = out(f, "vmap2.fits");
        distinct_copy(&m, &m2);
        v(&["calibrate-mueller", "--field", &format!("{m}:6.45:68.4"), "--field", &format!("{m2}:4:10")])
            .into_iter()
            .chain(v(&["--out", &out(f, "mf.json")]))
            .collect()
    }),
    ("explain", |f| {
        // A field with a free retardance from two declared skies, then the candidates.
        let m = s(&f.d.join("vmap.fits"));
        let m2 = out(f, "vmap_explain.fits");
        distinct_copy(&m, &m2);
        let mf = out(f, "mf_explain.json");
        let a = v(&["calibrate-mueller", "--field", &format!("{m}:6.45:68.4"), "--field", &format!("{m2}:4:10")]);
        let (code, _, err) = common::run(&a.into_iter().chain(v(&["--deg", "2", "--out", &mf])).collect::<Vec<_>>());
        assert_eq!(code, 0, "{err}");
        v(&["explain", &mf, "--instrument", "fors1", "--causes", "stressed_lens,polarizing_hwp", "--grid", "8"])
    }),
    ("plan", |_| {
        v(&["plan", "--target-percent", "0.02", "--sky-rate", "2", "--candidate", "6.45:68.4", "--candidate", "4:10"])
    }),
    ("simulate", |f| v(&["simulate", &s(&f.d.join("sky.toml")), "--out", &out(f, "sim")])),
    ("reduce", |f| {
        let mut a = v(&["reduce"]);
        a.extend(f.sky_frames.iter().cloned());
        a.extend(v(&["--instrument", &s(&f.tiny), "--bin", "10", "--out", &out(f, "map.fits")]));
        a
    }),
    ("reduce-circular", |f| {
        // A quarter-wave plate's frames: the V/I map's summary.
        let (inst, frames) = qwp_sky_frames(f);
        let mut a = v(&["reduce"]);
        a.extend(frames);
        a.extend(v(&["--instrument", &inst, "--bin", "10", "--out", &out(f, "vmap_circ.fits")]));
        a
    }),
    ("master-bias", |f| {
        let mut a = v(&["master-bias"]);
        a.extend(f.bias.iter().cloned());
        a.extend(v(&["--instrument", &s(&f.fors2), "--out", &out(f, "bias.fits")]));
        a
    }),
    ("master-flat", |f| {
        let mut a = v(&["master-flat"]);
        a.extend(f.flats.iter().cloned());
        a.extend(v(&["--instrument", &s(&f.fors2), "--out", &out(f, "flat.fits")]));
        a
    }),
    ("photometry", |f| {
        let mut a = star_args(f, "photometry");
        a.extend(v(&["--x", &f.star.0.to_string(), "--y", &f.star.1.to_string()]));
        a
    }),
    ("photometry-circular", |f| {
        let (inst, frames) = qwp_frames(f);
        let mut a = v(&["photometry"]);
        a.extend(frames);
        a.extend(v(&["--instrument", &inst, "--hwp-angles", "-45,45", "--x", "200", "--y", "300", "--aperture", "9"]));
        a.extend(v(&["--annulus", "14,24"]));
        a
    }),
    ("catalog", |f| {
        let mut a = star_args(f, "catalog");
        a.extend(v(&["--fwhm", "4.7", "--out", &out(f, "cat.csv")]));
        a
    }),
    ("zero-angle", |f| {
        let mut a = star_args(f, "zero-angle");
        a.extend(v(&[
            "--x",
            &f.star.0.to_string(),
            "--y",
            &f.star.1.to_string(),
            "--chi-deg",
            "136",
            "--sigma-chi-deg",
            "0.05",
        ]));
        a
    }),
    ("efficiency", |f| {
        // Three standards' rows in one table of other software (no setup recorded): one
        // unpolarized, two polarized.
        let cat = f.d.join("standards_rows.csv");
        let rows = "x,y,q,u,sigma_q,sigma_u\n100,100,0.004,-0.003,3e-4,3e-4\n300,300,0.018,0.030,3e-4,3e-4\n200,50,0.035,-0.012,3e-4,3e-4\n";
        std::fs::write(&cat, rows).unwrap();
        let std = |xy: &str, what: &str| format!("{}:{xy}:{what}", s(&cat));
        v(&[
            "efficiency",
            "--standard",
            &std("100,100", "unpolarized"),
            "--standard",
            &std("300,300", "0.04+-0.0001/30+-0.1"),
            "--standard",
            &std("200,50", "0.04+-0.0001/170+-0.1"),
            "--instrument",
            "calcite",
            "--filter",
            "V",
            "--output",
            &out(f, "response.fits"),
        ])
    }),
    ("calibrate-stars", |f| {
        // Catalogs of 60 stars over two pointings drawn through the V pattern: the shape of
        // the output, with stars rejected (6 polarized) so the rejected list has rows.
        let dir = f.d.join(format!("{}_stars", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let (files, _) = common::star_catalogs(&dir, 3, 60, 6, (0.0, 0.0), 5e-4, &[[0.0, 0.0], [0.5, -0.3]]);
        let mut a = vec!["calibrate-stars".to_string()];
        a.extend(files.iter().map(|p| s(p)));
        a.extend(v(&["--filter", "V", "--out", &out(f, "cal_stars.fits")]));
        a
    }),
    ("calibrate", |f| {
        v(&["calibrate", "--map", &s(&f.vmap), "--sky-p", "1.74", "--sky-chi", "-53.8", "--out", &out(f, "cal.fits")])
    }),
    ("fit", |f| v(&["fit", &s(&f.demo.join("cal_V.fits")), "--free-centre"])),
    ("plot", |f| v(&["plot", &s(&f.demo.join("cal_V.fits")), "--out", &out(f, "plots")])),
    ("wavelength-law", |f| {
        let c = |b: &str| s(&f.demo.join(format!("cal_{b}.fits")));
        v(&["wavelength-law", &c("B"), &c("V"), &c("I")])
    }),
    ("correct", |f| {
        v(&["correct", "--cal", &s(&f.cal), "--in", &s(&f.catalog), "--out", &out(f, "corr.csv"), "--coords", "pixel"])
    }),
    ("stokes", |f| {
        let p = f.d.join("fluxes.csv");
        std::fs::write(&p, "hwp_deg,f_o,f_e\n0,1000,1100\n22.5,1050,1010\n45,1100,1000\n67.5,1010,1050\n").unwrap();
        v(&["stokes", "--input", &s(&p)])
    }),
    ("bias", |_| v(&["bias", "--p", "0.01", "--sigma", "0.003"])),
    ("mc", |_| v(&["mc", "--n-hwp", "4", "--snr", "100", "--p0", "0.01", "--trials", "2000", "--seed", "3"])),
    ("mc-sweep", |_| v(&["mc", "--sweep", "--trials", "300", "--noise", "gauss-qu"])),
    ("mc-accuracy", |_| v(&["mc", "--accuracy-report", "--trials", "1000", "--noise", "gauss-qu"])),
    ("fresnel", |_| {
        v(&["fresnel", "--n-real", "1.52", "--aoi-deg", "30", "--wavelength-nm", "550", "--coating", "1.38:81.52"])
    }),
    ("raytrace", |_| {
        v(&["raytrace", "--instrument", "fors1", "--filter", "V", "--field-points", "5", "--pupil-rays", "16"])
    }),
    ("demo", |f| v(&["demo", "--no-frames", "--out", &out(f, "demo")])),
    ("scan", |f| {
        let (raw, _) = night(f);
        let inst = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../instruments/tiny_fors2.toml");
        v(&["scan", &raw, "--instrument", &s(&inst), "--out", &out(f, "plan.json")])
    }),
    ("run", |f| v(&["run", &night(f).1, "--dry-run"])),
    ("trend", |f| {
        // A plan of bias frames measures no standard: the shape of an empty trend.
        v(&["trend", &night(f).1, "--out", &out(f, "trend.ecsv")])
    }),
    // A plan not yet run: the page of its units, none done.
    ("report", |f| v(&["report", &night(f).1, "--out", &out(f, "report")])),
    ("simulate-night", |f| v(&["simulate", "--night", &out(f, "simulated_night")])),
];

/// Run one case and validate its stdout against its schema.
fn run_case(name: &str) {
    let (_, args) = CASES.iter().find(|(n, _)| *n == name).unwrap_or_else(|| panic!("no case {name}"));
    let f = fix();
    let mut a = args(f);
    a.push("--json".into());
    let (code, out, err) = common::run(&a);
    assert_eq!(code, 0, "instpol {a:?}: {err}");
    let doc: Value = serde_json::from_str(&out).unwrap_or_else(|e| panic!("{name}: not JSON ({e}): {out}"));
    if !schema_dir().join(format!("{name}.schema.json")).is_file() {
        panic!("schemas/{name}.schema.json is missing; the output to describe:\n{out}");
    }
    let e = validate(&schema(name), &doc);
    assert!(e.is_empty(), "{name}: the output does not match schemas/{name}.schema.json:\n{}", e.join("\n"));
}

macro_rules! cases {
    ($($t:ident => $n:expr),* $(,)?) => { $( #[test] fn $t() { run_case($n); } )* };
}

cases! {
    simulate_json => "simulate", reduce_json => "reduce", reduce_circular_json => "reduce-circular",
    master_bias_json => "master-bias",
    master_flat_json => "master-flat", photometry_json => "photometry", catalog_json => "catalog",
    photometry_circular_json => "photometry-circular",
    zero_angle_json => "zero-angle", efficiency_json => "efficiency", calibrate_json => "calibrate", calibrate_stars_json => "calibrate-stars", fit_json => "fit", plot_json => "plot",
    wavelength_law_json => "wavelength-law", correct_json => "correct", stokes_json => "stokes",
    bias_json => "bias", mc_json => "mc", mc_sweep_json => "mc-sweep", mc_accuracy_json => "mc-accuracy",
    fresnel_json => "fresnel", raytrace_json => "raytrace", demo_json => "demo", plan_json => "plan",
    calibrate_mueller_json => "calibrate-mueller", explain_json => "explain", scan_json => "scan",
    run_json => "run", trend_json => "trend", report_json => "report", simulate_night_json => "simulate-night",
}

/// The keys only some options print (residual map, RNG baseline) are in the schemas too:
/// validated on runs that print them. (`correlation`, from --correlated-errors on a regular
/// map, is described by hand from `fit::models::correlation::CorrelationInflation`.)
#[test]
fn optional_keys_json() {
    let f = fix();
    let runs = [
        (
            "calibrate",
            v(&[
                "calibrate",
                "--map",
                &s(&f.vmap),
                "--sky-p",
                "1.74",
                "--sky-chi",
                "-53.8",
                "--residual-map",
                "--out",
                &out(f, "cal_opt.fits"),
                "--plots",
                &out(f, "cal_opt_plots"),
                "--json",
            ]),
            vec!["rms_residual_loo", "approx_vs_exact", "centre_px", "plot_outputs"],
        ),
        ("mc", v(&["mc", "--trials", "2000", "--rng-baseline", "--json"]), vec!["rng_seconds", "engine_over_rng"]),
        // A Mueller-field calibration file, then a correction with it (mueller_* keys).
        (
            "calibrate-mueller",
            {
                let m2 = out(f, "vmap_m2.fits");
                distinct_copy(&f.vmap, &m2);
                v(&[
                    "calibrate-mueller",
                    "--field",
                    &format!("{}:6.45:68.4", s(&f.vmap)),
                    "--field",
                    &format!("{m2}:4:10"),
                ])
                .into_iter()
                .chain(v(&["--out", &out(f, "mcal.fits"), "--json"]))
                .collect()
            },
            vec!["model", "free"],
        ),
        (
            "correct",
            v(&[
                "correct",
                "--cal",
                &out(f, "mcal.fits"),
                "--in",
                &s(&f.catalog),
                "--out",
                &out(f, "mcorr.csv"),
                "--coords",
                "pixel",
                "--json",
            ]),
            vec!["mueller_model", "mueller_free"],
        ),
        // A catalog through a quarter-wave plate: V/I in its rows.
        (
            "catalog",
            {
                let (inst, frames) = qwp_frames(f);
                let mut a = v(&["catalog"]);
                a.extend(frames);
                a.extend(v(&["--instrument", &inst, "--hwp-angles", "-45,45", "--fwhm", "4.2", "--aperture", "9"]));
                a.extend(v(&["--annulus", "14,24", "--json"]));
                a
            },
            vec!["qwp_zero_angle_deg"],
        ),
    ];
    for (name, a, keys) in runs {
        let (code, o, err) = common::run(&a);
        assert_eq!(code, 0, "{a:?}: {err}");
        let doc: Value = serde_json::from_str(&o).unwrap();
        // The plots listed are the files drawn.
        for p in doc.get("plot_outputs").and_then(Value::as_array).into_iter().flatten() {
            assert!(Path::new(p.as_str().unwrap()).is_file(), "{name}: {p} listed but not written");
        }
        for k in keys {
            assert!(doc.get(k).is_some(), "{name}: {k} not printed: {doc}");
        }
        if doc.get("qwp_zero_angle_deg").is_some() {
            assert!(doc["rows"][0]["v"].is_number() && doc["rows"][0]["sigma_v"].is_number(), "{doc}");
        }
        let e = validate(&schema(name), &doc);
        assert!(e.is_empty(), "{name}: {}", e.join("\n"));
    }
}

#[test]
fn every_case_has_a_test_and_every_schema_a_case() {
    // A case without a #[test] above, or a schema file no case uses, is a contract nobody checks.
    let src = include_str!("json_schema.rs");
    for (n, _) in CASES {
        assert!(src.contains(&format!("=> \"{n}\"")), "case {n} has no test in cases!{{}}");
    }
    for (stem, _) in schema_files() {
        let stem = stem.as_str();
        assert!(
            stem == "error"
                || stem == "product"
                || stem == "validate"
                || stem == "validate-telescope"
                || stem == "fit-standards"
                || stem == "import-map"
                || CASES.iter().any(|(n, _)| *n == stem),
            "schemas/{stem}.schema.json is checked by no case"
        );
    }
}

/// Every schema file: its name (without `.schema.json`) and path.
fn schema_files() -> Vec<(String, PathBuf)> {
    std::fs::read_dir(schema_dir())
        .unwrap()
        .filter_map(|e| {
            let p = e.unwrap().path();
            let name = p.file_name()?.to_str()?.strip_suffix(".schema.json")?.to_string();
            Some((name, p))
        })
        .collect()
}

#[test]
fn every_schema_is_draft_2020_12_closed_and_described() {
    for (name, _) in schema_files() {
        let name = name.as_str();
        let sc = schema(name);
        assert_eq!(sc["$schema"], "https://json-schema.org/draft/2020-12/schema", "{name}");
        let mut errs = vec![];
        closed_objects(&sc, name, &mut errs);
        keywords(&sc, name, &mut errs);
        assert!(errs.is_empty(), "{}", errs.join("\n"));
    }
}

/// Outputs that say no product, each with why: they measure no data of an instrument (or are
/// not a command's output). Every other schema describes a `product` (at its top, or in each
/// entry for a command that writes several), so every `--json` on data says what it is of.
const NO_PRODUCT: &[(&str, &str)] = &[
    ("bias", "the bias of P from numbers given"),
    ("mc", "a simulation of numbers given"),
    ("mc-sweep", "a simulation of numbers given"),
    ("mc-accuracy", "a simulation of numbers given"),
    ("fresnel", "a mirror's Mueller matrix from numbers given"),
    ("raytrace", "the optics of an instrument file, no data"),
    ("stokes", "fluxes given as numbers, of no instrument"),
    ("plan", "the exposures a Mueller-field calibration would need, no data"),
    ("simulate", "frames made, which carry the instrument's own header keywords"),
    ("simulate-night", "frames made, which carry the instrument's own header keywords"),
    ("run", "the units of a plan, each of whose products says what it is"),
    ("report", "a page of a plan's products, each of which says what it is"),
    ("plot", "figures of a calibration file, which says what it is"),
    ("error", "an error, not a product"),
    ("product", "the product itself"),
];

#[test]
fn every_schema_of_data_describes_its_product() {
    for (name, p) in schema_files() {
        let name = name.as_str();
        let text = std::fs::read_to_string(&p).unwrap();
        let described = text.contains("\"$ref\": \"product.schema.json\"");
        let excused = NO_PRODUCT.iter().any(|(n, _)| *n == name);
        assert!(described || excused, "{name}: its schema has no product; add one, or say why in NO_PRODUCT");
        assert!(!(described && excused), "{name}: describes a product but is listed in NO_PRODUCT");
    }
}

/// A renamed key in a real command's output fails its schema (the schemas can fail).
#[test]
fn a_renamed_key_in_real_output_fails() {
    let (code, out, err) = common::run(&["bias", "--p", "0.01", "--sigma", "0.003", "--json"]);
    assert_eq!(code, 0, "{err}");
    let mut doc: Value = serde_json::from_str(&out).unwrap();
    assert!(validate(&schema("bias"), &doc).is_empty());
    let o = doc.as_object_mut().unwrap();
    let x = o.remove("sigma_p").unwrap();
    o.insert("p_err".into(), x);
    let e = validate(&schema("bias"), &doc);
    assert!(e.iter().any(|m| m.contains("'sigma_p' is missing")) && e.iter().any(|m| m.contains("'p_err'")), "{e:?}");
}

// ---------------------------------------------------------------------------------------------
// Errors under --json: one JSON object on stderr, the exit code unchanged.

fn error_of(args: &[String], want_code: i32, want_kind: &str) -> Value {
    let (code, _, err) = common::run(args);
    assert_eq!(code, want_code, "{args:?}: {err}");
    let line = err.lines().last().unwrap_or_else(|| panic!("{args:?}: empty stderr"));
    let doc: Value = serde_json::from_str(line).unwrap_or_else(|e| panic!("{args:?}: stderr is not JSON ({e}): {err}"));
    let e = validate(&schema("error"), &doc);
    assert!(e.is_empty(), "{}", e.join("\n"));
    assert_eq!(doc["error"]["kind"], want_kind, "{doc}");
    assert_eq!(doc["error"]["exit_code"], want_code, "{doc}");
    doc
}

#[test]
fn json_errors_bad_input_exit_2() {
    let d = error_of(&v(&["bias", "--p", "-1", "--sigma", "0.1", "--json"]), 2, "input");
    assert!(d["error"]["message"].as_str().unwrap().contains("--p"), "{d}");
    // A usage error clap refuses is JSON too under --json.
    let d = error_of(&v(&["bias", "--p", "0.1", "--json"]), 2, "input");
    assert!(d["error"]["message"].as_str().unwrap().contains("--sigma"), "{d}");
    // Without --json: the plain message, as before.
    let (code, _, err) = common::run(&["bias", "--p", "-1", "--sigma", "0.1"]);
    assert_eq!(code, 2);
    assert!(err.starts_with("error: --p"), "{err}");
}

#[test]
fn json_errors_io_exit_2() {
    // An output in a folder that does not exist: the file system refuses, named.
    let f = fix();
    let target = f.d.join("no-such-folder").join("cal.fits");
    let d = error_of(
        &v(&[
            "calibrate",
            "--map",
            &s(&f.vmap),
            "--sky-p",
            "1.74",
            "--sky-chi",
            "-53.8",
            "--out",
            &s(&target),
            "--json",
        ]),
        2,
        "io",
    );
    assert!(d["error"]["message"].as_str().unwrap().contains("no-such-folder"), "{d}");
}

#[test]
fn json_errors_failed_check_exit_1() {
    // A polarized star (p ~ 5.7%) claimed unpolarized against the V calibration: the check runs
    // and fails; the report is on stdout and the failure is the JSON error on stderr.
    let f = fix();
    let mut a = star_args(f, "validate");
    a.extend(v(&["--cal", &s(&f.calcite_cal), "--x", &f.star.0.to_string(), "--y", &f.star.1.to_string(), "--json"]));
    let d = error_of(&a, 1, "check");
    assert!(d["error"]["message"].as_str().unwrap().contains("FAIL"), "{d}");
    let (_, out, _) = common::run(&a);
    let doc: Value = serde_json::from_str(&out).unwrap();
    let e = validate(&schema("validate"), &doc);
    assert!(e.is_empty(), "validate: {}", e.join("\n"));
}

/// The third-party FORS2 maps and EFOSC2 standards (real data, /work/shared/data): import-map
/// and fit-standards validated against their schemas; skipped loudly when the data are absent.
#[test]
fn real_data_commands() {
    let Some(d) = crate::common::shared_data::shared_data(
        "",
        &["fors2-instpol/v_HIGH_inlaQ_bin10.fits", "efosc2-standards/pv_standards.txt"],
        "the real-data schema checks",
    ) else {
        return;
    };
    let (q, st) = (d.join("fors2-instpol/v_HIGH_inlaQ_bin10.fits"), d.join("efosc2-standards/pv_standards.txt"));
    let f = fix();
    let cases = [
        ("import-map", {
            let mut a = common::import_fors2_v_args(q.parent().unwrap(), Path::new(&out(f, "imp.fits")));
            a.extend(["--lambda-nm", "557", "--json"].map(String::from));
            a
        }),
        ("fit-standards", v(&["fit-standards", &s(&st), "--json"])),
    ];
    for (name, a) in cases {
        let (code, o, err) = common::run(&a);
        assert_eq!(code, 0, "{a:?}: {err}");
        let doc: Value = serde_json::from_str(&o).unwrap();
        let e = validate(&schema(name), &doc);
        assert!(e.is_empty(), "{name}: {}", e.join("\n"));
    }
}
