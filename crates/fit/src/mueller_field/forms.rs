//! The forms a Mueller field's free parameters take over the field besides the joint 2-D
//! polynomial ([`Smooth`]): the radial family (spin pairs about the optical axis, one
//! [`RadialModel`] each) and the natural-neighbour interpolant of per-bin fits
//! ([`ResidualMap`]). How they are built from per-bin fits, and why, is in
//! [`crate::mueller_field::smooth`]; this module only holds and evaluates them.

use crate::models::radial::RadialModel;
use crate::models::residual::{ResidualMap, ResidualPoint};
use crate::mueller_field::block::Kind;
use crate::{Error, Result};
use serde::{Deserialize, Serialize};

/// How the free parameters vary over the field.
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
pub enum Smooth {
    /// Each parameter a 2-D polynomial of degree `deg` in `x / scale`, `y / scale` (the joint fit).
    #[default]
    Poly,
    /// The radial family (module docs).
    Radial(RadialForm),
    /// The natural-neighbour interpolant of the per-bin fits (module docs).
    Interp(InterpForm),
}

impl Smooth {
    /// The form as a vocabulary word: `poly`, `radial`, `interp` (CLI `--smooth`, JSON
    /// `smooth`, the calibration file's `MU SMOOTH` in upper case).
    pub fn name(&self) -> &'static str {
        match self {
            Smooth::Poly => "poly",
            Smooth::Radial(_) => "radial",
            Smooth::Interp(_) => "interp",
        }
    }
}

/// One spin pair of free parameters fitted by the radial model.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct RadialPair {
    /// Index of the pair's first parameter in the kind's full vector (0: diattenuation,
    /// 2: retardance vector).
    pub param: usize,
    pub model: RadialModel,
}

impl RadialPair {
    /// 2 for the diattenuation, 4 for the retardance vector (module docs).
    pub fn spin(&self) -> u32 {
        if self.param == 2 {
            4
        } else {
            2
        }
    }

    /// The pair's values and their covariance `[var_a, cov_ab, var_b]` at `(x, y)` arcmin.
    pub fn eval(&self, x: f64, y: f64) -> ([f64; 2], [f64; 3]) {
        use field::FieldModel;
        let (xe, ye) = if self.spin() == 4 { double_angle(x, y) } else { (x, y) };
        let v = self.model.eval(xe, ye);
        ([v.q, v.u], [v.var_q, v.cov_qu, v.var_u])
    }
}

/// The position at twice the polar angle about the origin, the same radius.
pub(crate) fn double_angle(x: f64, y: f64) -> (f64, f64) {
    let r = x.hypot(y);
    if r < 1e-12 {
        return (x, y);
    }
    ((x * x - y * y) / r, 2.0 * x * y / r)
}

/// The radial form: one radial model per spin pair.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct RadialForm {
    pub pairs: Vec<RadialPair>,
}

/// The pairs of the full parameter vector a radial form describes, or why there are none.
pub fn radial_pairs(kind: Kind) -> std::result::Result<Vec<usize>, String> {
    match kind {
        Kind::Physical { retardance, rotation: false, depolarization: false } => {
            Ok(if retardance { vec![0, 2] } else { vec![0] })
        }
        _ => Err(format!(
            "the radial form describes the diattenuation and the retardance (spin pairs about the optical axis); the {} model ({}) has parameters without a radial pattern: use the poly or interp form",
            kind.model_name(),
            kind.free_words().join(", ")
        )),
    }
}

impl RadialForm {
    /// The pair parameters and `[var_a, cov_ab, var_b]` of every pair, in the order of the
    /// kind's free parameters (the pairs are its consecutive free parameters).
    pub fn params_at(&self, x: f64, y: f64) -> (Vec<f64>, Vec<f64>) {
        let nf = 2 * self.pairs.len();
        let mut vals = vec![0.0; nf];
        let mut cov = vec![0.0; nf * nf];
        for (k, pr) in self.pairs.iter().enumerate() {
            let (v, c) = pr.eval(x, y);
            let (a, b) = (2 * k, 2 * k + 1);
            vals[a] = v[0];
            vals[b] = v[1];
            cov[a * nf + a] = c[0];
            cov[a * nf + b] = c[1];
            cov[b * nf + a] = c[1];
            cov[b * nf + b] = c[2];
        }
        (vals, cov)
    }
}

/// One per-bin fit as the interpolant stores it: position, free parameters, their covariance.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct InterpPoint {
    pub x: f64,
    pub y: f64,
    pub vals: Vec<f64>,
    /// `n_free x n_free`, row-major.
    pub cov: Vec<f64>,
}

/// The interpolant: the per-bin points and their natural-neighbour maps (rebuilt on reading).
#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(try_from = "Vec<InterpPoint>", into = "Vec<InterpPoint>")]
pub struct InterpForm {
    points: Vec<InterpPoint>,
    /// Channel `c` is map `c / 2`, component `c % 2`; channels are the values, then the upper
    /// triangle of the covariance row by row.
    maps: Vec<ResidualMap>,
    nf: usize,
}

impl PartialEq for InterpForm {
    fn eq(&self, other: &Self) -> bool {
        self.points == other.points
    }
}

impl From<InterpForm> for Vec<InterpPoint> {
    fn from(f: InterpForm) -> Self {
        f.points
    }
}

impl TryFrom<Vec<InterpPoint>> for InterpForm {
    type Error = Error;
    fn try_from(points: Vec<InterpPoint>) -> Result<Self> {
        InterpForm::new(points)
    }
}

impl InterpForm {
    /// Triangulate the points (>= 3 not on one line, each with `n` values and an `n x n`
    /// covariance).
    pub fn new(points: Vec<InterpPoint>) -> Result<Self> {
        let nf = points.first().map(|p| p.vals.len()).unwrap_or(0);
        if points.iter().any(|p| p.vals.len() != nf || p.cov.len() != nf * nf) {
            return Err(Error::Input("interpolant points of different parameter counts".into()));
        }
        // Per point: its values, then the upper triangle of its covariance row by row.
        let channels: Vec<Vec<f64>> = points
            .iter()
            .map(|p| {
                let mut c = p.vals.clone();
                for k in 0..nf {
                    c.extend_from_slice(&p.cov[k * nf + k..(k + 1) * nf]);
                }
                c
            })
            .collect();
        let nc = nf + nf * (nf + 1) / 2;
        let mut maps = Vec::new();
        for c in (0..nc).step_by(2) {
            let pts = points
                .iter()
                .zip(&channels)
                .map(|(p, ch)| ResidualPoint { x: p.x, y: p.y, dq: ch[c], du: ch.get(c + 1).copied().unwrap_or(0.0) })
                .collect();
            let m = ResidualMap::new(pts)?;
            if m.points().len() != points.len() {
                return Err(Error::Input("interpolant points with non-finite positions or values".into()));
            }
            maps.push(m);
        }
        Ok(Self { points, maps, nf })
    }

    /// The per-bin points.
    pub fn points(&self) -> &[InterpPoint] {
        &self.points
    }

    /// The interpolated parameters and covariance; `None` outside the hull of the bins.
    pub fn params_at(&self, x: f64, y: f64) -> Option<(Vec<f64>, Vec<f64>)> {
        let mut ch = Vec::with_capacity(2 * self.maps.len());
        for m in &self.maps {
            let (a, b) = m.eval(x, y)?;
            ch.push(a);
            ch.push(b);
        }
        let nf = self.nf;
        let vals = ch[..nf].to_vec();
        let mut cov = vec![0.0; nf * nf];
        let mut c = nf;
        for k in 0..nf {
            for l in k..nf {
                cov[k * nf + l] = ch[c];
                cov[l * nf + k] = ch[c];
                c += 1;
            }
        }
        Some((vals, cov))
    }
}

/// The radial form of given coefficients (parameter-major as [`MuellerField::coeffs`](crate::mueller_field::MuellerField::coeffs) of a
/// radial form: the pairs of [`radial_pairs`], powers `1..=deg` each) and their covariance:
/// what a calibration file holds.
pub fn radial_form_of(kind: Kind, deg: usize, coeffs: &[f64], cov: &[f64]) -> std::result::Result<RadialForm, String> {
    let pairs = radial_pairs(kind)?;
    let n = coeffs.len();
    if n != pairs.len() * deg || cov.len() != n * n {
        return Err(format!("{n} coefficients for {} radial pairs of degree {deg}", pairs.len()));
    }
    let mut out = Vec::new();
    for (k, &param) in pairs.iter().enumerate() {
        let o = k * deg;
        let mut m = RadialModel::new(1, coeffs[o..o + deg].to_vec(), [0.0, 0.0]);
        let np = m.n_params();
        for i in 0..deg {
            for j in 0..deg {
                m.cov[i * np + j] = cov[(o + i) * n + o + j];
            }
        }
        out.push(RadialPair { param, model: m });
    }
    Ok(RadialForm { pairs: out })
}

/// `(PARAM, PX, PY)` of each coefficient of a radial form (the calibration file's MUELLER
/// rows): the pair's first parameter, the power of `r`, 0.
pub fn radial_rows(kind: Kind, deg: usize) -> std::result::Result<Vec<(usize, usize, usize)>, String> {
    Ok(radial_pairs(kind)?.into_iter().flat_map(|p| (1..=deg).map(move |k| (p, k, 0))).collect())
}
