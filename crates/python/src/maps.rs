//! Frames to a Stokes map (`instpol.reduce`, as `instpol reduce`) and a map as the package
//! returns it.

use crate::convert::*;
use crate::errors::*;
use numpy::PyArray1;
use pyo3::prelude::*;
use pyo3::types::PyDict;
use std::path::PathBuf;

/// Frames to a binned Stokes map (`instpol reduce`): returns the map's arrays flat, in bin order
/// (row j, column i at j * nx + i), its header values and the warnings.
#[pyfunction]
#[pyo3(signature = (frames, instrument, bin, nsigma, allow_incomplete, bias, flat, hwp_angles, assembled, output, correct_again=false))]
#[allow(clippy::too_many_arguments)]
pub(crate) fn _reduce<'py>(
    py: Python<'py>,
    frames: Vec<PathBuf>,
    instrument: Option<&str>,
    bin: usize,
    nsigma: f64,
    allow_incomplete: bool,
    bias: Option<PathBuf>,
    flat: Option<PathBuf>,
    hwp_angles: Option<Vec<f64>>,
    assembled: bool,
    output: Option<PathBuf>,
    correct_again: bool,
) -> PyResult<Bound<'py, PyDict>> {
    let inst = instrument::Instrument::load(&frames_instrument(instrument, &frames)?).map_err(inst_err)?;
    skyfield::reduce::check_bin(bin, &inst).map_err(|e| input_err(format!("bin {bin}: {e}")))?;
    let cfg = skyfield::reduce::ReduceConfig {
        bin_px: bin,
        clip: skyfield::bin::ClipConfig { nsigma, ..Default::default() },
        min_pixels: None,
        require_complete_set: !allow_incomplete,
    };
    let read = read_options(bias, flat, hwp_angles, assembled, correct_again)?;
    refuse_same_data(&frames, skyfield::same::By::Content)?;
    refuse_same_data(frames.iter().chain(&read.bias).chain(&read.flat), skyfield::same::By::Identity)?;
    refuse_overwrite(output.as_deref(), frames.iter().chain(&read.bias).chain(&read.flat))?;
    // The instrument's plate decides the map (the library's rule, as `instpol reduce` takes it).
    // The one step `instpol reduce` makes (workflow::steps::reduce).
    let r = py
        .detach(|| workflow::steps::reduce(&frames, &inst, &cfg, &read, output.as_deref(), &|| {}))
        .map_err(sky_err)?;
    match &r {
        skyfield::reduce::PlateReduced::Linear(r) => {
            map_dict(py, &r.map, r.warnings.iter().map(|w| w.to_string()).collect())
        }
        skyfield::reduce::PlateReduced::Circular(r) => {
            circular_map_dict(py, &r.map, r.warnings.iter().map(|w| w.to_string()).collect())
        }
    }
}

/// The header values and bin centres every map dict carries (`map_dict`, `circular_map_dict`).
pub(crate) fn map_header<'py>(
    py: Python<'py>,
    d: &Bound<'py, PyDict>,
    g: &skyfield::BinGeometry,
    instrument: &str,
    filter: &str,
) -> PyResult<Bound<'py, PyDict>> {
    let h = PyDict::new(py);
    h.set_item("instrument", instrument)?;
    h.set_item("filter", filter)?;
    h.set_item("bin_px", g.bin_px)?;
    h.set_item("origin_x", g.origin_x)?;
    h.set_item("origin_y", g.origin_y)?;
    h.set_item("nx", g.nx)?;
    h.set_item("ny", g.ny)?;
    h.set_item("pixel_scale_arcsec", g.pixel_scale_arcsec)?;
    h.set_item("detector_nx", g.detector_nx)?;
    h.set_item("detector_ny", g.detector_ny)?;
    let (mut xa, mut ya) = (Vec::with_capacity(g.len()), Vec::with_capacity(g.len()));
    for j in 0..g.ny {
        for i in 0..g.nx {
            let (x, y) = g.centre_arcmin(i, j);
            xa.push(x);
            ya.push(y);
        }
    }
    d.set_item("x_arcmin", arr1(py, xa))?;
    d.set_item("y_arcmin", arr1(py, ya))?;
    Ok(h)
}

/// A map's product (`skyfield::provenance::Product`, as its header records it) as the map
/// dictionary's `product` (None for a map that records none).
pub(crate) fn map_product<'py>(
    py: Python<'py>,
    d: &Bound<'py, PyDict>,
    p: Option<&skyfield::provenance::Product>,
) -> PyResult<()> {
    match p {
        Some(p) => d.set_item("product", product_dict(py, &p.with_run_inputs())?),
        None => d.set_item("product", py.None()),
    }
}

/// A quarter-wave plate's V/I map as the Python package returns it (`instpol.CircularMap`):
/// `v`, `sigma_v`, `sigma_v_phot`, coverage, intensity, validity flat in bin order, the header
/// (with `stokes = "V"`, `plate_angles_deg`, `qwp_zero_angle_deg`) and `warnings`.
pub(crate) fn circular_map_dict<'py>(
    py: Python<'py>,
    m: &skyfield::CircularMap,
    warnings: Vec<String>,
) -> PyResult<Bound<'py, PyDict>> {
    let d = PyDict::new(py);
    let h = map_header(py, &d, &m.geometry, &m.instrument, &m.filter)?;
    h.set_item("stokes", "V")?;
    h.set_item("plate_angles_deg", m.plate_angles_deg.clone())?;
    h.set_item("qwp_zero_angle_deg", m.qwp_zero_angle_deg)?;
    d.set_item("header", h)?;
    map_product(py, &d, m.product.as_ref())?;
    for (name, v) in [
        ("v", &m.v),
        ("sigma_v", &m.sigma_v),
        ("sigma_v_phot", &m.sigma_v_phot),
        ("intensity", &m.intensity),
        ("intensity_snr", &m.intensity_snr),
    ] {
        d.set_item(name, arr1(py, v.clone()))?;
    }
    d.set_item("n_pixels", PyArray1::from_vec(py, m.n_pixels.clone()))?;
    d.set_item("valid", bools(py, m.valid.clone()))?;
    d.set_item("warnings", warnings)?;
    Ok(d)
}

/// A Stokes map as the Python package returns it: its arrays flat, in bin order (row j,
/// column i at j * nx + i), its header values and `warnings`.
pub(crate) fn map_dict<'py>(
    py: Python<'py>,
    m: &skyfield::StokesMap,
    warnings: Vec<String>,
) -> PyResult<Bound<'py, PyDict>> {
    let d = PyDict::new(py);
    let h = map_header(py, &d, &m.geometry, &m.instrument, &m.filter)?;
    h.set_item("hwp_angles_deg", m.hwp_angles_deg.clone())?;
    // What the map's q, u lack to be in the sky frame (HWPZERO; None when not recorded).
    h.set_item("hwp_zero_angle_deg", m.hwp_zero_angle_deg)?;
    d.set_item("header", h)?;
    map_product(py, &d, m.product.as_ref())?;
    for (name, v) in [
        ("q", &m.q),
        ("u", &m.u),
        ("sigma_q", &m.sigma_q),
        ("sigma_u", &m.sigma_u),
        ("cov_qu", &m.cov_qu),
        ("sigma_q_phot", &m.sigma_q_phot),
        ("sigma_u_phot", &m.sigma_u_phot),
        ("p", &m.p),
        ("intensity", &m.intensity),
        ("intensity_snr", &m.intensity_snr),
    ] {
        d.set_item(name, arr1(py, v.clone()))?;
    }
    d.set_item("chi_deg", arr1(py, m.chi.iter().map(|c| c.to_degrees()).collect()))?;
    d.set_item("n_pixels", PyArray1::from_vec(py, m.n_pixels.clone()))?;
    d.set_item("valid", bools(py, m.valid.clone()))?;
    d.set_item("warnings", warnings)?;
    Ok(d)
}
