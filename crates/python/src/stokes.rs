//! One source's dual-beam reduction (`instpol.stokes`, as `instpol stokes`) and the bias
//! correction of `P` (`instpol.bias`, as `instpol bias`).

use crate::convert::*;
use crate::errors::*;
use numpy::prelude::*;
use numpy::{PyReadonlyArray1, PyReadonlyArray2};
use pyo3::prelude::*;
use pyo3::types::PyDict;
use rayon::prelude::*;
use stokes::stats::{Estimator, IntervalKind};

/// Dual-beam reduction of `m` stars measured at the same `n` HWP angles (`eq:F`, `eq:Q`,
/// `eq:U`, `eq:sigp`, `eq:sigchi`, `eq:fourcoeff`, `eq:a0`, `eq:kappa2`): `f_o`, `f_e` (and the
/// optional per-beam errors) are `(m, n)`. `single`: one star (errors name no star).
#[pyfunction]
#[pyo3(signature = (hwp_deg, f_o, f_e, sigma_o, sigma_e, kappa, angles_in_radians, single))]
#[allow(clippy::too_many_arguments)]
pub(crate) fn _stokes<'py>(
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
pub(crate) type Star = (stokes::Reduction, Option<stokes::repeats::Combined>);

/// Each star's row of `f_o`, `f_e` (and of the per-beam errors) reduced at the plate angles
/// `theta` (rad) (`m` stars), repeated exposures combined and kappa corrected as `instpol stokes` does;
/// the first failure is the error (naming its star unless `single`).
pub(crate) fn reduce_stars(
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
                // The one composition of instpol stokes (stokes::repeats::reduce_repeated):
                // repeats combined, the measurement, kappa, the reduction.
                let kappa = kappa.map_or(stokes::KappaCorrection::None, stokes::KappaCorrection::Known);
                let sigma = errs.as_ref().map(|(a, b)| (&a[..], &b[..]));
                match stokes::repeats::reduce_repeated(theta, &o, &e, sigma, kappa) {
                    Ok(r) => Ok((r.reduction, r.combined)),
                    Err(stokes::repeats::RepeatedError::Combine(e)) => Err(match e {
                        stokes::Error::NegativeCount { index } => format!("column {index} of f_o, f_e: {e}"),
                        e => e.to_string(),
                    }),
                    Err(stokes::repeats::RepeatedError::Reduce {
                        error: e @ stokes::Error::KappaOutOfRange(_),
                        ..
                    }) => Err(format!("kappa: {e}")),
                    Err(stokes::repeats::RepeatedError::Reduce { error, .. }) => Err(error.to_string()),
                }
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
pub(crate) fn reductions_dict<'py>(
    py: Python<'py>,
    red: &[stokes::Reduction],
    n: usize,
) -> PyResult<Bound<'py, PyDict>> {
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
pub(crate) fn exposures_dict<'py>(
    py: Python<'py>,
    repeats: &[Option<stokes::repeats::Combined>],
    hwp: &[f64],
) -> PyResult<Option<Bound<'py, PyDict>>> {
    let (m, n_in) = (repeats.len(), hwp.len());
    if repeats.is_empty() || repeats.iter().any(|c| c.is_none()) {
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
pub(crate) fn _bias<'py>(
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
