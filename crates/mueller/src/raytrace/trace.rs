//! The ray tracer proper: geometry, polarization ray-tracing matrices, pupil integration,
//! field profiles, fits and the wavelength law.

use super::Prescription;
use crate::analysis::jones_to_mueller;
use crate::fresnel::{Coefficients, C64};
use crate::thinfilm::{stack_unchecked, Layer};
use crate::{Error, Mueller};
use nalgebra::{DMatrix, DVector, Matrix2, Matrix3, Vector3};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

/// The paper's wavelength law (section `sec:cause`): `p(lambda) / p(550) = A + B lambda`.
pub const PAPER_LAW_A: f64 = 0.02;
/// Slope of the paper's wavelength law (per nm).
pub const PAPER_LAW_B: f64 = 1.73e-3;

#[derive(Debug, Clone)]
struct CSurf {
    name: String,
    z0: f64,
    curv: f64,
    conic: f64,
    semi_ap: f64,
    n_before: f64,
    n_after: f64,
    /// Layers in the order light meets them.
    layers: Vec<Layer>,
}

/// A prescription evaluated at one wavelength, ready to trace.
#[derive(Debug, Clone)]
pub struct Compiled {
    pub wavelength_nm: f64,
    pub field_radius_arcmin: f64,
    pub description: String,
    surfaces: Vec<CSurf>,
    focal_ratio: f64,
    scale_arcsec_per_mm: f64,
    exit_pupil_mm: Option<f64>,
    obstruction: f64,
}

/// One ray-surface intersection (reported to the visitor of [`Compiled::trace_ray`]).
#[derive(Debug, Clone, Copy)]
pub struct Intersection {
    pub surface: usize,
    /// Angle of incidence (rad).
    pub aoi: f64,
    /// Coefficients of the surface (with its coating) at that angle.
    pub coefficients: Coefficients,
    /// Whether the medium on both sides and every layer is lossless.
    pub lossless: bool,
}

/// Pupil sampling: `rings` Gauss-Legendre rings in `rho^2` times `spokes` equally spaced
/// azimuths.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Sampling {
    pub rings: usize,
    pub spokes: usize,
}

impl Sampling {
    /// The default pupil sampling: about 256 rays (8 rings x 32 spokes).
    pub const DEFAULT_RAYS: usize = 256;

    /// About `m` rays: `rings = round(sqrt(m / 4))`, `spokes = 4 rings`, so that the
    /// azimuthal spacing at mid-pupil matches the radial one.
    pub fn from_rays(m: usize) -> Self {
        let r = ((m as f64 / 4.0).sqrt().round() as usize).max(1);
        Self { rings: r, spokes: 4 * r }
    }

    /// Number of rays traced per field point.
    pub fn rays(&self) -> usize {
        self.rings * self.spokes
    }
}

impl Default for Sampling {
    fn default() -> Self {
        Self::from_rays(Self::DEFAULT_RAYS)
    }
}

/// Gauss-Legendre nodes and weights on [0, 1] (weights sum to 1).
fn gauss_legendre01(n: usize) -> Vec<(f64, f64)> {
    let mut out = Vec::with_capacity(n);
    for i in 0..n {
        let mut z = (std::f64::consts::PI * (i as f64 + 0.75) / (n as f64 + 0.5)).cos();
        let mut pp = 1.0;
        for _ in 0..100 {
            let (mut p1, mut p2) = (1.0, 0.0);
            for j in 1..=n {
                let p3 = p2;
                p2 = p1;
                p1 = ((2.0 * j as f64 - 1.0) * z * p2 - (j as f64 - 1.0) * p3) / j as f64;
            }
            pp = n as f64 * (z * p1 - p2) / (z * z - 1.0);
            let dz = p1 / pp;
            z -= dz;
            if dz.abs() < 1e-15 {
                break;
            }
        }
        out.push((0.5 * (1.0 + z), 1.0 / ((1.0 - z * z) * pp * pp)));
    }
    out
}

/// Transverse basis of a ray: the global x, y axes carried by the minimal rotation of `z`
/// onto `k` (valid for rays going forward, `k_z > -1`).
fn basis(k: &Vector3<f64>) -> (Vector3<f64>, Vector3<f64>) {
    let f = 1.0 / (1.0 + k.z);
    (Vector3::new(1.0 - k.x * k.x * f, -k.x * k.y * f, -k.x), Vector3::new(-k.x * k.y * f, 1.0 - k.y * k.y * f, -k.y))
}

fn outer(a: &Vector3<f64>, b: &Vector3<f64>, t: C64) -> Matrix3<C64> {
    Matrix3::from_fn(|i, j| t * (a[i] * b[j]))
}

/// The instrumental polarization of one field point.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FieldPoint {
    pub x_arcmin: f64,
    pub y_arcmin: f64,
    pub r_arcmin: f64,
    /// Polar angle of the field point (rad).
    pub alpha: f64,
    /// Pupil-averaged Mueller matrix (normalized to the traced pupil area).
    pub mueller: Mueller,
    /// Polarization given to unpolarized light (fraction).
    pub p: f64,
    /// Its angle (rad, in [0, pi)).
    pub phi: f64,
    pub rays_traced: usize,
    pub rays_lost: usize,
}

impl FieldPoint {
    fn from_mueller(x: f64, y: f64, m: Mueller, traced: usize, lost: usize) -> Self {
        let p = m[(1, 0)].hypot(m[(2, 0)]) / m[(0, 0)];
        let phi = crate::fold_pi(0.5 * m[(2, 0)].atan2(m[(1, 0)]));
        Self {
            x_arcmin: x,
            y_arcmin: y,
            r_arcmin: x.hypot(y),
            alpha: y.atan2(x),
            mueller: m,
            p,
            phi,
            rays_traced: traced,
            rays_lost: lost,
        }
    }

    /// `phi - alpha` wrapped to (-pi/2, pi/2]: 0 for a radial pattern.
    pub fn phi_rel(&self) -> f64 {
        let d = (self.phi - self.alpha).rem_euclid(std::f64::consts::PI);
        if d > std::f64::consts::FRAC_PI_2 {
            d - std::f64::consts::PI
        } else {
            d
        }
    }
}

impl Compiled {
    pub(super) fn new(p: &Prescription, lam: f64) -> Result<Self, Error> {
        let mut z = p.first_surface_distance_mm;
        let mut n_before = 1.0;
        let mut surfaces = Vec::with_capacity(p.surfaces.len());
        for (i, s) in p.surfaces.iter().enumerate() {
            let n_after = p.dispersion(&s.glass)?.index(lam);
            let air_glass = (n_before == 1.0) != (n_after == 1.0);
            let coating = match &s.coating {
                Some(c) => Some(c),
                None if air_glass => p.default_coating.as_ref(),
                None => None,
            };
            let mut layers = match coating {
                Some(c) => p
                    .layers(c, lam)
                    .map_err(|e| super::invalid(format!("optics.surfaces[{i}].coating"), e.to_string()))?,
                None => Vec::new(),
            };
            // Listed from the air side: light leaving the glass meets them in reverse.
            if n_after == 1.0 && n_before != 1.0 {
                layers.reverse();
            }
            surfaces.push(CSurf {
                name: if s.name.is_empty() { format!("S{}", i + 1) } else { s.name.clone() },
                z0: z,
                curv: s.radius_mm.map_or(0.0, |r| 1.0 / r),
                conic: s.conic,
                semi_ap: 0.5 * s.clear_aperture_mm,
                n_before,
                n_after,
                layers,
            });
            z += s.thickness_mm;
            n_before = n_after;
        }
        Ok(Self {
            wavelength_nm: lam,
            field_radius_arcmin: p.field_radius_arcmin,
            description: p.description.clone(),
            surfaces,
            focal_ratio: p.focal_ratio,
            scale_arcsec_per_mm: p.field_scale_arcsec_per_mm,
            exit_pupil_mm: p.exit_pupil_distance_mm,
            obstruction: p.central_obstruction,
        })
    }

    /// Number of surfaces.
    pub fn surface_count(&self) -> usize {
        self.surfaces.len()
    }

    /// Name of surface `i` (its `name`, or `S<i+1>`).
    pub fn surface_name(&self, i: usize) -> &str {
        &self.surfaces[i].name
    }

    /// Trace one ray from `origin` along `dir` through every surface. Only surface `only`
    /// (if given) polarizes: the others refract without Fresnel losses. `visit` sees every
    /// intersection. Returns the flux-normalized Jones matrix in the transverse bases of the
    /// entering and leaving rays and the leaving direction, or `None` if the ray misses a
    /// surface, falls outside a clear aperture or is totally reflected.
    pub fn trace_ray(
        &self,
        origin: Vector3<f64>,
        dir: Vector3<f64>,
        only: Option<usize>,
        mut visit: impl FnMut(&Intersection),
    ) -> Option<(Matrix2<C64>, Vector3<f64>)> {
        let d0 = dir.normalize();
        let (mut p, mut k) = (origin, d0);
        let one = C64::new(1.0, 0.0);
        let mut prt = Matrix3::<C64>::identity();
        for (i, s) in self.surfaces.iter().enumerate() {
            let rel = p - Vector3::new(0.0, 0.0, s.z0);
            let t = if s.curv == 0.0 {
                -rel.z / k.z
            } else {
                // c (x^2 + y^2 + (1 + K) z^2) - 2 z = 0 along the ray: a t^2 + 2 b t + cc = 0.
                // Both roots in the cancellation-free form; keep the nearest forward one on
                // the vertex branch of the conic (1 - c (1 + K) z > 0).
                let (c, kk) = (s.curv, 1.0 + s.conic);
                let a = c * (k.x * k.x + k.y * k.y + kk * k.z * k.z);
                let b = c * (rel.x * k.x + rel.y * k.y + kk * rel.z * k.z) - k.z;
                let cc = c * (rel.x * rel.x + rel.y * rel.y + kk * rel.z * rel.z) - 2.0 * rel.z;
                let disc = b * b - a * cc;
                if disc < 0.0 {
                    return None;
                }
                let q = -(b + if b >= 0.0 { 1.0 } else { -1.0 } * disc.sqrt());
                let ok = |t: f64| t.is_finite() && t >= 0.0 && 1.0 - c * kk * (rel.z + t * k.z) > 0.0;
                match (q / a, cc / q) {
                    (t1, t2) if ok(t1) && ok(t2) => t1.min(t2),
                    (t1, _) if ok(t1) => t1,
                    (_, t2) if ok(t2) => t2,
                    _ => return None,
                }
            };
            if !(t.is_finite() && t >= 0.0) {
                return None;
            }
            p += t * k;
            if p.x * p.x + p.y * p.y > s.semi_ap * s.semi_ap {
                return None;
            }
            let mut n = if s.curv == 0.0 {
                Vector3::z()
            } else {
                let zr = p.z - s.z0;
                Vector3::new(s.curv * p.x, s.curv * p.y, s.curv * (1.0 + s.conic) * zr - 1.0).normalize()
            };
            if n.dot(&k) < 0.0 {
                n = -n;
            }
            let cos_i = n.dot(&k).min(1.0);
            let sin_i = (1.0 - cos_i * cos_i).max(0.0).sqrt();
            let mu = s.n_before / s.n_after;
            let sin2_t = mu * mu * (1.0 - cos_i * cos_i);
            if sin2_t >= 1.0 {
                return None;
            }
            let cos_t = (1.0 - sin2_t).sqrt();
            let k2 = (mu * k + (cos_t - mu * cos_i) * n).normalize();
            let active = only.is_none_or(|o| o == i);
            let (ts, tp) = if active {
                let c = stack_unchecked(
                    s.n_before,
                    &s.layers,
                    C64::new(s.n_after, 0.0),
                    self.wavelength_nm,
                    cos_i,
                    s.n_before * sin_i,
                );
                visit(&Intersection {
                    surface: i,
                    aoi: cos_i.acos(),
                    coefficients: c,
                    lossless: s.layers.iter().all(|l| l.n.im == 0.0),
                });
                (c.t_s_flux, c.t_p_flux)
            } else {
                (one, one)
            };
            // Local s/p basis: (p, s, k) right-handed for the incident and refracted rays.
            let sv = k.cross(&n);
            let sn = sv.norm();
            let s_hat = if sn > 1e-14 {
                sv / sn
            } else {
                let (x, _) = basis(&k);
                x.normalize()
            };
            let p_in = s_hat.cross(&k);
            let p_out = s_hat.cross(&k2);
            let pm = outer(&s_hat, &s_hat, ts) + outer(&p_out, &p_in, tp) + outer(&k2, &k, one);
            prt = pm * prt;
            k = k2;
        }
        let (xi, yi) = basis(&d0);
        let (xo, yo) = basis(&k);
        let proj = |a: &Vector3<f64>, b: &Vector3<f64>| {
            let pb = prt * b.map(|v| C64::new(v, 0.0));
            a.x * pb.x + a.y * pb.y + a.z * pb.z
        };
        Some((Matrix2::new(proj(&xo, &xi), proj(&xo, &yi), proj(&yo, &xi), proj(&yo, &yi)), k))
    }

    /// Field position (arcmin) to focal-plane position (mm).
    fn object(&self, x_arcmin: f64, y_arcmin: f64) -> Vector3<f64> {
        let s = 60.0 / self.scale_arcsec_per_mm;
        Vector3::new(x_arcmin * s, y_arcmin * s, 0.0)
    }

    /// Direction of the ray from the field point through pupil point `(rho, psi)` (rho in
    /// units of the pupil radius).
    fn ray_dir(&self, obj: &Vector3<f64>, rho: f64, psi: f64) -> Vector3<f64> {
        let (s, c) = psi.sin_cos();
        match self.exit_pupil_mm {
            Some(l) => {
                let a = l / (2.0 * self.focal_ratio);
                (obj - Vector3::new(rho * a * c, rho * a * s, -l)).normalize()
            }
            None => {
                let u = 1.0 / (2.0 * self.focal_ratio);
                Vector3::new(-rho * u * c, -rho * u * s, 1.0).normalize()
            }
        }
    }

    /// The chief ray alone at field point `(x, y)` arcmin.
    pub fn chief_ray(&self, x_arcmin: f64, y_arcmin: f64, only: Option<usize>) -> Result<FieldPoint, Error> {
        let obj = self.object(x_arcmin, y_arcmin);
        let (j, _) = self.trace_ray(obj, self.ray_dir(&obj, 0.0, 0.0), only, |_| {}).ok_or_else(|| {
            super::invalid(format!("field point ({x_arcmin}, {y_arcmin}) arcmin"), "the chief ray is vignetted")
        })?;
        Ok(FieldPoint::from_mueller(x_arcmin, y_arcmin, jones_to_mueller(&j), 1, 0))
    }

    /// The pupil-averaged Mueller matrix and polarization at field point `(x, y)` arcmin.
    pub fn field_point(
        &self,
        x_arcmin: f64,
        y_arcmin: f64,
        sampling: &Sampling,
        only: Option<usize>,
    ) -> Result<FieldPoint, Error> {
        let obj = self.object(x_arcmin, y_arcmin);
        let e2 = self.obstruction * self.obstruction;
        let mut m = Mueller::zeros();
        let (mut traced, mut lost) = (0, 0);
        let dpsi = 2.0 * std::f64::consts::PI / sampling.spokes as f64;
        for (u, w) in gauss_legendre01(sampling.rings) {
            let rho = (e2 + (1.0 - e2) * u).sqrt();
            for j in 0..sampling.spokes {
                let psi = (j as f64 + 0.5) * dpsi;
                match self.trace_ray(obj, self.ray_dir(&obj, rho, psi), only, |_| {}) {
                    Some((jm, _)) => {
                        m += jones_to_mueller(&jm) * (w / sampling.spokes as f64);
                        traced += 1;
                    }
                    None => lost += 1,
                }
            }
        }
        if traced == 0 {
            return Err(super::invalid(
                format!("field point ({x_arcmin}, {y_arcmin}) arcmin"),
                "every ray is vignetted (outside a clear aperture or totally reflected)",
            ));
        }
        Ok(FieldPoint::from_mueller(x_arcmin, y_arcmin, m, traced, lost))
    }

    /// Field points at `radii` (arcmin) along polar angle `alpha` (rad), in parallel.
    pub fn profile(
        &self,
        radii: &[f64],
        alpha: f64,
        sampling: &Sampling,
        only: Option<usize>,
    ) -> Result<Vec<FieldPoint>, Error> {
        let (s, c) = alpha.sin_cos();
        radii.par_iter().map(|&r| self.field_point(r * c, r * s, sampling, only)).collect()
    }

    /// Polarization at field point `(x, y)` made by each surface alone (the others refract
    /// without Fresnel losses), in parallel over the surfaces.
    pub fn per_surface(&self, x_arcmin: f64, y_arcmin: f64, sampling: &Sampling) -> Result<Vec<FieldPoint>, Error> {
        (0..self.surfaces.len())
            .into_par_iter()
            .map(|i| self.field_point(x_arcmin, y_arcmin, sampling, Some(i)))
            .collect()
    }
}

/// A radial polynomial `p(r) = sum c_k r^(powers_k)`, r in arcmin.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Polynomial {
    pub powers: Vec<i32>,
    pub coefficients: Vec<f64>,
}

impl Polynomial {
    /// Evaluate at `r` (arcmin).
    pub fn eval(&self, r: f64) -> f64 {
        self.powers.iter().zip(&self.coefficients).map(|(&k, &c)| c * r.powi(k)).sum()
    }
}

/// Least-squares fit of `p(r) = sum c_k r^(powers_k)` (e.g. powers 1, 2, 3: the paper's form
/// in section `sec:fors1`).
pub fn fit_radial(r: &[f64], p: &[f64], powers: &[i32]) -> Result<Polynomial, Error> {
    if r.len() != p.len() || r.len() < powers.len() || powers.is_empty() {
        return Err(super::invalid("radial fit", format!("{} points for {} terms", r.len(), powers.len())));
    }
    let a = DMatrix::from_fn(r.len(), powers.len(), |i, j| r[i].powi(powers[j]));
    let b = DVector::from_column_slice(p);
    let c = a.svd(true, true).solve(&b, 1e-14).map_err(|e| super::invalid("radial fit", e.to_string()))?;
    Ok(Polynomial { powers: powers.to_vec(), coefficients: c.iter().copied().collect() })
}

/// The wavelength dependence of the field polarization at one radius:
/// `p(lambda) / p(550 nm) ~ a + b lambda` (lambda in nm), as the paper's section `sec:cause`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct WavelengthLaw {
    pub a: f64,
    pub b: f64,
    pub radius_arcmin: f64,
    /// `(lambda_nm, p(lambda) / p(550))` samples used in the fit.
    pub samples: Vec<(f64, f64)>,
}

impl WavelengthLaw {
    /// `a + b lambda`.
    pub fn eval(&self, lambda_nm: f64) -> f64 {
        self.a + self.b * lambda_nm
    }
}

impl Prescription {
    /// `p(lambda) / p(550)` at radius `r_arcmin` (along the x axis) for each wavelength, and
    /// its straight-line fit; wavelengths are traced in parallel.
    pub fn wavelength_law(&self, r_arcmin: f64, sampling: &Sampling, lambdas: &[f64]) -> Result<WavelengthLaw, Error> {
        if lambdas.len() < 2 {
            return Err(super::invalid("wavelength law", "need at least two wavelengths"));
        }
        let p = |l: f64| -> Result<f64, Error> { Ok(self.compile(l)?.field_point(r_arcmin, 0.0, sampling, None)?.p) };
        let p550 = p(550.0)?;
        if p550 <= 0.0 {
            return Err(super::invalid("wavelength law", format!("p(550 nm) = {p550} at r = {r_arcmin} arcmin")));
        }
        let ratios: Vec<f64> = lambdas.par_iter().map(|&l| Ok(p(l)? / p550)).collect::<Result<_, Error>>()?;
        let fit = fit_radial(lambdas, &ratios, &[0, 1])?;
        Ok(WavelengthLaw {
            a: fit.coefficients[0],
            b: fit.coefficients[1],
            radius_arcmin: r_arcmin,
            samples: lambdas.iter().copied().zip(ratios).collect(),
        })
    }
}

/// A rotationally symmetric instrumental-polarization field (format `instpol-field-v1`,
/// documented in the module docs).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct FieldFile {
    pub format: String,
    pub source: String,
    pub wavelength_nm: f64,
    pub radius_arcmin: Vec<f64>,
    pub p: Vec<f64>,
    pub phi_rel_deg: Vec<f64>,
    pub polynomial: Polynomial,
}

impl FieldFile {
    /// The format tag.
    pub const FORMAT: &'static str = "instpol-field-v1";

    /// From a radial profile (points in increasing radius) and its polynomial fit.
    pub fn new(source: &str, wavelength_nm: f64, points: &[FieldPoint], polynomial: Polynomial) -> Self {
        Self {
            format: Self::FORMAT.into(),
            source: source.into(),
            wavelength_nm,
            radius_arcmin: points.iter().map(|p| p.r_arcmin).collect(),
            p: points.iter().map(|p| p.p).collect(),
            phi_rel_deg: points.iter().map(|p| if p.p > 0.0 { p.phi_rel().to_degrees() } else { 0.0 }).collect(),
            polynomial,
        }
    }

    /// `(p, phi)` at field position `(x, y)` arcmin: `p` interpolated linearly in radius
    /// (clamped at the ends), `phi` radial plus the tabulated offset.
    pub fn eval(&self, x: f64, y: f64) -> (f64, f64) {
        let r = x.hypot(y);
        let rr = &self.radius_arcmin;
        let i = rr.partition_point(|&v| v <= r).clamp(1, rr.len().max(2) - 1);
        let (p, off) = if rr.len() < 2 {
            (self.p.first().copied().unwrap_or(0.0), 0.0)
        } else {
            let f = ((r - rr[i - 1]) / (rr[i] - rr[i - 1])).clamp(0.0, 1.0);
            (
                self.p[i - 1] + f * (self.p[i] - self.p[i - 1]),
                self.phi_rel_deg[i - 1] + f * (self.phi_rel_deg[i] - self.phi_rel_deg[i - 1]),
            )
        };
        (p, crate::fold_pi(y.atan2(x) + off.to_radians()))
    }
}
