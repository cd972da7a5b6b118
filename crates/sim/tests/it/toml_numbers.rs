//! Every number of every file a user writes in TOML is checked where it is read: each float of
//! the built-in instrument files, of the built-in scenes and of the standards list is replaced
//! in turn by `nan`, `inf` and `-inf`, and the loader (instrument, scene, standards) refuses
//! the file naming that key. Two filters (or standards) of one name are refused too.

use std::path::Path;

/// The key path of every float in `t` (`a.b`, `x[2].y`), in the form the loaders report.
fn float_keys(v: &toml::Value, key: &str, out: &mut Vec<String>) {
    match v {
        toml::Value::Float(_) => out.push(key.to_string()),
        toml::Value::Table(t) => {
            for (k, x) in t {
                float_keys(x, &if key.is_empty() { k.clone() } else { format!("{key}.{k}") }, out);
            }
        }
        toml::Value::Array(a) => {
            for (i, x) in a.iter().enumerate() {
                float_keys(x, &format!("{key}[{i}]"), out);
            }
        }
        _ => {}
    }
}

/// `v` with the float at `key` replaced by `x`.
fn replaced(v: &toml::Value, key: &str, here: &str, x: f64) -> toml::Value {
    match v {
        toml::Value::Float(_) if here == key => toml::Value::Float(x),
        toml::Value::Table(t) => toml::Value::Table(
            t.iter()
                .map(|(k, y)| {
                    let h = if here.is_empty() { k.clone() } else { format!("{here}.{k}") };
                    (k.clone(), replaced(y, key, &h, x))
                })
                .collect(),
        ),
        toml::Value::Array(a) => toml::Value::Array(
            a.iter().enumerate().map(|(i, y)| replaced(y, key, &format!("{here}[{i}]"), x)).collect(),
        ),
        other => other.clone(),
    }
}

/// Each float of `text` made non-finite in turn must be refused by `load`, naming the key.
fn every_float_refused(what: &str, text: &str, load: &dyn Fn(&str) -> Result<(), String>) -> usize {
    let v: toml::Value = toml::Value::Table(text.parse().unwrap());
    load(text).unwrap_or_else(|e| panic!("{what} as shipped is refused: {e}"));
    let mut keys = vec![];
    float_keys(&v, "", &mut keys);
    for key in &keys {
        for x in [f64::NAN, f64::INFINITY, f64::NEG_INFINITY] {
            let t = toml::to_string(&replaced(&v, key, "", x)).unwrap();
            let e = load(&t).expect_err(&format!("{what} with {key} = {x} is accepted"));
            assert!(e.contains(key.as_str()) && e.contains("finite"), "{what}, {key} = {x}: {e}");
        }
    }
    keys.len()
}

#[test]
fn every_number_of_the_shipped_files_is_checked() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("../..");
    let mut n = 0;
    for name in ["fors1", "fors2", "efosc2", "calcite"] {
        let text = instrument::builtin_source(name).unwrap();
        n += every_float_refused(name, text, &|t| {
            instrument::Instrument::from_toml_str(t, Path::new("inst.toml")).map(|_| ()).map_err(|e| e.to_string())
        });
    }
    let scenes = root.join("instruments/scenes");
    for entry in std::fs::read_dir(&scenes).unwrap().flatten() {
        let path = entry.path();
        let text = std::fs::read_to_string(&path).unwrap();
        n += every_float_refused(&path.display().to_string(), &text, &|t| {
            sim::Scene::from_toml_str(t, &path).map(|_| ()).map_err(|e| e.to_string())
        });
    }
    let standards = std::fs::read_to_string(root.join("instruments/standards.toml")).unwrap();
    n += every_float_refused("standards.toml", &standards, &|t| {
        fit::standards::Standards::from_toml_str(t, Path::new("standards.toml")).map(|_| ()).map_err(|e| e.to_string())
    });
    assert!(n > 100, "{n} numbers tried");
}

#[test]
fn two_filters_or_standards_of_one_name_are_refused() {
    let fors1 = instrument::builtin_source("fors1").unwrap();
    let twice = fors1.replacen("name = \"R\"", "name = \"V\"", 1);
    assert_ne!(twice, fors1);
    let e = instrument::Instrument::from_toml_str(&twice, Path::new("inst.toml")).unwrap_err().to_string();
    assert!(e.contains("also filter V's"), "{e}");
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("../..");
    let standards = std::fs::read_to_string(root.join("instruments/standards.toml")).unwrap();
    let first = standards.find("name = \"").unwrap();
    let name: String = standards[first + 8..].chars().take_while(|&c| c != '"').collect();
    let copy = format!(
        "{standards}\n[[star]]\nname = \"{name}\"\nkind = \"unpolarized\"\n\n[[star.band]]\nband = \"V\"\np_percent = 0.0\nsigma_p_percent = 0.01\nsource = \"a copy\"\n"
    );
    let e = fit::standards::Standards::from_toml_str(&copy, Path::new("standards.toml")).unwrap_err().to_string();
    assert!(e.contains("is also star"), "{e}");
}
