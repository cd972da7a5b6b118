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
//! | `instpol.stokes`           | `stokes::Measurement::reduce` (`instpol stokes`)           |
//! | `instpol.bias`             | `stokes::stats::debias` (`instpol bias`)                   |
//! | `Calibration.load`         | `fit::Calibration::load` (`instpol correct --cal`)         |
//! | `Calibration.evaluate`     | `fit::correct::Corrector::instrumental`                    |
//! | `Calibration.correct`      | `fit::correct::Corrector::par_correct_batch` (`correct`)   |
//! | `instpol.reduce`           | `skyfield::reduce::reduce_for_plate` (`instpol reduce`)    |
//! | `instpol.catalog`          | `skyfield::catalog::catalog_files` (`instpol catalog`)     |
//! | `instpol.simulate`         | `sim::Plan::write` (`instpol simulate`)                    |
//! | `instpol.calibrate`        | `fit::pipeline::calibrate_sky_field` (`calibrate --map`)   |
//!
//! Errors: `instpol.InputError` (a `ValueError`) for bad values or file contents,
//! `instpol.FileError` (an `OSError`) for files that cannot be opened, read or written; the
//! messages are the libraries', as the CLI prints them.

use fit::columns::{Inputs, Units};
use fit::correct::Method;
use numpy::prelude::*;
use numpy::{PyArray1, PyArray2, PyReadonlyArray1, PyReadonlyArray2};
use pyo3::create_exception;
use pyo3::exceptions::{PyOSError, PyValueError};
use pyo3::prelude::*;
use pyo3::types::PyDict;
use rayon::prelude::*;
use std::borrow::Cow;
use std::path::PathBuf;
use stokes::stats::{Estimator, IntervalKind};

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

fn input_err(msg: impl std::fmt::Display) -> PyErr {
    InputError::new_err(msg.to_string())
}

fn sky_err(e: skyfield::Error) -> PyErr {
    match e {
        skyfield::Error::Fits { .. } | skyfield::Error::Write { .. } => FileError::new_err(e.to_string()),
        e => input_err(e),
    }
}

/// A calibration that cannot be loaded: FileError when the file cannot be read, InputError when
/// it is not a valid calibration; the message of `instpol correct --cal`.
fn load_err(path: &std::path::Path, e: fit::Error) -> PyErr {
    let file = matches!(e, fit::Error::Io { .. } | fit::Error::Fits { .. });
    let msg = format!("cannot load calibration {}: {e}", path.display());
    if file {
        FileError::new_err(msg)
    } else {
        input_err(msg)
    }
}

/// The instrument frames are read as: the one named, else the built-in one the first frame's
/// `INSTRUME` names (with a Python warning that says so), else InputError asking for
/// `instrument=` (`skyfield::io::instrument_from_headers`, as the CLI's `--instrument`).
fn frames_instrument(given: Option<&str>, frames: &[PathBuf]) -> PyResult<String> {
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

fn inst_err(e: instrument::Error) -> PyErr {
    match e {
        instrument::Error::Io { .. } => FileError::new_err(e.to_string()),
        e => input_err(e),
    }
}

/// A contiguous view of a float64 array (the Python half makes it contiguous).
fn slice<'a>(a: &'a PyReadonlyArray1<'_, f64>, what: &str) -> PyResult<&'a [f64]> {
    a.as_slice().map_err(|_| input_err(format!("{what}: expected a contiguous float64 array")))
}

fn slice2<'a>(a: &'a PyReadonlyArray2<'_, f64>, what: &str) -> PyResult<&'a [f64]> {
    a.as_slice().map_err(|_| input_err(format!("{what}: expected a contiguous float64 array")))
}

fn arr1<'py>(py: Python<'py>, v: Vec<f64>) -> Bound<'py, PyArray1<f64>> {
    PyArray1::from_vec(py, v)
}

fn arr2<'py>(py: Python<'py>, v: Vec<f64>, rows: usize, cols: usize) -> PyResult<Bound<'py, PyArray2<f64>>> {
    PyArray1::from_vec(py, v).reshape([rows, cols])
}

fn bools<'py>(py: Python<'py>, v: Vec<bool>) -> Bound<'py, PyArray1<bool>> {
    PyArray1::from_vec(py, v)
}

fn opt(x: Option<f64>) -> f64 {
    x.unwrap_or(f64::NAN)
}

/// Dual-beam reduction of `m` stars measured at the same `n` HWP angles (`eq:F`, `eq:Q`,
/// `eq:U`, `eq:sigp`, `eq:sigchi`, `eq:fourcoeff`, `eq:a0`, `eq:kappa2`): `f_o`, `f_e` (and the
/// optional per-beam errors) are `(m, n)`. `single`: one star (errors name no star).
#[pyfunction]
#[pyo3(signature = (hwp_deg, f_o, f_e, sigma_o, sigma_e, kappa, angles_in_radians, single))]
#[allow(clippy::too_many_arguments)]
fn _stokes<'py>(
    py: Python<'py>,
    hwp_deg: PyReadonlyArray1<'py, f64>,
    f_o: PyReadonlyArray2<'py, f64>,
    f_e: PyReadonlyArray2<'py, f64>,
    sigma_o: Option<PyReadonlyArray2<'py, f64>>,
    sigma_e: Option<PyReadonlyArray2<'py, f64>>,
    kappa: Option<f64>,
    angles_in_radians: bool,
    single: bool,
) -> PyResult<Bound<'py, PyDict>> {
    let hwp = slice(&hwp_deg, "hwp_deg")?;
    let n = hwp.len();
    let [m, nf] = [f_o.shape()[0], f_o.shape()[1]];
    if nf != n || f_e.shape() != f_o.shape() {
        return Err(input_err(format!(
            "f_o has shape {:?} and f_e {:?}: both must have one column per HWP angle ({n} angles in hwp_deg)",
            f_o.shape(),
            f_e.shape()
        )));
    }
    let sig = match (&sigma_o, &sigma_e) {
        (Some(a), Some(b)) => {
            if a.shape() != f_o.shape() || b.shape() != f_o.shape() {
                return Err(input_err(format!(
                    "sigma_o {:?} and sigma_e {:?} must have the shape of f_o {:?}",
                    a.shape(),
                    b.shape(),
                    f_o.shape()
                )));
            }
            Some((slice2(a, "sigma_o")?, slice2(b, "sigma_e")?))
        }
        (None, None) => None,
        (Some(_), None) => return Err(input_err("sigma_o is given without sigma_e (give both or neither)")),
        (None, Some(_)) => return Err(input_err("sigma_e is given without sigma_o (give both or neither)")),
    };
    let (fo, fe) = (slice2(&f_o, "f_o")?, slice2(&f_e, "f_e")?);
    let theta: Vec<f64> = if angles_in_radians {
        hwp.to_vec()
    } else {
        if let Err(e) = stokes::check_degrees(hwp) {
            return Err(input_err(format!(
                "hwp_deg holds {e}. Give the angles in degrees, or pass angles_in_radians=True"
            )));
        }
        hwp.iter().map(|d| d.to_radians()).collect()
    };
    let (red, repeats) = reduce_stars(py, &theta, (fo, fe), sig, kappa, m, single)?;
    let d = reductions_dict(py, &red, n)?;
    d.set_item("exposures", exposures_dict(py, &repeats, hwp)?)?;
    Ok(d)
}

/// A star's reduction, and its exposures' check when a plate position repeats.
type Star = (stokes::Reduction, Option<stokes::repeats::Combined>);

/// Each star's row of `f_o`, `f_e` (and of the per-beam errors) reduced at the plate angles
/// `theta` (rad) (`m` stars), repeated exposures combined and kappa corrected as `instpol stokes` does;
/// the first failure is the error (naming its star unless `single`).
fn reduce_stars(
    py: Python<'_>,
    theta: &[f64],
    (fo, fe): (&[f64], &[f64]),
    sig: Option<(&[f64], &[f64])>,
    kappa: Option<f64>,
    m: usize,
    single: bool,
) -> PyResult<(Vec<stokes::Reduction>, Vec<Option<stokes::repeats::Combined>>)> {
    let n = theta.len();
    let results: Vec<Result<Star, String>> = py.detach(|| {
        (0..m)
            .into_par_iter()
            .map(|s| {
                let row = |a: &[f64]| a[s * n..(s + 1) * n].to_vec();
                let (o, e) = (row(fo), row(fe));
                let errs = sig.map(|(so, se)| (row(so), row(se)));
                // Exposures at one plate position are combined as instpol stokes does.
                let combined =
                    stokes::repeats::combine_exposures(theta, &o, &e, errs.as_ref().map(|(a, b)| (&a[..], &b[..])))
                        .map_err(|e| match e {
                            stokes::Error::NegativeCount { index } => format!("column {index} of f_o, f_e: {e}"),
                            e => e.to_string(),
                        })?;
                let (th, o, e, errs) = match &combined {
                    Some(c) => (
                        c.theta.clone(),
                        c.f_o.clone(),
                        c.f_e.clone(),
                        errs.map(|_| (c.sigma_o.clone(), c.sigma_e.clone())),
                    ),
                    None => (theta.to_vec(), o, e, errs),
                };
                let meas = match errs {
                    Some((so, se)) => stokes::Measurement::with_errors(th, o, e, so, se),
                    None => stokes::Measurement::poisson(th, o, e),
                }
                .map_err(|e| e.to_string())?;
                let meas = match kappa {
                    Some(k) => meas.corrected_for_kappa(k).map_err(|e| format!("kappa: {e}"))?,
                    None => meas,
                };
                Ok((meas.reduce().map_err(|e| e.to_string())?, combined))
            })
            .collect()
    });
    let mut red = Vec::with_capacity(m);
    let mut repeats = Vec::with_capacity(m);
    for (s, r) in results.into_iter().enumerate() {
        match r {
            Ok((r, c)) => {
                red.push(r);
                repeats.push(c);
            }
            Err(e) if single => return Err(input_err(e)),
            Err(e) => return Err(input_err(format!("star {s} (row {s} of f_o, f_e): {e}"))),
        }
    }
    Ok((red, repeats))
}

/// The stars' reductions as Python columns (one value per star; `f`, kappa and the harmonics
/// one row per star); `n` the plate angles before repeats were combined.
fn reductions_dict<'py>(py: Python<'py>, red: &[stokes::Reduction], n: usize) -> PyResult<Bound<'py, PyDict>> {
    let m = red.len();
    // The HWP positions after combining repeats (the same for every star: the angles are).
    let n = red.first().map_or(n, |r| r.n);
    let col = |f: &dyn Fn(&stokes::Reduction) -> f64| -> Vec<f64> { red.iter().map(f).collect() };
    let d = PyDict::new(py);
    d.set_item("n_hwp", n)?;
    d.set_item("q", arr1(py, col(&|r| r.qu.q)))?;
    d.set_item("u", arr1(py, col(&|r| r.qu.u)))?;
    d.set_item("p", arr1(py, col(&|r| r.p)))?;
    d.set_item("chi_deg", arr1(py, col(&|r| r.chi_deg())))?;
    d.set_item("sigma_q", arr1(py, col(&|r| r.qu.var_q.sqrt())))?;
    d.set_item("sigma_u", arr1(py, col(&|r| r.qu.var_u.sqrt())))?;
    d.set_item("cov_qu", arr1(py, col(&|r| r.qu.cov_qu)))?;
    d.set_item("sigma_p", arr1(py, col(&|r| r.sigma_p)))?;
    d.set_item("sigma_chi_deg", arr1(py, col(&|r| opt(r.sigma_chi_deg_reported()))))?;
    d.set_item("chi_defined", bools(py, red.iter().map(|r| r.chi_defined).collect()))?;
    d.set_item("snr", arr1(py, col(&|r| r.snr)))?;
    d.set_item("sigma_p_analytic", arr1(py, col(&|r| r.sigma_p_analytic)))?;
    d.set_item("sigma_chi_analytic_deg", arr1(py, col(&|r| r.sigma_chi_analytic.to_degrees())))?;
    d.set_item("a0", arr1(py, col(&|r| r.a0)))?;
    d.set_item("sigma_a0", arr1(py, col(&|r| r.sigma_a0)))?;
    d.set_item("mean_kappa", arr1(py, col(&|r| opt(r.kappa_mean))))?;
    // kappa_j and the harmonics depend on the angle set only for their number: the same for
    // every star.
    let nk = red.first().map_or(0, |r| r.kappa.len());
    let nh = red.first().map_or(0, |r| r.fourier.len());
    let flat = |f: &dyn Fn(&stokes::Reduction) -> Vec<f64>| -> Vec<f64> { red.iter().flat_map(f).collect() };
    d.set_item("kappa", arr2(py, flat(&|r| r.kappa.iter().map(|k| k.kappa).collect()), m, nk)?)?;
    d.set_item("f", arr2(py, flat(&|r| r.f.clone()), m, n)?)?;
    d.set_item("sigma_f", arr2(py, flat(&|r| r.sigma_f.clone()), m, n)?)?;
    let four = pyo3::types::PyDict::new(py);
    four.set_item("k", red.first().map_or(vec![], |r| r.fourier.iter().map(|h| h.k).collect::<Vec<_>>()))?;
    four.set_item("a", arr2(py, flat(&|r| r.fourier.iter().map(|h| h.a).collect()), m, nh)?)?;
    four.set_item("b", arr2(py, flat(&|r| r.fourier.iter().map(|h| h.b).collect()), m, nh)?)?;
    four.set_item("sigma_a", arr2(py, flat(&|r| r.fourier.iter().map(|h| h.sigma_a).collect()), m, nh)?)?;
    four.set_item("sigma_b", arr2(py, flat(&|r| r.fourier.iter().map(|h| h.sigma_b).collect()), m, nh)?)?;
    four.set_item("power", arr2(py, flat(&|r| r.fourier.iter().map(|h| h.power()).collect()), m, nh)?)?;
    d.set_item("fourier", four)?;
    let est: Vec<String> = red
        .iter()
        .map(|r| match r.estimator {
            stokes::Estimator::FourierSums => "fourier_sums",
            stokes::Estimator::LeastSquares => "least_squares",
            stokes::Estimator::WeightedLeastSquares => "weighted_least_squares",
        })
        .map(String::from)
        .collect();
    d.set_item("estimator", est)?;
    let warn: Vec<Vec<String>> = red.iter().map(|r| r.warnings.iter().map(|w| w.to_string()).collect()).collect();
    d.set_item("warnings", warn)?;
    Ok(d)
}

/// Repeated exposures: each input exposure's own F and its pull about its position's mean
/// (stokes::repeats), as instpol stokes --json's `exposures`; None when no position repeats.
/// `hwp` the input plate angles (deg).
fn exposures_dict<'py>(
    py: Python<'py>,
    repeats: &[Option<stokes::repeats::Combined>],
    hwp: &[f64],
) -> PyResult<Option<Bound<'py, PyDict>>> {
    let (m, n_in) = (repeats.len(), hwp.len());
    if !(repeats.iter().all(|c| c.is_some()) && !repeats.is_empty()) {
        return Ok(None);
    }
    let checks = |f: &dyn Fn(&stokes::repeats::ExposureCheck) -> f64| -> Vec<f64> {
        repeats.iter().flat_map(|c| c.as_ref().map_or(vec![], |c| c.checks.iter().map(f).collect())).collect()
    };
    let ex = PyDict::new(py);
    ex.set_item("index", (0..n_in).collect::<Vec<usize>>())?;
    ex.set_item("hwp_deg", arr1(py, hwp.to_vec()))?;
    ex.set_item("f", arr2(py, checks(&|k| k.f), m, n_in)?)?;
    ex.set_item("pull", arr2(py, checks(&|k| k.pull), m, n_in)?)?;
    let outl: Vec<bool> = repeats
        .iter()
        .flat_map(|c| c.as_ref().map_or(vec![], |c| c.checks.iter().map(|k| k.outlier).collect()))
        .collect();
    ex.set_item("outlier", bools(py, outl).reshape([m, n_in])?)?;
    Ok(Some(ex))
}

/// Bias correction of `P` (section `sec:bias`) and an interval on `P0`, element by element over
/// flat arrays of equal length (`sigma_q`, `sigma_u` optional; `chi_deg` the measured angle).
#[pyfunction]
#[pyo3(signature = (p, sigma, estimator, interval, cl, sigma_q, sigma_u, chi_deg, single))]
#[allow(clippy::too_many_arguments)]
fn _bias<'py>(
    py: Python<'py>,
    p: PyReadonlyArray1<'py, f64>,
    sigma: PyReadonlyArray1<'py, f64>,
    estimator: &str,
    interval: &str,
    cl: f64,
    sigma_q: Option<PyReadonlyArray1<'py, f64>>,
    sigma_u: Option<PyReadonlyArray1<'py, f64>>,
    chi_deg: PyReadonlyArray1<'py, f64>,
    single: bool,
) -> PyResult<Bound<'py, PyDict>> {
    let est: Estimator = estimator.parse().map_err(input_err)?;
    let kind: IntervalKind = interval.parse().map_err(input_err)?;
    let (p, sigma, chi) = (slice(&p, "p")?, slice(&sigma, "sigma")?, slice(&chi_deg, "chi_deg")?);
    let sq = sigma_q.as_ref().map(|a| slice(a, "sigma_q")).transpose()?;
    let su = sigma_u.as_ref().map(|a| slice(a, "sigma_u")).transpose()?;
    let n = p.len();
    if [sigma.len(), chi.len(), sq.map_or(n, |a| a.len()), su.map_or(n, |a| a.len())].iter().any(|&l| l != n) {
        return Err(input_err("p, sigma, sigma_q, sigma_u and chi_deg must have one shape (after broadcasting)"));
    }
    let res: Vec<Result<stokes::stats::Debiased, String>> = py.detach(|| {
        (0..n)
            .into_par_iter()
            .map(|i| {
                stokes::stats::debias(
                    p[i],
                    sigma[i],
                    est,
                    kind,
                    cl,
                    sq.map(|a| a[i]),
                    su.map(|a| a[i]),
                    chi[i].to_radians(),
                )
                .map_err(|e| e.to_string())
            })
            .collect()
    });
    let mut out = Vec::with_capacity(n);
    for (i, r) in res.into_iter().enumerate() {
        match r {
            Ok(r) => out.push(r),
            Err(e) if single => return Err(input_err(e)),
            Err(e) => return Err(input_err(format!("element {i}: {e}"))),
        }
    }
    let d = PyDict::new(py);
    d.set_item("estimator", est.name())?;
    d.set_item("interval_kind", kind.to_string())?;
    d.set_item("cl", cl)?;
    d.set_item("estimate", arr1(py, out.iter().map(|r| r.estimate.value).collect()))?;
    d.set_item("in_validity_range", bools(py, out.iter().map(|r| r.estimate.in_validity_range).collect()))?;
    d.set_item("lo", arr1(py, out.iter().map(|r| opt(r.interval.lo)).collect()))?;
    d.set_item("hi", arr1(py, out.iter().map(|r| opt(r.interval.hi)).collect()))?;
    d.set_item("upper_limit_only", bools(py, out.iter().map(|r| r.interval.upper_limit_only).collect()))?;
    d.set_item("empty", bools(py, out.iter().map(|r| r.interval.empty).collect()))?;
    let all = PyDict::new(py);
    for (k, e) in Estimator::ALL.iter().enumerate() {
        all.set_item(e.name(), arr1(py, out.iter().map(|r| r.all[k]).collect()))?;
    }
    d.set_item("all_estimators", all)?;
    Ok(d)
}

/// The field model a calibration file holds: a partial polarizer p, phi (`instpol calibrate`,
/// `import-map`, `fit`) or a Mueller field (`instpol calibrate-mueller --out CAL.fits`); or
/// none, in a telescope-only file (`instpol fit-standards --output`), named by its instrument
/// and its telescope model's only band ("" with several).
enum Field<'a> {
    PPhi(&'a fit::Calibration),
    Mueller(&'a fit::mueller_cal::MuellerCal),
    TelescopeOnly {
        instrument: &'a str,
        filter: &'a str,
    },
    /// An instrument's constant response from standards (`instpol efficiency`).
    Response(&'a fit::response_cal::ResponseCal),
}

/// A calibration file as `fit::calibration::load` reads it (`instpol correct`'s reader): a
/// partial polarizer (`fit::Calibration`) or a Mueller field (`fit::mueller_cal::MuellerCal`),
/// with the telescope model stored beside the field one or alone (`instpol fit-standards
/// --output`), applied after the field with each row's parallactic angle.
#[pyclass(module = "instpol._instpol", frozen)]
struct _Calibration {
    file: fit::calibration::CalibrationFile,
    path: PathBuf,
}

impl _Calibration {
    /// The file's field model, or what names a telescope-only file.
    fn field(&self) -> Field<'_> {
        if let Some(r) = &self.file.response {
            return Field::Response(r);
        }
        match (&self.file.field, &self.file.mueller, &self.file.telescope) {
            (Some(c), _, _) => Field::PPhi(c),
            (None, Some(m), _) => Field::Mueller(m),
            (None, None, t) => Field::TelescopeOnly {
                instrument: &self.file.instrument,
                filter: t.as_ref().filter(|t| t.bands.len() == 1).map_or("", |t| t.bands[0].0.as_str()),
            },
        }
    }

    fn instrument_filter(&self) -> (&str, &str) {
        match self.field() {
            Field::PPhi(c) => (&c.instrument, &c.filter),
            Field::Mueller(m) => (&m.instrument, &m.filter),
            Field::TelescopeOnly { instrument, filter } => (instrument, filter),
            Field::Response(r) => (&r.instrument, &r.filter),
        }
    }

    fn pixel(&self) -> Option<fit::calfile::PixelGrid> {
        fit::columns::pixel_grid(&self.file)
    }

    /// A telescope model's band that cannot be chosen, in this package's words.
    fn band_error(&self, e: fit::telescope::BandChoiceError) -> PyErr {
        use fit::telescope::{BandChoiceError, BandSource};
        let path = self.path.display();
        input_err(match e {
            BandChoiceError::Missing { band, source: BandSource::Asked, bands } => {
                format!("band '{band}': the telescope model of {path} has bands {}: choose one with band=", bands.join(", "))
            }
            BandChoiceError::Missing { band, source: BandSource::FieldCalibration, bands } => format!(
                "{path}: the field calibration is for filter {band}, a band the telescope model does not have (it has {}): choose one with band=",
                bands.join(", ")
            ),
            BandChoiceError::Ambiguous { bands } => {
                format!("the telescope model of {path} has bands {}: choose one with band=", bands.join(", "))
            }
        })
    }

    /// A refusal of `fit::request::plan_map` in this package's words.
    fn map_error(&self, e: fit::request::Refusal, input: &std::path::Path) -> PyErr {
        use fit::request::Refusal as E;
        let (cal_path, input) = (self.path.display(), input.display());
        input_err(match e {
            E::TelescopeOptions { mueller } => format!(
                "parang_deg, rotator_deg and band are for calibrations with a telescope model; {cal_path} holds {}",
                if mueller { "a Mueller field" } else { "none" }
            ),
            E::Mismatch { mismatch: fit::setup::Mismatch::Setup { data, calibration }, .. } => format!(
                "{input} is a {} {} map but {cal_path} calibrates {} {} (instrument, filter): use the calibration of the map's instrument and filter (or allow_mismatch=True)",
                data.0, data.1, calibration.0, calibration.1
            ),
            E::BandMismatch { map_filter, band } => format!(
                "{input} is a {map_filter} map but the telescope model's band is {band}: use the band of the map's filter (band=), or allow_mismatch=True"
            ),
            E::NoParallactic => format!(
                "{input}: the map needs the parallactic angle of its exposures for the telescope model of {cal_path}: give parang_deg=(START, END) (deg: the first frame's start, the last frame's end; instpol reduce records it when the instrument's [telescope] section names the header keywords)"
            ),
            E::NoRotator { .. } => format!(
                "the telescope model of {cal_path} was fitted with rotator angles: give the exposures' with rotator_deg="
            ),
            E::Band(b) => return self.band_error(b),
            e => return self.rows_error(e, false),
        })
    }

    /// A note of `fit::request` on a map's correction, in this package's words.
    fn note_text(&self, n: &fit::request::Note, input: &std::path::Path) -> String {
        use fit::request::Note;
        let (cal_path, input) = (self.path.display(), input.display());
        match n {
            Note::TrackReplaced { recorded: (s, e) } => format!(
                "parang_deg replaces the parallactic angle {input} recorded ({:.3} to {:.3} deg)",
                s.to_degrees(),
                e.to_degrees()
            ),
            Note::RotatorIgnored => format!(
                "rotator_deg is ignored: the telescope model of {cal_path} was fitted without rotator angles (its offset holds the rotator's)"
            ),
            Note::ZeroAngleUnknown(w) => w.clone(),
            Note::MismatchAllowed(m) => format!(
                "allow_mismatch: {input} and {cal_path} do not fit together ({m}); corrected all the same"
            ),
            Note::CarriedZeroAngle { carried, calibration, applied } => format!(
                "q, u carry the HWP zero angle {carried} deg but {cal_path} records {calibration} deg: the rows are turned by the difference, {applied} deg, into the calibration's frame (every chi0 moves by it)"
            ),
            Note::AnglesWithoutTelescope => format!(
                "{cal_path} holds no telescope model: the telescope's polarization is NOT removed"
            ),

        }
    }

    /// A refusal of `fit::request` in this package's words (`per_row`: parang_deg was given).
    fn rows_error(&self, e: fit::request::Refusal, per_row: bool) -> PyErr {
        use fit::request::Refusal as E;
        let path = self.path.display();
        match e {
            E::TelescopeOptions { mueller: true } => input_err(format!(
                "parang_deg, parang_end_deg and band are for calibrations with a telescope model; {path} holds a Mueller field"
            )),
            E::TelescopeOptions { mueller: false } if per_row => input_err(format!(
                "parang_deg given but {path} holds no telescope model: the telescope's polarization would NOT be removed (fit one with instpol fit-standards --output --field-cal)"
            )),
            E::TelescopeOptions { mueller: false } => input_err(format!(
                "band or recorded given but {path} holds no telescope model: the telescope's polarization would NOT be removed"
            )),
            E::MuellerFirstOrder => input_err(format!(
                "method \"first-order\": {path} holds a Mueller field, which is inverted exactly (eq:approx is the p, phi model's first order)"
            )),
            E::NoParallactic => input_err(format!(
                "{path} holds a telescope model ({}): give each row's parallactic angle, parang_deg= (deg, as the standards were fitted with), as `instpol correct` reads it from the column parang_deg",
                self.file.telescope.as_ref().map_or("", |t| t.model.name())
            )),
            E::TwoTracks => input_err("give parang_deg (each row's track) or recorded (the catalog's exposures), not both"),
            E::NoRotator { per_row: false } => {
                input_err("recorded: the telescope model was fitted with rotator angles and the catalog recorded none")
            }
            E::NoRotator { per_row: true } => input_err(format!(
                "the telescope model of {path} was fitted with rotator angles, which correct() does not take: correct the catalog with instpol correct (column rotator_deg, or --rotator)"
            )),
            E::Band(b) => self.band_error(b),
            E::Exposures(m) => input_err(format!("recorded: {m}")),
            E::Mismatch { mismatch, .. } => input_err(format!(
                "{mismatch}: give the calibration of the rows' instrument and filter (instrument=, filter= are the rows'), or allow_mismatch=True"
            )),
            E::FrameUnstated { .. } => input_err(format!(
                "{e}: give sky_pa_deg= (catalog()['product']['sky_pa_deg']) or product=catalog()['product'], or sky_pa_deg=0 (with hwp_chi_offset_deg=) for rows in the instrument's own frame"
            )),
            e => input_err(e.to_string()),
        }
    }

    /// Positions in arcmin from the detector centre, from `units` "px" (0-based pixels of the
    /// calibration's grid) or "arcmin" (`fit::columns::arcmin_positions`).
    fn arcmin<'a>(&self, x: &'a [f64], y: &'a [f64], units: &str) -> PyResult<(Cow<'a, [f64]>, Cow<'a, [f64]>)> {
        let units = match units {
            "arcmin" => Units::Arcmin,
            "px" | "pixel" => Units::Pixel,
            u => return Err(input_err(format!("units '{u}': expected \"px\" or \"arcmin\""))),
        };
        fit::columns::arcmin_positions(x, y, units, self.pixel()).map_err(|_| {
            input_err("the calibration has no pixel grid: give the positions in arcmin (units=\"arcmin\")")
        })
    }
}

#[pymethods]
impl _Calibration {
    #[staticmethod]
    fn load(py: Python<'_>, path: PathBuf) -> PyResult<Self> {
        // The reader `instpol correct` uses: a Mueller field, or a field model and a telescope
        // model when the file holds one (ignoring it would return the telescope's polarization
        // as the sky's).
        // A telescope-only file (instpol fit-standards --output): correct() applies the
        // telescope alone, as `instpol correct` does.
        let file = py.detach(|| fit::calibration::load(&path)).map_err(|e| load_err(&path, e))?;
        Ok(Self { file, path })
    }

    #[getter]
    fn path(&self) -> PathBuf {
        self.path.clone()
    }
    #[getter]
    fn instrument(&self) -> String {
        self.instrument_filter().0.to_string()
    }
    #[getter]
    fn filter(&self) -> String {
        self.instrument_filter().1.to_string()
    }
    #[getter]
    fn lambda_nm(&self) -> f64 {
        match self.field() {
            Field::PPhi(c) => c.lambda_nm,
            Field::Mueller(_) | Field::TelescopeOnly { .. } | Field::Response(_) => f64::NAN,
        }
    }
    #[getter]
    fn hwp_chi_offset_deg(&self) -> f64 {
        match self.field() {
            Field::PPhi(c) => c.hwp_chi_offset_deg,
            // A Mueller field: the zero angle its maps were turned by (fit::mueller_cal); a
            // telescope model alone records none (its frame: fit::telescope_cal).
            Field::Mueller(m) => m.hwp_chi_offset_deg,
            Field::TelescopeOnly { .. } => 0.0,
            // A constant response: the zero angle of the sky frame it lives in.
            Field::Response(r) => r.hwp_chi_offset_deg,
        }
    }
    #[getter]
    fn model(&self) -> &'static str {
        match self.field() {
            Field::PPhi(c) => c.model.kind(),
            Field::Mueller(_) => "MUELLER",
            Field::TelescopeOnly { .. } => "TELESCOPE",
            Field::Response(_) => fit::response_cal::RESPONSE_MODEL,
        }
    }
    /// A Mueller field's model in words (`physical`, `general`), as `instpol correct --json`
    /// says it; None for a p, phi calibration.
    #[getter]
    fn mueller_model(&self) -> Option<&'static str> {
        match self.field() {
            Field::Mueller(m) => Some(m.field.kind.model_name()),
            Field::PPhi(_) | Field::TelescopeOnly { .. } | Field::Response(_) => None,
        }
    }
    /// A Mueller field's free effects (`diattenuation`, `retardance`, ...); empty otherwise.
    #[getter]
    fn mueller_free(&self) -> Vec<&'static str> {
        match self.field() {
            Field::Mueller(m) => m.field.kind.free_words(),
            Field::PPhi(_) | Field::TelescopeOnly { .. } | Field::Response(_) => vec![],
        }
    }
    #[getter]
    fn rms_residual(&self) -> f64 {
        match self.field() {
            Field::PPhi(c) => c.rms_residual,
            Field::Mueller(_) | Field::TelescopeOnly { .. } | Field::Response(_) => f64::NAN,
        }
    }
    #[getter]
    fn centre_arcmin(&self) -> (f64, f64) {
        match self.field() {
            Field::PPhi(c) => {
                let c = c.centre_arcmin();
                (c[0], c[1])
            }
            Field::Mueller(_) | Field::TelescopeOnly { .. } | Field::Response(_) => (f64::NAN, f64::NAN),
        }
    }
    #[getter]
    fn has_pixel_grid(&self) -> bool {
        self.pixel().is_some()
    }
    /// The bands of the telescope model stored in the file (empty without one).
    #[getter]
    fn telescope_bands(&self) -> Vec<String> {
        self.file.telescope.as_ref().map_or(vec![], |t| t.bands.iter().map(|b| b.0.clone()).collect())
    }

    /// Instrumental `(q, u)` with the calibration's covariance at flat arrays `x`, `y`, and
    /// whether each position lies inside the calibrated field.
    fn _evaluate<'py>(
        &self,
        py: Python<'py>,
        x: PyReadonlyArray1<'py, f64>,
        y: PyReadonlyArray1<'py, f64>,
        units: &str,
    ) -> PyResult<Bound<'py, PyDict>> {
        use field::FieldModel;
        let (x, y) = (slice(&x, "x")?, slice(&y, "y")?);
        if x.len() != y.len() {
            return Err(input_err("x and y must have one shape (after broadcasting)"));
        }
        if let Field::TelescopeOnly { .. } = self.field() {
            return Err(input_err(format!(
                "{} holds only a telescope model: it has no field to evaluate (correct() applies it with parang_deg=)",
                self.path.display()
            )));
        }
        let (x, y) = self.arcmin(x, y, units)?;
        let (x, y) = (x.as_ref(), y.as_ref());
        fn at<M: FieldModel + Sync>(m: &M, x: &[f64], y: &[f64]) -> Vec<(fit::model::InstPol, bool)> {
            x.par_iter().zip(y).map(|(&x, &y)| (m.eval(x, y), m.contains(x, y))).collect()
        }
        let v = py.detach(|| match self.field() {
            Field::PPhi(c) => at(c, x, y),
            Field::Mueller(m) => at(&m.field, x, y),
            Field::TelescopeOnly { .. } => vec![],
            // The same everywhere: (q0, u0) with the file's covariance.
            Field::Response(r) => {
                let (q0, u0, c) = (r.response.q0, r.response.u0, &r.covariance);
                vec![(mueller::Qu::new(q0, u0, c[0][0], c[1][1], c[0][1]), true); x.len()]
            }
        });
        let d = PyDict::new(py);
        d.set_item("q", arr1(py, v.iter().map(|a| a.0.q).collect()))?;
        d.set_item("u", arr1(py, v.iter().map(|a| a.0.u).collect()))?;
        d.set_item("sigma_q", arr1(py, v.iter().map(|a| a.0.var_q.sqrt()).collect()))?;
        d.set_item("sigma_u", arr1(py, v.iter().map(|a| a.0.var_u.sqrt()).collect()))?;
        d.set_item("cov_qu", arr1(py, v.iter().map(|a| a.0.cov_qu).collect()))?;
        d.set_item("inside", bools(py, v.iter().map(|a| a.1).collect()))?;
        Ok(d)
    }

    /// `instpol correct` on flat arrays: exact inversion of `eq:instpol` (or `eq:approx`), the
    /// HWP zero angle first, errors propagated; `estimator`: also the bias-corrected `P0`.
    #[pyo3(signature = (x, y, q, u, sigma_q, sigma_u, cov_qu, units, method, allow_extrapolation, extrapolation_error, estimator, parang_deg, parang_end_deg, band, recorded, carried_deg, setup, allow_mismatch, sky_pa_deg=None))]
    #[allow(clippy::too_many_arguments)]
    fn _correct<'py>(
        &self,
        py: Python<'py>,
        x: PyReadonlyArray1<'py, f64>,
        y: PyReadonlyArray1<'py, f64>,
        q: PyReadonlyArray1<'py, f64>,
        u: PyReadonlyArray1<'py, f64>,
        sigma_q: PyReadonlyArray1<'py, f64>,
        sigma_u: PyReadonlyArray1<'py, f64>,
        cov_qu: Option<PyReadonlyArray1<'py, f64>>,
        units: &str,
        method: &str,
        allow_extrapolation: bool,
        extrapolation_error: f64,
        estimator: Option<&str>,
        parang_deg: Option<PyReadonlyArray1<'py, f64>>,
        parang_end_deg: Option<PyReadonlyArray1<'py, f64>>,
        band: Option<String>,
        recorded: Option<Recorded>,
        carried_deg: Option<f64>,
        setup: Option<(String, String, Option<String>)>,
        allow_mismatch: bool,
        sky_pa_deg: Option<f64>,
    ) -> PyResult<Bound<'py, PyDict>> {
        let base = request(method, allow_extrapolation, extrapolation_error, band.as_deref(), allow_mismatch)?;
        // What the rows are (instrument, filter, plate: catalog()'s), checked against the
        // calibration as a table's keywords are.
        let setup = setup.map(|(instrument, filter, plate)| fit::setup::Setup { instrument, filter, plate });
        // The zero angle q, u already carry (catalog()'s do): given, else what `recorded`
        // says, else none (q, u at the plate); the calibration's less it is applied, as
        // `instpol correct` takes a table's hwp_chi_offset_deg column.
        if carried_deg.is_some_and(|z| !mueller::plausible_degrees(z)) {
            return Err(input_err("hwp_chi_offset_deg must be finite degrees"));
        }
        let carried = carried_deg.or_else(|| recorded.as_ref().and_then(|r| r.zero_angle_deg));
        if sky_pa_deg.is_some_and(|z| !mueller::plausible_degrees(z)) {
            return Err(input_err("sky_pa_deg must be finite degrees"));
        }
        let frame = mueller::Frame::carrying_on_sky(carried, sky_pa_deg).ok_or_else(|| {
            input_err("sky_pa_deg without hwp_chi_offset_deg: give the zero angle the rows carry too (catalog()'s chi_offset_deg)")
        })?;
        let est: Option<Estimator> =
            estimator.map(|e| e.parse().map_err(|e| input_err(format!("estimator: {e}")))).transpose()?;
        let (x, y, q, u) = (slice(&x, "x")?, slice(&y, "y")?, slice(&q, "q")?, slice(&u, "u")?);
        let (sq, su) = (slice(&sigma_q, "sigma_q")?, slice(&sigma_u, "sigma_u")?);
        let cov = cov_qu.as_ref().map(|c| slice(c, "cov_qu")).transpose()?;
        let n = x.len();
        if [y.len(), q.len(), u.len(), sq.len(), su.len(), cov.map_or(n, |c| c.len())].iter().any(|&l| l != n) {
            return Err(input_err("x, y, q, u, sigma_q, sigma_u and cov_qu must have one shape (after broadcasting)"));
        }
        let pa = parang_deg.as_ref().map(|c| slice(c, "parang_deg")).transpose()?;
        let pa_end = parang_end_deg.as_ref().map(|c| slice(c, "parang_end_deg")).transpose()?;
        if [pa.map_or(n, |c| c.len()), pa_end.map_or(n, |c| c.len())].iter().any(|&l| l != n) {
            return Err(input_err("parang_deg and parang_end_deg must have the shape of x (after broadcasting)"));
        }
        if pa_end.is_some() && pa.is_none() {
            return Err(input_err("parang_end_deg needs parang_deg (each row's start)"));
        }
        // The one rule set of `instpol correct`'s tables (fit::request).
        let request = fit::request::Request {
            frame,
            per_row: pa.map(|start_deg| fit::request::PerRowAngles { start_deg, end_deg: pa_end, rotator_deg: None }),
            recorded: recorded.as_ref().map(|r| &r.angles),
            data: setup.as_ref(),
            frame_unstated: sky_pa_deg.is_none(),
            ..base
        };
        let plan = fit::request::plan_rows(&self.file, &request, n).map_err(|e| self.rows_error(e, pa.is_some()))?;
        let (x, y) = self.arcmin(x, y, units)?;
        let input = Inputs { frame: request.frame, x: &x, y: &y, q, u, sigma_q: sq, sigma_u: su, cov_qu: cov };
        let out = py.detach(|| fit::columns::correct_columns(&input, est, &|_| {}, |k, m| plan.correct(k, m)));
        let out = out.map_err(|(row, e)| input_err(format!("index {row}: {e}")))?;
        let d = PyDict::new(py);
        for (name, c) in out.names.iter().zip(out.values) {
            d.set_item(name, arr1(py, c))?;
        }
        d.set_item(fit::correct::EXTRAPOLATED_COLUMN, bools(py, out.extrapolated))?;
        d.set_item("n_extrapolated", out.n_extrapolated)?;
        d.set_item("n_unmeasured", out.n_unmeasured)?;
        if let Some(t) = &plan.telescope {
            d.set_item("telescope_model", t.fit.model.name())?;
            d.set_item("telescope_band", t.band.as_str())?;
            d.set_item("telescope_exposures", recorded.as_ref().map(|r| r.angles.exposure_tracks.len()))?;
        }
        Ok(d)
    }

    /// `instpol correct` on a Stokes map file (from `instpol reduce` or `reduce(output=)`): the
    /// calibration's field, Mueller field or telescope chain over every valid bin
    /// (`fit::request::MapPlan::correct`), the map's instrument and filter checked, the
    /// telescope's band and track by the CLI's rules; `output`: the corrected map, written with
    /// the correction's record (`INSTCORR`, ...). Returns the corrected map as `_reduce` does,
    /// with the correction's summary.
    #[pyo3(signature = (input, output, method, allow_extrapolation, extrapolation_error, parang_deg, rotator_deg, band, allow_mismatch))]
    #[allow(clippy::too_many_arguments)]
    fn _correct_map<'py>(
        &self,
        py: Python<'py>,
        input: PathBuf,
        output: Option<PathBuf>,
        method: &str,
        allow_extrapolation: bool,
        extrapolation_error: f64,
        parang_deg: Option<Vec<f64>>,
        rotator_deg: Option<f64>,
        band: Option<String>,
        allow_mismatch: bool,
    ) -> PyResult<Bound<'py, PyDict>> {
        use fit::telescope::{angle_from_deg, track_from_deg, TrackDegError};
        let base = request(method, allow_extrapolation, extrapolation_error, band.as_deref(), allow_mismatch)?;
        let bad = |name: &str, x: f64| input_err(format!("{name} {x}: not an angle in degrees (-360 to 360)"));
        let given = parang_deg.as_deref().map(track_from_deg).transpose().map_err(|e| match e {
            TrackDegError::NotAnAngle(x) => bad("parang_deg", x),
            TrackDegError::Count(_) => input_err("parang_deg: expected START or (START, END) in degrees"),
        })?;
        let rotator = rotator_deg.map(|r| angle_from_deg(r).ok_or_else(|| bad("rotator_deg", r))).transpose()?;
        refuse_overwrite(output.as_deref(), [&input, &self.path])?;
        let map = py
            .detach(|| skyfield::StokesMap::read_uncorrected(&input))
            .map_err(|e| input_err(format!("Stokes map {}: {e}", input.display())))?;
        // The one rule set of `instpol correct` on a map (fit::request::plan_map).
        let request = fit::request::Request { parang: given, rotator, ..base };
        let plan = fit::request::plan_map(&self.file, &request, &map).map_err(|e| self.map_error(e, &input))?;
        let notes: Vec<String> = plan.notes.iter().map(|n| self.note_text(n, &input)).collect();
        let name = self.path.file_name().map(|n| n.to_string_lossy().to_string()).unwrap_or_default();
        let (c, stamp) = py
            .detach(|| {
                let r = plan.correct(&map, &name);
                let (c, stamp) = r.map_err(|e| format!("{} {e}", input.display()))?;
                if let Some(out) = &output {
                    c.map.write_corrected_fits(out, &stamp).map_err(|e| e.to_string())?;
                }
                Ok::<_, String>((c, stamp))
            })
            .map_err(input_err)?;
        let d = map_dict(py, &c.map, notes)?;
        let r = PyDict::new(py);
        r.set_item("calibration", &stamp.calibration)?;
        r.set_item("method", &stamp.method)?;
        r.set_item("hwp_chi_offset_deg", stamp.hwp_chi_offset_deg)?;
        r.set_item("n_bins", c.n_bins)?;
        r.set_item("n_extrapolated", c.n_extrapolated)?;
        if let Some(t) = &stamp.telescope {
            r.set_item("telescope_model", &t.model)?;
            r.set_item("telescope_band", &t.band)?;
            r.set_item("rotator_deg", t.rotator_deg)?;
        }
        if let Some((a, b)) = c.map.parallactic_rad {
            r.set_item("parang_deg", (a.to_degrees(), b.to_degrees()))?;
        }
        d.set_item("correction", r)?;
        Ok(d)
    }
}

/// A catalog's recorded telescope angles as the package passes them (`catalog()`'s
/// `recorded_angles`: the set's track and rotator in deg, each exposure's HWP angle and track
/// in deg), in radians, and the HWP zero angle (deg) the catalog's q, u carry
/// (`hwp_chi_offset_deg`, as the CLI's tables carry it in a column; `None` when not given).
struct Recorded {
    angles: skyfield::RecordedAngles,
    zero_angle_deg: Option<f64>,
}

impl<'a, 'py> FromPyObject<'a, 'py> for Recorded {
    type Error = PyErr;
    fn extract(ob: pyo3::Borrowed<'a, 'py, PyAny>) -> PyResult<Self> {
        let bad = || {
            input_err("recorded: expected catalog()['recorded_angles'] (a dict of parang_deg, rotator_deg, exposures)")
        };
        let d = ob.cast::<PyDict>().map_err(|_| bad())?;
        let get = |k: &str| d.get_item(k).ok().flatten().ok_or_else(bad);
        let (s, e): (f64, f64) = get("parang_deg")?.extract().map_err(|_| bad())?;
        let rot: Option<f64> = get("rotator_deg")?.extract().map_err(|_| bad())?;
        let ex: Vec<(f64, f64, f64)> = get("exposures")?.extract().map_err(|_| bad())?;
        let zero_angle_deg: Option<f64> = match d.get_item("hwp_chi_offset_deg").ok().flatten() {
            Some(z) => Some(z.extract().map_err(|_| bad())?),
            None => None,
        };
        let finite = mueller::plausible_degrees;
        if !zero_angle_deg.is_none_or(finite) {
            return Err(input_err("recorded: hwp_chi_offset_deg must be finite degrees"));
        }
        if !(finite(s)
            && finite(e)
            && rot.is_none_or(finite)
            && ex.iter().all(|x| finite(x.0) && finite(x.1) && finite(x.2)))
            || ex.is_empty()
        {
            return Err(input_err("recorded: angles must be finite degrees and list at least one exposure"));
        }
        let angles = skyfield::RecordedAngles {
            parallactic_rad: Some((s.to_radians(), e.to_radians())),
            rotator_rad: rot.map(f64::to_radians),
            exposure_tracks: ex
                .into_iter()
                .map(|(h, a, b)| skyfield::ExposureTrack { hwp_deg: h, start: a.to_radians(), end: b.to_radians() })
                .collect(),
        };
        Ok(Self { angles, zero_angle_deg })
    }
}

fn read_options(
    bias: Option<PathBuf>,
    flat: Option<PathBuf>,
    hwp_angles: Option<Vec<f64>>,
    assembled: bool,
    correct_again: bool,
) -> PyResult<skyfield::calib::ReadOptions> {
    if let Some(v) = &hwp_angles {
        if v.is_empty() || v.iter().any(|x| !x.is_finite()) {
            return Err(input_err(
                "hwp_angles: expected finite angles in degrees, one per frame, e.g. [0, 22.5, 45, 67.5]",
            ));
        }
    }
    Ok(skyfield::calib::ReadOptions { bias, flat, hwp_angles_deg: hwp_angles, assembled, correct_again })
}

/// No function writes over one of its own inputs, whatever name `output` gives it (the one
/// rule of both faces, `skyfield::durable::refuse_overwrite`).
fn refuse_overwrite<'a>(
    output: Option<&std::path::Path>,
    inputs: impl IntoIterator<Item = &'a PathBuf>,
) -> PyResult<()> {
    let Some(out) = output else { return Ok(()) };
    skyfield::durable::refuse_overwrite(out, inputs.into_iter().map(PathBuf::as_path)).map_err(input_err)
}

/// Input files that are the same data under two names (the same path, a link, or with
/// `By::Content` a copy: `skyfield::same::distinct_files` decides) refused naming both: they
/// would be counted twice.
fn refuse_same_data<'a>(inputs: impl IntoIterator<Item = &'a PathBuf>, by: skyfield::same::By) -> PyResult<()> {
    let paths: Vec<&PathBuf> = inputs.into_iter().collect();
    match skyfield::same::distinct_files(&paths, by).duplicates.first() {
        Some(d) => {
            Err(input_err(format!("{d}: each input may be given once (the same data twice would be counted twice)")))
        }
        None => Ok(()),
    }
}

/// What the package's corrections ask of `fit::request`, before each adds its angles: `method=`
/// ("exact" or "first-order") and `extrapolation_error=` checked, no angles yet, and any angles
/// given later are the caller's arguments (refused without a telescope model, where a table's
/// columns would only be noted).
fn request<'a>(
    method: &str,
    allow_extrapolation: bool,
    extrapolation_error: f64,
    band: Option<&'a str>,
    allow_mismatch: bool,
) -> PyResult<fit::request::Request<'a>> {
    let method = match method {
        "exact" => Method::Exact,
        "first-order" | "first_order" => Method::FirstOrder,
        m => return Err(input_err(format!("method '{m}': expected \"exact\" or \"first-order\""))),
    };
    fit::request::check_extrapolation_error(extrapolation_error)
        .map_err(|f| input_err(format!("extrapolation_error {f} must be a non-negative number")))?;
    let base = fit::request::Request::new(method, allow_extrapolation, extrapolation_error);
    Ok(fit::request::Request { band, angles_are_arguments: true, allow_mismatch, ..base })
}

/// Frames to a binned Stokes map (`instpol reduce`): returns the map's arrays flat, in bin order
/// (row j, column i at j * nx + i), its header values and the warnings.
#[pyfunction]
#[pyo3(signature = (frames, instrument, bin, nsigma, allow_incomplete, bias, flat, hwp_angles, assembled, output, correct_again=false))]
#[allow(clippy::too_many_arguments)]
fn _reduce<'py>(
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
    let r = py
        .detach(|| {
            let mut r = skyfield::reduce::reduce_for_plate(&frames, &inst, &cfg, &read, &|| {})?;
            match &mut r {
                skyfield::reduce::PlateReduced::Linear(r) => {
                    // The exposures' telescope angles, as `instpol reduce` records them.
                    fit::telescope_cal::record_telescope_angles(&mut r.map, &r.exposures, &frames, &inst);
                    if let Some(out) = &output {
                        r.map.write_fits(out)?;
                    }
                }
                skyfield::reduce::PlateReduced::Circular(r) => {
                    if let Some(out) = &output {
                        r.map.write_fits(out)?;
                    }
                }
            }
            Ok::<_, skyfield::Error>(r)
        })
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
fn map_header<'py>(
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
fn map_product<'py>(
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
fn circular_map_dict<'py>(
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
fn map_dict<'py>(py: Python<'py>, m: &skyfield::StokesMap, warnings: Vec<String>) -> PyResult<Bound<'py, PyDict>> {
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

/// Every paired star of a frame set (`instpol catalog`): one entry per column, one value per
/// star, plus the catalog's metadata.
#[pyfunction]
#[pyo3(signature = (frames, instrument, fwhm, threshold, aperture, annulus, bias, flat, hwp_angles, assembled, kappa, kappa_from_data, pair_tol, cal, allow_extrapolation, force, correct_again=false))]
#[allow(clippy::too_many_arguments)]
fn _catalog<'py>(
    py: Python<'py>,
    frames: Vec<PathBuf>,
    instrument: Option<&str>,
    fwhm: f64,
    threshold: f64,
    aperture: &str,
    annulus: (f64, f64),
    bias: Option<PathBuf>,
    flat: Option<PathBuf>,
    hwp_angles: Option<Vec<f64>>,
    assembled: bool,
    kappa: Option<f64>,
    kappa_from_data: bool,
    pair_tol: f64,
    cal: Option<PathBuf>,
    allow_extrapolation: bool,
    force: bool,
    correct_again: bool,
) -> PyResult<Bound<'py, PyDict>> {
    use skyfield::catalog::{catalog_files, CatalogConfig};
    let radius = skyfield::photometry::ApertureRadius::parse(aperture).ok_or_else(|| {
        InputError::new_err(format!(
            "aperture '{aperture}': expected a radius in px (8), a multiple of the FWHM ('2.5fwhm') or 'best'"
        ))
    })?;
    let kappa = match (kappa, kappa_from_data) {
        (Some(_), true) => return Err(InputError::new_err("give kappa or kappa_from_data, not both")),
        (Some(k), false) => stokes::KappaCorrection::Known(k),
        (None, true) => stokes::KappaCorrection::FromData,
        (None, false) => stokes::KappaCorrection::None,
    };
    let inst = instrument::Instrument::load(&frames_instrument(instrument, &frames)?).map_err(inst_err)?;
    let cfg = CatalogConfig {
        detect: skyfield::detect::DetectConfig {
            fwhm_px: fwhm,
            threshold_sigma: threshold,
            pair_tol_px: pair_tol,
            ..Default::default()
        },
        radius,
        annulus: Some(annulus),
        weighting: skyfield::aperture::Weighting::Exact,
        kappa,
        force,
    };
    cfg.check().map_err(sky_err)?;
    let read = read_options(bias, flat, hwp_angles, assembled, correct_again)?;
    refuse_same_data(&frames, skyfield::same::By::Content)?;
    refuse_same_data(frames.iter().chain(&read.bias).chain(&read.flat).chain(&cal), skyfield::same::By::Identity)?;
    let loaded = match &cal {
        Some(p) => Some(py.detach(|| fit::calibration::load(p)).map_err(|e| load_err(p, e))?),
        None => None,
    };
    let (cat, warnings) = py
        .detach(|| {
            let (cat, warnings) = catalog_files(&frames, &inst, &read, &cfg, Box::new(|| {}))?;
            Ok::<_, skyfield::Error>((cat, warnings.iter().map(|w| w.to_string()).collect::<Vec<_>>()))
        })
        .map_err(sky_err)?;
    // Corrected in the same run, as `instpol catalog --cal` (the one rule in fit::catalog_correct).
    let corrected = match (&loaded, &cal) {
        (Some(l), Some(p)) => {
            let opts = fit::correct::CorrectOptions { allow_extrapolation, ..Default::default() };
            let (c, used) = fit::catalog_correct::correct_catalog_loaded(&cat, &inst, &frames, l, opts)
                .map_err(|e| input_err(format!("cal {}: {e}", p.display())))?;
            Some((c, used))
        }
        _ => None,
    };
    let d = catalog_dict(py, &cat)?;
    d.set_item("recorded_angles", recorded_angles_dict(py, &cat, &frames, &inst)?)?;
    if let Some((c, used)) = &corrected {
        set_corrected(&d, c, used.as_ref())?;
    }
    d.set_item("warnings", warnings)?;
    Ok(d)
}

/// A catalog's rows as Python columns (one value per star), with its metadata.
fn catalog_dict<'py>(py: Python<'py>, cat: &skyfield::catalog::Catalog) -> PyResult<Bound<'py, PyDict>> {
    let rows = &cat.rows;
    let n = cat.hwp_deg.len();
    let d = PyDict::new(py);
    let col = |f: fn(&skyfield::catalog::Row) -> f64| arr1(py, rows.iter().map(f).collect());
    d.set_item("id", PyArray1::from_vec(py, rows.iter().map(|r| r.id as u64).collect()))?;
    d.set_item("x", col(|r| r.x))?;
    d.set_item("y", col(|r| r.y))?;
    d.set_item("x_e", col(|r| r.x_e))?;
    d.set_item("y_e", col(|r| r.y_e))?;
    d.set_item("x_arcmin", col(|r| r.x_arcmin))?;
    d.set_item("y_arcmin", col(|r| r.y_arcmin))?;
    d.set_item("fwhm_px", col(|r| r.fwhm_px))?;
    d.set_item("aperture_px", col(|r| r.aperture_px))?;
    d.set_item("flux_e", col(|r| r.flux_e))?;
    d.set_item("q", col(|r| r.q))?;
    d.set_item("u", col(|r| r.u))?;
    d.set_item("sigma_q", col(|r| r.sigma_q))?;
    d.set_item("sigma_u", col(|r| r.sigma_u))?;
    d.set_item("cov_qu", col(|r| r.cov_qu))?;
    d.set_item("p", col(|r| r.p))?;
    d.set_item("sigma_p", col(|r| r.sigma_p))?;
    d.set_item("chi_deg", col(|r| r.chi_deg))?;
    d.set_item("sigma_chi_deg", col(|r| r.sigma_chi_deg))?;
    d.set_item("a0", col(|r| r.a0))?;
    d.set_item("kappa", col(|r| opt(r.kappa)))?;
    d.set_item("kappa_applied", col(|r| opt(r.kappa_applied)))?;
    d.set_item("chi2_mod", col(|r| r.chi2_mod))?;
    d.set_item("dof_mod", PyArray1::from_vec(py, rows.iter().map(|r| r.dof_mod as u64).collect()))?;
    d.set_item("sigma_q_scatter", col(|r| r.sigma_q_scatter))?;
    d.set_item("sigma_u_scatter", col(|r| r.sigma_u_scatter))?;
    d.set_item("flags", PyArray1::from_vec(py, rows.iter().map(|r| r.flags).collect()))?;
    d.set_item("flag_names", rows.iter().map(|r| skyfield::catalog::flags::names(r.flags)).collect::<Vec<_>>())?;
    d.set_item("note", rows.iter().map(|r| r.note.clone()).collect::<Vec<_>>())?;
    // The frames' celestial WCS: each star's RA, Dec (deg), as the catalog's table has them.
    if rows.iter().any(|r| r.ra_deg.is_some()) {
        d.set_item("ra_deg", col(|r| opt(r.ra_deg)))?;
        d.set_item("dec_deg", col(|r| opt(r.dec_deg)))?;
    }
    // Through a quarter-wave plate: V/I of every star and the plate's zero angle (the linear
    // columns are NaN), as `instpol catalog` writes them.
    if let Some(z) = cat.qwp_zero_angle_deg {
        d.set_item("v", col(|r| opt(r.v)))?;
        d.set_item("sigma_v", col(|r| opt(r.sigma_v)))?;
        d.set_item("qwp_zero_angle_deg", z)?;
    }
    let f: Vec<f64> = rows.iter().flat_map(|r| (0..n).map(|i| r.f.get(i).copied().unwrap_or(f64::NAN))).collect();
    d.set_item("f", arr2(py, f, rows.len(), n)?)?;
    d.set_item("hwp_deg", cat.hwp_deg.clone())?;
    d.set_item("filter", &cat.filter)?;
    // What the catalog is (instrument, filter, plate, frame, detector), as its tables' keywords.
    if let Some(p) = &cat.product {
        d.set_item("product", product_dict(py, p)?)?;
    }
    d.set_item("chi_offset_deg", cat.chi_offset_deg)?;
    d.set_item("oe_offset_px", cat.oe_offset_px)?;
    d.set_item("unpaired", cat.unpaired.clone())?;
    d.set_item("unpaired_why", cat.unpaired_why.iter().map(|w| pythonize_why(*w)).collect::<Vec<_>>())?;
    d.set_item("unpaired_shift_px", cat.unpaired_shift_px)?;
    d.set_item("n_sources", cat.n_sources)?;
    Ok(d)
}

/// The exposures' telescope angles, as `instpol catalog` records them in its tables: what
/// `Calibration.correct(..., recorded=...)` takes; None when the frames record none.
fn recorded_angles_dict<'py>(
    py: Python<'py>,
    cat: &skyfield::catalog::Catalog,
    frames: &[PathBuf],
    inst: &instrument::Instrument,
) -> PyResult<Option<Bound<'py, PyDict>>> {
    let Some(r) = fit::telescope_cal::recorded_angles(&cat.frames, frames, inst) else { return Ok(None) };
    let rd = PyDict::new(py);
    let (s, e) = r.parallactic_rad.unwrap_or_default();
    rd.set_item("parang_deg", (s.to_degrees(), e.to_degrees()))?;
    rd.set_item("rotator_deg", r.rotator_rad.map(f64::to_degrees))?;
    let ex: Vec<(f64, f64, f64)> =
        r.exposure_tracks.iter().map(|x| (x.hwp_deg, x.start.to_degrees(), x.end.to_degrees())).collect();
    rd.set_item("exposures", ex)?;
    // What the q, u carry: correct(recorded=...) takes it as the CLI takes a table's
    // hwp_chi_offset_deg column.
    rd.set_item("hwp_chi_offset_deg", cat.chi_offset_deg)?;
    Ok(Some(rd))
}

/// The corrected columns of `instpol correct` (NaN for a star not measured), with what the
/// correction applied and the telescope model it used.
fn set_corrected(
    d: &Bound<'_, PyDict>,
    c: &fit::catalog_correct::CorrectedCatalog,
    used: Option<&fit::catalog_correct::TelescopeUsed>,
) -> PyResult<()> {
    let py = d.py();
    let out = fit::columns::Outputs::of_rows(&c.rows);
    for (name, values) in out.names.iter().zip(out.values) {
        d.set_item(name, arr1(py, values))?;
    }
    d.set_item("extrapolated", PyArray1::from_vec(py, out.extrapolated))?;
    d.set_item("chi_offset_applied_deg", c.chi_offset_applied_deg)?;
    d.set_item("n_extrapolated", c.n_extrapolated)?;
    d.set_item("telescope_model", used.map(|t| t.model))?;
    d.set_item("telescope_band", used.map(|t| t.band.clone()))?;
    d.set_item("telescope_exposures", used.map(|t| t.exposures))?;
    Ok(())
}

/// The main job end to end on the paper's fields (`workflow::demo::run`, what `instpol demo` runs)
/// into the folder `out`: its report as JSON text (the `instpol demo --json` keys; no plots,
/// so `plot_outputs` lists none). FileError when a file cannot be written, InputError else.
#[pyfunction]
#[pyo3(signature = (out, through_frames, keep_frames, seed))]
fn _demo(py: Python<'_>, out: PathBuf, through_frames: bool, keep_frames: bool, seed: u64) -> PyResult<String> {
    let opts = workflow::demo::DemoOptions { through_frames, keep_frames, seed };
    let demo = py.detach(|| workflow::demo::run(&out, &opts, &|_| {})).map_err(|e| match e {
        workflow::demo::Error::Create { .. }
        | workflow::demo::Error::Fit(fit::Error::Io { .. } | fit::Error::Fits { .. }) => {
            FileError::new_err(e.to_string())
        }
        workflow::demo::Error::Frames(e) => sky_err(e),
        e => input_err(e),
    })?;
    serde_json::to_string(&demo.report).map_err(|e| input_err(format!("the demo's report: {e}")))
}

/// Raw-like frames of a scene (`sim::Plan::write`, what `instpol simulate` runs) into the folder
/// `out`: what was written as JSON text (`instpol simulate --json`'s keys). `scene`: a scene
/// file, or with `scene_json` the scene's table as JSON text (`label` names it in errors, its
/// paths taken as they are). `field`: a calibration whose model replaces the scene's
/// `[effects.instpol]` (of the scene's instrument and filter). No frame lands on the scene, its
/// instrument file or the calibration; a run that fails removes the files it created.
#[pyfunction]
#[pyo3(signature = (scene, scene_json, out, field, force))]
fn _simulate(
    py: Python<'_>,
    scene: PathBuf,
    scene_json: Option<&str>,
    out: PathBuf,
    field: Option<PathBuf>,
    force: bool,
) -> PyResult<String> {
    let sim_err = |e: sim::Error| match e {
        sim::Error::File { .. } => FileError::new_err(e.to_string()),
        sim::Error::Frames(e) => sky_err(e),
        sim::Error::Instrument(e) => inst_err(e),
        e => input_err(e),
    };
    let sc = match scene_json {
        Some(text) => serde_json::from_str::<sim::Scene>(text)
            .map_err(|e| input_err(format!("scene {}: {e}", scene.display())))?
            .checked(&scene)
            .map_err(sim_err)?,
        None => sim::Scene::from_file(&scene).map_err(sim_err)?,
    };
    let mut inputs: Vec<PathBuf> = vec![];
    if scene_json.is_none() {
        inputs.push(scene.clone());
    }
    if std::path::Path::new(&sc.instrument).is_file() {
        inputs.push(PathBuf::from(&sc.instrument));
    }
    let model = match &field {
        Some(p) => {
            inputs.push(p.clone());
            let cal = fit::Calibration::load(p).map_err(|e| load_err(p, e))?;
            let inst = instrument::Instrument::load(&sc.instrument).map_err(inst_err)?;
            if !fit::setup::matches_calibration(&inst.name, &sc.filter, &cal) {
                return Err(input_err(format!(
                    "{} calibrates {} {} but the scene is {} {}: use a calibration of the scene's instrument and filter",
                    p.display(),
                    cal.instrument,
                    cal.filter,
                    inst.name,
                    sc.filter
                )));
            }
            Some(std::sync::Arc::new(cal) as std::sync::Arc<dyn field::FieldModel>)
        }
        None => None,
    };
    let plan = sim::Plan::build_with_field(&sc, model).map_err(sim_err)?;
    plan.check_output_size(&scene, force).map_err(sim_err)?;
    let planned: Vec<PathBuf> = plan.output_files().iter().map(|f| out.join(f)).collect();
    for p in &planned {
        refuse_overwrite(Some(p), &inputs)?;
    }
    let existed: Vec<bool> = planned.iter().map(|p| p.exists()).collect();
    let written = py.detach(|| plan.write(&out, &|| {}));
    let written = match written {
        Ok(w) => w,
        Err(e) => {
            for (p, was) in planned.iter().zip(existed) {
                if !was {
                    let _ = std::fs::remove_file(p);
                }
            }
            return Err(sim_err(e));
        }
    };
    serde_json::to_string(&written).map_err(|e| input_err(format!("what was written: {e}")))
}

/// The instrumental field from a Stokes map of an empty field whose sky polarization is known
/// (`fit::pipeline::calibrate_sky_field`, what `instpol calibrate --map` runs): the fit's
/// summary as JSON text (`instpol calibrate --json`'s keys, no plots); the calibration written
/// to `out` when given. `sky`: (P percent, chi deg); `model`, `exclude` as the CLI's options.
#[pyfunction]
#[pyo3(signature = (map, instrument, sky, model, include_c0, free_centre, exclude, residual_map, out))]
#[allow(clippy::too_many_arguments)]
fn _calibrate(
    py: Python<'_>,
    map: PathBuf,
    instrument: Option<&str>,
    sky: (f64, f64),
    model: &str,
    include_c0: bool,
    free_centre: bool,
    exclude: Vec<String>,
    residual_map: bool,
    out: Option<PathBuf>,
) -> PyResult<String> {
    let fit_err = |e: fit::Error| match e {
        fit::Error::Io { .. } | fit::Error::Fits { .. } => FileError::new_err(e.to_string()),
        e => input_err(e),
    };
    for (name, v) in [("sky_p_percent", sky.0), ("sky_chi_deg", sky.1)] {
        if !v.is_finite() {
            return Err(input_err(format!("{name} {v}: expected a finite number")));
        }
    }
    let sky = skyfield::solve::SkyPolarization::from_percent_deg(sky.0, sky.1).map_err(sky_err)?;
    let mut fo = fit::RadialFitOptions { include_c0, free_centre, ..Default::default() };
    for e in &exclude {
        fo.exclusions.push(e.parse().map_err(fit_err)?);
    }
    let mut opts = fit::pipeline::CalibrateOptions { fit: fo, residual_map, ..Default::default() };
    opts.set_model_name(model).map_err(fit_err)?;
    let inputs = [map.clone()];
    let name = frames_instrument(instrument, &inputs)?;
    let inst = instrument::Instrument::load(&name).map_err(inst_err)?;
    let mut all_inputs = inputs.to_vec();
    if std::path::Path::new(&name).is_file() {
        all_inputs.push(PathBuf::from(&name));
    }
    refuse_overwrite(out.as_deref(), &all_inputs)?;
    let stokes_map = skyfield::StokesMap::read_uncorrected(&map).map_err(sky_err)?;
    if let Some(w) = fit::setup::zero_angle_disagreement(&stokes_map, &inst) {
        py.import("warnings")?.call_method1("warn", (w,))?;
    }
    let run = py
        .detach(|| fit::pipeline::calibrate_sky_field(&stokes_map, &sky, &inst, vec![map.display().to_string()], &opts))
        .map_err(fit_err)?;
    let mut summary = fit::pipeline::FitSummary::new(&run);
    if let Some(out) = &out {
        run.calibration.save(out).map_err(fit_err)?;
        summary.calibration_file = Some(out.display().to_string());
    }
    serde_json::to_string(&summary).map_err(|e| input_err(format!("the fit's summary: {e}")))
}

/// The instrumental field from field-star catalogs (`fit::stars_field`, what `instpol
/// calibrate-stars` runs): the summary as JSON text (`calibrate-stars --json`'s keys, no
/// plots); the calibration written to `out` when given. `interstellar`: None for a fitted
/// term, `(0, 0)` with `zero` for none, or `(P percent, chi deg)`.
#[pyfunction]
#[pyo3(signature = (catalogs, instrument, filter, out, interstellar_free, interstellar, offsets, model, free_centre, reject_alpha, match_radius_arcsec, allow_mismatch))]
#[allow(clippy::too_many_arguments)]
fn _calibrate_stars(
    py: Python<'_>,
    catalogs: Vec<PathBuf>,
    instrument: Option<&str>,
    filter: &str,
    out: Option<PathBuf>,
    interstellar_free: bool,
    interstellar: Option<(f64, f64)>,
    offsets: Option<Vec<(f64, f64)>>,
    model: &str,
    free_centre: bool,
    reject_alpha: f64,
    match_radius_arcsec: f64,
    allow_mismatch: bool,
) -> PyResult<String> {
    use fit::stars_field::{read_catalogs, stars_field, stars_meta, Interstellar, StarsOptions, StarsSummary};
    if catalogs.is_empty() {
        return Err(input_err("no catalogs given: the star catalogs of the pointings (instpol catalog --out)"));
    }
    refuse_same_data(&catalogs, skyfield::same::By::Content)?;
    refuse_overwrite(out.as_deref(), catalogs.iter())?;
    // The one rule of the instrument of catalogs (`instpol calibrate-stars`'s): an inferred or
    // assumed one is said as a Python warning.
    let fit_err = |e: fit::Error| match e {
        fit::Error::Io { .. } | fit::Error::Fits { .. } => FileError::new_err(e.to_string()),
        e => input_err(format!("{e} (instrument=)")),
    };
    let (name, chosen) = fit::stars_field::catalogs_instrument(instrument, &catalogs).map_err(fit_err)?;
    let said = match chosen {
        fit::stars_field::InstrumentChoice::Given => None,
        fit::stars_field::InstrumentChoice::Recorded(i) => {
            Some(format!("instrument {name}, which the catalogs say they are of (INSTRUME = '{i}')"))
        }
        fit::stars_field::InstrumentChoice::Assumed => Some(format!(
            "the catalogs do not say which instrument they are of (no INSTRUME keyword): taken as {name}; give instrument= if they are another's"
        )),
    };
    if let Some(w) = said {
        py.import("warnings")?.call_method1("warn", (w,))?;
    }
    let inst = instrument::Instrument::load(&name).map_err(inst_err)?;
    let interstellar = match (interstellar_free, interstellar) {
        (true, _) => Interstellar::Free,
        (false, None) => Interstellar::Zero,
        (false, Some((p, chi))) => {
            Interstellar::from_percent_deg(p, chi).map_err(|e| input_err(format!("interstellar: {e}")))?
        }
    };
    let mut calibrate = fit::pipeline::CalibrateOptions::default();
    calibrate.set_model_name(model).map_err(input_err)?;
    calibrate.fit.free_centre = free_centre;
    if !(match_radius_arcsec > 0.0 && match_radius_arcsec.is_finite()) {
        return Err(input_err(format!("match_radius_arcsec {match_radius_arcsec} must be positive")));
    }
    let opts = StarsOptions {
        calibrate,
        interstellar,
        offsets: offsets.map(|o| o.into_iter().map(|(x, y)| [x, y]).collect()),
        match_radius_arcmin: match_radius_arcsec / 60.0,
        reject_alpha,
    };
    let summary = py.detach(|| -> Result<StarsSummary, fit::Error> {
        let expect = (!allow_mismatch).then_some((inst.name.as_str(), filter));
        let (rows, z, notes) = read_catalogs(&catalogs, expect)?;
        let meta = stars_meta(&inst, filter, z, catalogs.iter().map(|p| p.display().to_string()).collect());
        let run = stars_field(&rows, catalogs.len(), meta, &opts)?;
        if let Some(p) = &out {
            run.run.calibration.save(p)?;
        }
        let mut s = StarsSummary::new(&run, &rows, reject_alpha);
        s.warnings.splice(0..0, notes);
        s.fit.calibration_file = out.as_ref().map(|p| p.display().to_string());
        Ok(s)
    });
    let summary = summary.map_err(|e| match e {
        fit::Error::Io { .. } | fit::Error::Fits { .. } => FileError::new_err(e.to_string()),
        e => input_err(e),
    })?;
    serde_json::to_string(&summary).map_err(|e| input_err(format!("the summary: {e}")))
}

fn night_err(e: workflow::night::Error) -> PyErr {
    match e {
        workflow::night::Error::Output { .. } => FileError::new_err(e.to_string()),
        e => input_err(e),
    }
}

/// A folder of raw files sorted by their headers into a plan (`workflow::night::scan::scan`,
/// what `instpol scan` runs): the plan as JSON text (`instpol scan --json`'s keys but
/// `provenance`); written to `out` too when given (TOML, or JSON for a .json name).
#[pyfunction]
#[pyo3(signature = (dirs, instrument, products, sky, sky_table, standards, pointing_tol_arcsec, max_gap_min, bin, fwhm, aperture, out))]
#[allow(clippy::too_many_arguments)]
fn _scan(
    py: Python<'_>,
    dirs: Vec<PathBuf>,
    instrument: String,
    products: PathBuf,
    sky: Vec<(String, f64, f64)>,
    sky_table: Option<PathBuf>,
    standards: Option<PathBuf>,
    pointing_tol_arcsec: f64,
    max_gap_min: f64,
    bin: usize,
    fwhm: f64,
    aperture: f64,
    out: Option<PathBuf>,
) -> PyResult<String> {
    let mut opts = workflow::night::ScanOptions::new(&instrument, &products);
    opts.sky_fields = sky
        .into_iter()
        .map(|(target, p_percent, chi_deg)| workflow::night::SkyField { target, p_percent, chi_deg })
        .collect();
    if let Some(t) = &sky_table {
        opts.sky_fields.extend(workflow::night::SkyField::read_table(t).map_err(night_err)?);
    }
    opts.standards = standards;
    opts.pointing_tol_arcsec = pointing_tol_arcsec;
    opts.max_gap_min = max_gap_min;
    opts.bin_px = bin;
    opts.fwhm_px = fwhm;
    opts.aperture_px = aperture;
    let plan = py.detach(|| workflow::night::scan(&dirs, &opts)).map_err(night_err)?;
    if let Some(o) = &out {
        plan.write(o).map_err(night_err)?;
    }
    serde_json::to_string(&plan).map_err(|e| input_err(format!("the plan: {e}")))
}

/// Run a plan, given as JSON text or as a plan file (TOML, or JSON for a .json name;
/// `workflow::night::run::run`, what `instpol run` runs), with the `instpol` binary `program` as
/// the units' executor: the report as JSON text (`instpol run --json`'s keys but `provenance`).
/// A plan that cannot run (a cycle, a missing input, an unknown kind or unit, outputs over
/// inputs): InputError, nothing run.
#[pyfunction]
#[pyo3(signature = (plan_text, plan_path, jobs, only, dry_run, program))]
fn _run(
    py: Python<'_>,
    plan_text: Option<String>,
    plan_path: Option<PathBuf>,
    jobs: usize,
    only: Option<Vec<String>>,
    dry_run: bool,
    program: PathBuf,
) -> PyResult<String> {
    let plan: workflow::night::Plan = match (plan_text, plan_path) {
        (Some(t), _) => serde_json::from_str(&t).map_err(|e| input_err(format!("the plan is not a plan: {e}")))?,
        (None, Some(p)) => workflow::night::Plan::load(&p).map_err(|e| match e {
            workflow::night::Error::Input { .. } => FileError::new_err(e.to_string()),
            e => input_err(e),
        })?,
        (None, None) => return Err(input_err("no plan")),
    };
    if jobs == 0 {
        return Err(input_err("jobs = 0: run at least one unit at a time"));
    }
    if let Some(ids) = &only {
        for id in ids {
            plan.unit(id).map_err(night_err)?;
        }
    }
    let opts = workflow::night::RunOptions { jobs, only, dry_run };
    let exec = workflow::night::process_executor(program, plan.records.clone());
    let report = py.detach(|| workflow::night::run::run(&plan, &opts, &exec, &|_| {})).map_err(night_err)?;
    serde_json::to_string(&report).map_err(|e| input_err(format!("the report: {e}")))
}

#[pymodule]
fn _instpol(m: &Bound<'_, PyModule>) -> PyResult<()> {
    let py = m.py();
    m.add("InputError", py.get_type::<InputError>())?;
    m.add("FileError", py.get_type::<FileError>())?;
    m.add("__version__", env!("CARGO_PKG_VERSION"))?;
    m.add("__citation__", skyfield::provenance::citation())?;
    m.add_function(wrap_pyfunction!(_stokes, m)?)?;
    m.add_function(wrap_pyfunction!(_bias, m)?)?;
    m.add_function(wrap_pyfunction!(_reduce, m)?)?;
    m.add_function(wrap_pyfunction!(_catalog, m)?)?;
    m.add_function(wrap_pyfunction!(_calibrate_stars, m)?)?;
    m.add_function(wrap_pyfunction!(_demo, m)?)?;
    m.add_function(wrap_pyfunction!(_simulate, m)?)?;
    m.add_function(wrap_pyfunction!(_calibrate, m)?)?;
    m.add_function(wrap_pyfunction!(_scan, m)?)?;
    m.add_function(wrap_pyfunction!(_run, m)?)?;
    m.add_class::<_Calibration>()?;
    Ok(())
}

/// An unpaired source's reason as the catalog JSON writes it (`off_detector`, `no_partner`,
/// `lone_e`).
fn pythonize_why(w: skyfield::detect::Unpaired) -> String {
    serde_json::to_value(w).ok().and_then(|v| v.as_str().map(String::from)).unwrap_or_default()
}

/// What a catalog is (`skyfield::provenance::Product`), as `catalog()["product"]`.
fn product_dict<'py>(py: Python<'py>, p: &skyfield::provenance::Product) -> PyResult<Bound<'py, PyDict>> {
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
