//! `instpol._instpol`: the compiled half of the Python package `instpol`.
//!
//! Thin by design (`docs/architecture.md`, "Two faces over one library"): numpy arrays in, the
//! same library functions the `instpol` CLI calls, numpy arrays out. The Python half
//! (`python/instpol/__init__.py`) turns user input into contiguous float64 arrays, broadcasts and
//! reshapes; this half runs the science with the GIL released (`Python::detach`) and never
//! touches a Python object per element.
//!
//! | Python                     | library function (as the CLI command)                      |
//! |----------------------------|------------------------------------------------------------|
//! | `instpol.stokes`           | `stokes::repeats::reduce_repeated` (`instpol stokes`)      |
//! | `instpol.bias`             | `stokes::stats::debias` (`instpol bias`)                   |
//! | `Calibration.load`         | `fit::Calibration::load` (`instpol correct --cal`)         |
//! | `Calibration.evaluate`     | `fit::correction::correct::Corrector::instrumental`                    |
//! | `Calibration.correct`      | `fit::correction::correct::Corrector::par_correct_batch` (`correct`)   |
//! | `instpol.reduce`           | `workflow::steps::reduce` (`instpol reduce`)               |
//! | `instpol.catalog`          | `workflow::steps::catalog` (`instpol catalog`)             |
//! | `instpol.simulate`         | `sim::Plan::write` (`instpol simulate`)                    |
//! | `instpol.calibrate`        | `workflow::steps::calibrate_map` (`calibrate --map`)       |
//! | `instpol.run`              | `workflow::night::run::run`, `library_executor` (`run`)    |
//!
//! One module per topic, this file only registering them: `stokes` (one source, bias), `maps`
//! (frames to a Stokes map), `catalog` (stars of a frame set), `calibration` (a calibration file
//! loaded, evaluated, applied), `calibrate` (the field measured on a sky field or from stars),
//! `simulate` (the simulator and the demo), `night` (a night scanned and run), `errors` (the two
//! exceptions) and `convert` (arrays and the inputs every function checks the same way).
//!
//! Errors: `instpol.InputError` (a `ValueError`) for bad values or file contents,
//! `instpol.FileError` (an `OSError`) for files that cannot be opened, read or written; the
//! messages are the libraries', as the CLI prints them.

mod calibrate;
mod calibration;
mod catalog;
mod convert;
mod errors;
mod maps;
mod night;
mod simulate;
mod stokes;

use errors::{FileError, InputError};
use pyo3::prelude::*;

#[pymodule]
fn _instpol(m: &Bound<'_, PyModule>) -> PyResult<()> {
    let py = m.py();
    m.add("InputError", py.get_type::<InputError>())?;
    m.add("FileError", py.get_type::<FileError>())?;
    m.add("__version__", env!("CARGO_PKG_VERSION"))?;
    m.add("__citation__", skyfield::provenance::citation())?;
    m.add_function(wrap_pyfunction!(stokes::_stokes, m)?)?;
    m.add_function(wrap_pyfunction!(stokes::_bias, m)?)?;
    m.add_function(wrap_pyfunction!(maps::_reduce, m)?)?;
    m.add_function(wrap_pyfunction!(catalog::_catalog, m)?)?;
    m.add_function(wrap_pyfunction!(calibrate::_calibrate_stars, m)?)?;
    m.add_function(wrap_pyfunction!(simulate::_demo, m)?)?;
    m.add_function(wrap_pyfunction!(simulate::_simulate, m)?)?;
    m.add_function(wrap_pyfunction!(calibrate::_calibrate, m)?)?;
    m.add_function(wrap_pyfunction!(night::_scan, m)?)?;
    m.add_function(wrap_pyfunction!(night::_run, m)?)?;
    m.add_class::<calibration::_Calibration>()?;
    Ok(())
}
