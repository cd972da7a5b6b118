//! The package's two exceptions and the libraries' errors mapped onto them: `InputError` (a
//! `ValueError`) for bad values or file contents, `FileError` (an `OSError`) for files that
//! cannot be opened, read or written; the messages are the libraries', as the CLI prints them.

use pyo3::create_exception;
use pyo3::exceptions::{PyOSError, PyValueError};
use pyo3::prelude::*;

create_exception!(
    instpol,
    InputError,
    PyValueError,
    "Bad input: a value, an array or a file's content (a ValueError), with the message the CLI
prints for it.

Examples
--------
A polarization degree cannot be negative:

>>> import instpol
>>> try:
...     instpol.bias(-0.01, 0.002)
... except instpol.InputError as e:
...     print(isinstance(e, ValueError))
True"
);

create_exception!(
    instpol,
    FileError,
    PyOSError,
    "A file that cannot be opened, read or written (an OSError), with the message the CLI prints
for it.

Examples
--------
>>> import instpol
>>> try:
...     instpol.Calibration.load(\"no-such-calibration.fits\")
... except instpol.FileError as e:
...     print(isinstance(e, OSError))
True"
);

pub(crate) fn input_err(msg: impl std::fmt::Display) -> PyErr {
    InputError::new_err(msg.to_string())
}

pub(crate) fn sky_err(e: skyfield::Error) -> PyErr {
    match e {
        skyfield::Error::Fits { .. } | skyfield::Error::Write { .. } => FileError::new_err(e.to_string()),
        e => input_err(e),
    }
}

/// A calibration that cannot be loaded: FileError when the file cannot be read, InputError when
/// it is not a valid calibration; the message of `instpol correct --cal`.
pub(crate) fn load_err(path: &std::path::Path, e: fit::Error) -> PyErr {
    let file = matches!(e, fit::Error::Io { .. } | fit::Error::Fits { .. });
    let msg = format!("cannot load calibration {}: {e}", path.display());
    if file {
        FileError::new_err(msg)
    } else {
        input_err(msg)
    }
}

pub(crate) fn inst_err(e: instrument::Error) -> PyErr {
    match e {
        instrument::Error::Io { .. } => FileError::new_err(e.to_string()),
        e => input_err(e),
    }
}

pub(crate) fn night_err(e: workflow::night::Error) -> PyErr {
    match e {
        workflow::night::Error::Output { .. } => FileError::new_err(e.to_string()),
        e => input_err(e),
    }
}
