//! Between numpy and the libraries: contiguous views of arrays in, arrays out, and the
//! inputs every function checks the same way (the frames' instrument, the read options, no
//! output over an input, no input twice).

use crate::errors::*;
use numpy::prelude::*;
use numpy::{PyArray1, PyArray2, PyReadonlyArray1, PyReadonlyArray2};
use pyo3::prelude::*;
use pyo3::types::PyDict;
use std::path::PathBuf;

/// The instrument frames are read as: the one named, else the built-in one the first frame's
/// `INSTRUME` names (with a Python warning that says so), else InputError asking for
/// `instrument=` (`skyfield::io::instrument_from_headers`, as the CLI's `--instrument`).
pub(crate) fn frames_instrument(given: Option<&str>, frames: &[PathBuf]) -> PyResult<String> {
    if let Some(g) = given {
        return Ok(g.to_string());
    }
    let first = frames.first().ok_or_else(|| input_err("no frames: give at least one file"))?;
    let (name, how) =
        skyfield::io::instrument_from_headers(first).map_err(|e| input_err(format!("{e} (instrument=)")))?;
    Python::attach(|py| {
        let w = py.import("warnings")?;
        w.call_method1("warn", (format!("{how}; give instrument= to read them as another"),)).map(|_| ())
    })?;
    Ok(name)
}

/// A contiguous view of a float64 array (the Python half makes it contiguous).
pub(crate) fn slice<'a>(a: &'a PyReadonlyArray1<'_, f64>, what: &str) -> PyResult<&'a [f64]> {
    a.as_slice().map_err(|_| input_err(format!("{what}: expected a contiguous float64 array")))
}

pub(crate) fn slice2<'a>(a: &'a PyReadonlyArray2<'_, f64>, what: &str) -> PyResult<&'a [f64]> {
    a.as_slice().map_err(|_| input_err(format!("{what}: expected a contiguous float64 array")))
}

pub(crate) fn arr1<'py>(py: Python<'py>, v: Vec<f64>) -> Bound<'py, PyArray1<f64>> {
    PyArray1::from_vec(py, v)
}

pub(crate) fn arr2<'py>(py: Python<'py>, v: Vec<f64>, rows: usize, cols: usize) -> PyResult<Bound<'py, PyArray2<f64>>> {
    PyArray1::from_vec(py, v).reshape([rows, cols])
}

pub(crate) fn bools<'py>(py: Python<'py>, v: Vec<bool>) -> Bound<'py, PyArray1<bool>> {
    PyArray1::from_vec(py, v)
}

pub(crate) fn opt(x: Option<f64>) -> f64 {
    x.unwrap_or(f64::NAN)
}

pub(crate) fn read_options(
    bias: Option<PathBuf>,
    flat: Option<PathBuf>,
    hwp_angles: Option<Vec<f64>>,
    assembled: bool,
    correct_again: bool,
) -> PyResult<skyfield::calib::ReadOptions> {
    if let Some(v) = &hwp_angles {
        // The library's rule (skyfield::calib::ReadOptions::check_hwp_angles), worded here.
        if skyfield::calib::ReadOptions::check_hwp_angles(v).is_err() {
            return Err(input_err(
                "hwp_angles: expected finite angles in degrees, one per frame, e.g. [0, 22.5, 45, 67.5]",
            ));
        }
    }
    Ok(skyfield::calib::ReadOptions { bias, flat, hwp_angles_deg: hwp_angles, assembled, correct_again })
}

/// No function writes over one of its own inputs, whatever name `output` gives it (the one
/// rule of both faces, `skyfield::durable::refuse_overwrite`).
pub(crate) fn refuse_overwrite<'a>(
    output: Option<&std::path::Path>,
    inputs: impl IntoIterator<Item = &'a PathBuf>,
) -> PyResult<()> {
    let Some(out) = output else { return Ok(()) };
    skyfield::durable::refuse_overwrite(out, inputs.into_iter().map(PathBuf::as_path)).map_err(input_err)
}

/// Input files that are the same data under two names (the same path, a link, or with
/// `By::Content` a copy: `skyfield::same::distinct_files` decides) refused naming both: they
/// would be counted twice.
pub(crate) fn refuse_same_data<'a>(
    inputs: impl IntoIterator<Item = &'a PathBuf>,
    by: skyfield::same::By,
) -> PyResult<()> {
    let paths: Vec<&PathBuf> = inputs.into_iter().collect();
    match skyfield::same::distinct_files(&paths, by).duplicates.first() {
        Some(d) => {
            Err(input_err(format!("{d}: each input may be given once (the same data twice would be counted twice)")))
        }
        None => Ok(()),
    }
}

/// An unpaired source's reason as the catalog JSON writes it (`off_detector`, `no_partner`,
/// `lone_e`).
pub(crate) fn pythonize_why(w: skyfield::detect::Unpaired) -> String {
    serde_json::to_value(w).ok().and_then(|v| v.as_str().map(String::from)).unwrap_or_default()
}

/// What a catalog is (`skyfield::provenance::Product`), as `catalog()["product"]`.
pub(crate) fn product_dict<'py>(py: Python<'py>, p: &skyfield::provenance::Product) -> PyResult<Bound<'py, PyDict>> {
    let pd = PyDict::new(py);
    pd.set_item("instrument", p.instrument.as_deref())?;
    pd.set_item("instrument_hash", p.instrument_hash.as_deref())?;
    pd.set_item("filter", p.filter.as_deref())?;
    pd.set_item("wavelength_um", p.wavelength_um)?;
    pd.set_item("plate", p.plate.as_deref())?;
    pd.set_item("hwp_chi_offset_deg", p.zero_angle_deg)?;
    pd.set_item("detector_px", p.detector_px)?;
    pd.set_item("pixel_scale_arcsec", p.pixel_scale_arcsec)?;
    // On a rotator the rows' q, u are in the celestial frame: Calibration.correct takes it.
    pd.set_item("sky_pa_deg", p.position_angle_deg)?;
    Ok(pd)
}

/// What `product_dict` gave back (`catalog()["product"]`): the instrument file, detector and
/// pixel scale it records, for the one compatibility check; `None` for `None`. A value of the
/// wrong type is an InputError naming its key.
pub(crate) fn product_of_dict(d: Option<&Bound<'_, PyDict>>) -> PyResult<Option<skyfield::provenance::Product>> {
    let Some(d) = d else { return Ok(None) };
    fn get<'py, T: for<'a> FromPyObject<'a, 'py>>(
        d: &Bound<'py, PyDict>,
        key: &str,
        what: &str,
    ) -> PyResult<Option<T>> {
        match d.get_item(key)? {
            Some(v) if !v.is_none() => {
                v.extract().map(Some).map_err(|_| input_err(format!("product['{key}']: expected {what}")))
            }
            _ => Ok(None),
        }
    }
    Ok(Some(skyfield::provenance::Product {
        instrument: get(d, "instrument", "a name")?,
        instrument_hash: get(d, "instrument_hash", "'blake3:<hex>'")?,
        filter: get(d, "filter", "a name")?,
        plate: get(d, "plate", "half_wave or quarter_wave")?,
        detector_px: get(d, "detector_px", "(nx, ny) pixels")?,
        pixel_scale_arcsec: get(d, "pixel_scale_arcsec", "arcsec per pixel")?,
        ..Default::default()
    }))
}
