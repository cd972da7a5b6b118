//! The one judge of whether a fit's data determine its parameters.
//!
//! Every linear solve of the crate and every Gauss-Newton step of [`crate::lsq`] asks
//! [`judge`] before it inverts: a failed inverse is no test (a matrix singular in exact
//! arithmetic is seldom singular in floating point, and stars on a tilted line gave a plane
//! with coefficients of +-2000 where the same stars on `y = 0` were refused), so the judge
//! looks at the singular values of the weighted design matrix (the Jacobian of the
//! standardized residuals), its columns first scaled to unit norm so that a parameter's unit
//! does not count. A smallest singular value below [`REL_TOL`] of the largest leaves a
//! direction of parameter space the data do not determine; the right singular vector of that
//! value says which parameters it moves, and the refusal ([`Undetermined`]) names them and the
//! input that would determine them (the caller's words: star layout, radii, parallactic-angle
//! coverage, plate-angle coverage, number of fields).

use nalgebra::DMatrix;

/// A smallest singular value of the column-scaled weighted design matrix below this fraction
/// of the largest is a parameter (combination) the data leave free.
pub const REL_TOL: f64 = 1e-10;

/// The data do not determine some parameter of a fit.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[error(
    "the data do not determine {free} (smallest singular value {ratio:.1e} of the largest, below {tol:.0e}): {remedy}"
)]
pub struct Undetermined {
    /// The parameter, or the combination of parameters, left free.
    pub free: String,
    /// The smallest singular value over the largest (0 for a parameter no datum touches).
    pub ratio: f64,
    /// The tolerance it fell below.
    pub tol: f64,
    /// What input would determine it.
    pub remedy: String,
}

/// A fit's words for the judge: its parameters' names and the input that determines them.
#[derive(Debug, Clone, PartialEq)]
pub struct Words {
    pub names: Vec<String>,
    pub remedy: String,
}

impl Words {
    pub fn new(names: Vec<String>, remedy: impl Into<String>) -> Self {
        Words { names, remedy: remedy.into() }
    }

    fn name(&self, k: usize) -> String {
        self.names.get(k).cloned().unwrap_or_else(|| format!("parameter {}", k + 1))
    }
}

/// The smallest over the largest singular value of `design` with its columns scaled to unit
/// norm, and the right singular vector of the smallest (a zero column is a parameter no datum
/// touches: ratio 0 and that parameter alone). `None` for a matrix with no rows or columns.
pub fn scaled_conditioning(design: &DMatrix<f64>) -> Option<(f64, Vec<f64>)> {
    let n = design.ncols();
    if n == 0 || design.nrows() == 0 {
        return None;
    }
    let mut d = design.clone();
    for (k, mut col) in d.column_iter_mut().enumerate() {
        let norm = col.norm();
        if !(norm > 0.0) || !norm.is_finite() {
            let mut v = vec![0.0; n];
            v[k] = 1.0;
            return Some((0.0, v));
        }
        col /= norm;
    }
    // Fewer rows than columns: the missing singular values are zeros, with no vector from a
    // thin SVD; the direction is any null vector, found from the full row space.
    if design.nrows() < n {
        return Some((0.0, null_direction(&d)));
    }
    let svd = d.svd(false, true);
    let v_t = svd.v_t?;
    let s = &svd.singular_values;
    let (mut kmin, mut max) = (0, 0.0f64);
    for (k, &x) in s.iter().enumerate() {
        max = max.max(x);
        if x < s[kmin] {
            kmin = k;
        }
    }
    let ratio = if max > 0.0 { s[kmin] / max } else { 0.0 };
    Some((ratio, v_t.row(kmin).iter().copied().collect()))
}

/// A unit vector orthogonal to every row of `d` (fewer rows than columns).
fn null_direction(d: &DMatrix<f64>) -> Vec<f64> {
    let n = d.ncols();
    let mut sq = DMatrix::<f64>::zeros(n, n);
    sq.view_mut((0, 0), (d.nrows(), n)).copy_from(d);
    let svd = sq.svd(false, true);
    let v_t = svd.v_t.unwrap_or_else(|| DMatrix::identity(n, n));
    let s = &svd.singular_values;
    let kmin = (0..n).min_by(|&a, &b| s[a].total_cmp(&s[b])).unwrap_or(0);
    v_t.row(kmin).iter().copied().collect()
}

/// The parameters a direction moves, in words: one name when one parameter carries it, else
/// the combination of those that carry a fifth of it or more.
fn describe(v: &[f64], words: &Words) -> String {
    let mut parts: Vec<(usize, f64)> = v.iter().map(|x| x.abs()).enumerate().collect();
    parts.sort_by(|a, b| b.1.total_cmp(&a.1));
    match parts.first() {
        None => "the parameters".into(),
        Some(&(k, x)) if x > 0.95 => words.name(k),
        _ => {
            let names: Vec<String> = parts.iter().filter(|(_, x)| *x >= 0.2).map(|(k, _)| words.name(*k)).collect();
            match names.split_last() {
                Some((last, first)) if !first.is_empty() => {
                    format!("a combination of {} and {last}", first.join(", "))
                }
                _ => names.concat(),
            }
        }
    }
}

/// Judge the weighted design matrix `design` (rows: standardized residuals, columns: the
/// parameters `words` names): `Err` naming the free parameter and the remedy when its scaled
/// conditioning ([`scaled_conditioning`]) is below [`REL_TOL`] or not a number.
pub fn judge(design: &DMatrix<f64>, words: &Words) -> Result<(), Undetermined> {
    if design.iter().any(|x| !x.is_finite()) {
        return Err(Undetermined {
            free: "the parameters (the fit's design matrix holds a value that is not finite)".into(),
            ratio: f64::NAN,
            tol: REL_TOL,
            remedy: words.remedy.clone(),
        });
    }
    let Some((ratio, v)) = scaled_conditioning(design) else {
        return Ok(());
    };
    if ratio >= REL_TOL {
        return Ok(());
    }
    Err(Undetermined { free: describe(&v, words), ratio, tol: REL_TOL, remedy: words.remedy.clone() })
}

/// The weak directions of a fit known by its normal matrix `normal = J^T W J` alone (the
/// Mueller field accumulates it from each datum's 2 x 2 weight): every eigenvector of the
/// matrix scaled to unit diagonal (the normal matrix of the column-scaled design) whose
/// eigenvalue is below `rel` times the largest. Those eigenvalues are the squares of the
/// scaled design's singular values, so `rel` here is [`REL_TOL`]'s square in kind; a fit
/// with a zero diagonal (a parameter no datum touches) must say so before asking.
pub fn weak_directions(normal: &DMatrix<f64>, rel: f64) -> Vec<Vec<f64>> {
    let n = normal.nrows();
    let d: Vec<f64> = (0..n).map(|i| normal[(i, i)].sqrt()).collect();
    let s = DMatrix::from_fn(n, n, |i, j| normal[(i, j)] / (d[i] * d[j]));
    let eig = s.symmetric_eigen();
    let mx = eig.eigenvalues.max();
    eig.eigenvalues
        .iter()
        .zip(eig.eigenvectors.column_iter())
        .filter(|(e, _)| **e < rel * mx)
        .map(|(_, v)| v.iter().copied().collect())
        .collect()
}

/// The weighted design matrix of a linear fit from its basis values per datum (`rows[i][k]`,
/// the k-th basis function at datum i) and each datum's weight (`1 / sigma^2` times a robust
/// weight): row i is `sqrt(w_i) rows[i]`.
pub fn weighted_design(rows: &DMatrix<f64>, weights: &[f64]) -> DMatrix<f64> {
    let mut d = rows.clone();
    for (i, w) in weights.iter().enumerate() {
        let s = w.max(0.0).sqrt();
        for x in d.row_mut(i).iter_mut() {
            *x *= s;
        }
    }
    d
}

#[cfg(test)]
mod tests {
    use super::*;

    fn words(n: usize) -> Words {
        Words::new((0..n).map(|k| format!("c{k}")).collect(), "spread the data")
    }

    /// A plane on points of a tilted line: `y = 0.5 x + 0.2` makes `c2 - 0.5 c1 - 0.2 c0`
    /// free (exactly, in real numbers; to rounding in floating point), which the judge names.
    #[test]
    fn a_tilted_line_leaves_a_plane_free() {
        let n = 40;
        let a = DMatrix::from_fn(n, 3, |i, k| {
            let x = -3.0 + 6.0 * i as f64 / (n - 1) as f64;
            [1.0, x, 0.5 * x + 0.2][k]
        });
        let e = judge(&a, &words(3)).unwrap_err();
        assert!(e.free.contains("c1") && e.free.contains("c2"), "{e}");
        assert!(e.ratio < 1e-12, "{e}");
        // The null vector of the scaled design is that combination: (-0.2, -0.5, 1) in the
        // unscaled parameters.
        let (_, v) = scaled_conditioning(&a).unwrap();
        let norms: Vec<f64> = a.column_iter().map(|c| c.norm()).collect();
        let u: Vec<f64> = v.iter().zip(&norms).map(|(x, s)| x / s).collect();
        assert!((u[0] / u[2] + 0.2).abs() < 1e-6 && (u[1] / u[2] + 0.5).abs() < 1e-6, "{u:?}");
    }

    /// A plane on a spread of points passes, a parameter no datum touches is named alone, and
    /// fewer data than parameters are refused.
    #[test]
    fn spread_points_pass_and_a_zero_column_is_named() {
        let a = DMatrix::from_fn(30, 3, |i, k| [1.0, (i % 6) as f64, (i / 6) as f64][k]);
        assert!(judge(&a, &words(3)).is_ok());
        let z = DMatrix::from_fn(30, 3, |i, k| [1.0, (i % 6) as f64, 0.0][k]);
        let e = judge(&z, &words(3)).unwrap_err();
        assert_eq!((e.free.as_str(), e.ratio), ("c2", 0.0));
        assert!(e.to_string().contains("spread the data"), "{e}");
        let short = DMatrix::from_fn(2, 3, |i, k| [1.0, i as f64, (i * i) as f64 + 0.5][k]);
        assert!(judge(&short, &words(3)).is_err());
        let nan = DMatrix::from_fn(4, 2, |i, k| if i == 2 && k == 1 { f64::NAN } else { (i + k) as f64 });
        assert!(judge(&nan, &words(2)).is_err());
    }

    /// The normal matrix's weak directions are the scaled design's: a plane on a tilted line
    /// has one, the combination the judge names; a plane on spread points none.
    #[test]
    fn weak_directions_of_a_normal_matrix() {
        let line = DMatrix::from_fn(40, 3, |i, k| {
            let x = -3.0 + 6.0 * i as f64 / 39.0;
            [1.0, x, 0.5 * x + 0.2][k]
        });
        let w = weak_directions(&(line.transpose() * &line), 1e-12);
        assert_eq!(w.len(), 1);
        let (_, v) = scaled_conditioning(&line).unwrap();
        let dot: f64 = w[0].iter().zip(&v).map(|(a, b)| a * b).sum();
        assert!((dot.abs() - 1.0).abs() < 1e-6, "{w:?} against {v:?}");
        let spread = DMatrix::from_fn(30, 3, |i, k| [1.0, (i % 6) as f64, (i / 6) as f64][k]);
        assert!(weak_directions(&(spread.transpose() * &spread), 1e-12).is_empty());
    }

    /// The weights scale rows by their square roots: the normal matrix of the weighted design
    /// is `A^T W A`.
    #[test]
    fn weighted_design_gives_the_weighted_normal_matrix() {
        let a = DMatrix::from_fn(5, 2, |i, k| [1.0, i as f64][k]);
        let w = [1.0, 4.0, 0.25, 9.0, 2.0];
        let d = weighted_design(&a, &w);
        let n = d.transpose() * &d;
        let want = a.transpose() * DMatrix::from_diagonal(&nalgebra::DVector::from_row_slice(&w)) * &a;
        assert!((n - want).abs().max() < 1e-12);
    }
}
