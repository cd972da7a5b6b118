//! Fixtures shared by the skyfield integration tests.

use instrument::Instrument;
use skyfield::fits::KeyValue;
use std::path::Path;

/// FORS1 shrunk to a 64 x 64 detector with three 10-px strip pairs, and the given bias (ADU).
pub fn tiny_with_bias(bias_adu: f64) -> Instrument {
    let text = include_str!("../../../../instruments/fors1.toml")
        .replace("nx = 2048", "nx = 64")
        .replace("ny = 2048", "ny = 64")
        .replace("throw_arcsec = 22.0", "throw_arcsec = 2.0")
        .replace("strip_count = 9", "strip_count = 3")
        .replace("first_strip_y_px = 34", "first_strip_y_px = 2")
        .replace("bias_adu = 0.0", &format!("bias_adu = {bias_adu:?}"));
    Instrument::from_toml_str(&text, Path::new("tiny.toml")).unwrap()
}

/// Header keywords of a frame: the instrument's HWP-angle and filter keywords, and `extra`.
pub fn keys(inst: &Instrument, hwp: f64, filter: &str, extra: &[(&str, f64)]) -> Vec<(String, KeyValue, String)> {
    let mut k = vec![
        (inst.polarimetry.hwp_angle_keyword.clone(), KeyValue::F64(hwp), String::new()),
        (inst.polarimetry.filter_keyword.clone(), KeyValue::Str(filter.into()), String::new()),
    ];
    k.extend(extra.iter().map(|(n, v)| (n.to_string(), KeyValue::F64(*v), String::new())));
    k
}
