//! Polarimetric standard stars and the validation of a calibration on one of them.
//!
//! The list ships as data (`instruments/standards.toml`, built in; another file can be loaded by
//! path): unpolarized and polarized standards with their published `P`, `chi` per band and the
//! source of every number. [`validate_star`] compares a star measured at a field position with
//! what the calibration predicts there, the way section `sec:fors1` checks the V map with an
//! unpolarized star in the lower-right corner.

use crate::correction::correct::{self, CorrectOptions, Corrector, Measurement};
use crate::models::model::FieldModel;
use mueller::Qu;
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};

/// Errors of the standard-star list and the validation; each names the file, star or band.
#[derive(Debug, thiserror::Error)]
pub enum Error {
    #[error("cannot read standard-star file {path}: {source}")]
    Io { path: PathBuf, source: std::io::Error },
    #[error("standard-star file {path}: {message}")]
    Parse { path: PathBuf, message: String },
    #[error("standard-star file {path}: star '{star}' band {band}: {why}")]
    Invalid { path: PathBuf, star: String, band: String, why: String },
    #[error("no standard star '{name}' in the list (known: {known})")]
    UnknownStar { name: String, known: String },
    #[error("standard star '{star}' has no published value in band '{band}' (bands: {known})")]
    UnknownBand { star: String, band: String, known: String },
    #[error("the combined covariance of measurement and prediction is singular (all errors zero?): cannot express the residual in sigma")]
    SingularCovariance,
    #[error(transparent)]
    Correct(#[from] correct::Error),
}

/// Unpolarized (null) or polarized standard.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Kind {
    Unpolarized,
    Polarized,
}

/// A published value in one band.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct BandValue {
    pub band: String,
    /// Polarization degree (percent, as published) and its 1-sigma error.
    pub p_percent: f64,
    pub sigma_p_percent: f64,
    /// Polarization angle (deg, [0, 180)) and its error; absent for null standards.
    #[serde(default)]
    pub chi_deg: Option<f64>,
    #[serde(default)]
    pub sigma_chi_deg: Option<f64>,
    /// Where the numbers come from.
    pub source: String,
}

/// One standard star.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Star {
    pub name: String,
    #[serde(default)]
    pub aliases: Vec<String>,
    pub kind: Kind,
    /// J2000 coordinates as published (sexagesimal strings), when given.
    #[serde(default)]
    pub ra: Option<String>,
    #[serde(default)]
    pub dec: Option<String>,
    #[serde(rename = "band")]
    pub bands: Vec<BandValue>,
}

/// The list of standards.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Standards {
    #[serde(rename = "star")]
    pub stars: Vec<Star>,
}

/// What a standard is expected to be, intrinsically, in one band: normalized `(q, u)` with a
/// covariance (fractions); an unpolarized star is [`Qu::ZERO`].
pub type Expected = Qu;

/// How many sigma `got` lies from the `expected` polarization: the Mahalanobis distance with
/// both covariances summed (the `*_residual_sigma` of [`validate_star`] and of the telescope
/// chain's validation).
pub(crate) fn sigma_from(expected: &Qu, got: &Qu) -> Result<f64, Error> {
    mahalanobis(
        got.q - expected.q,
        got.u - expected.u,
        got.var_q + expected.var_q,
        got.var_u + expected.var_u,
        got.cov_qu + expected.cov_qu,
    )
}

const BUILTIN: &str = include_str!("../../../instruments/standards.toml");

fn norm(s: &str) -> String {
    s.chars().filter(|c| !c.is_whitespace() && *c != '_').flat_map(|c| c.to_lowercase()).collect()
}

impl Standards {
    /// The list that ships with instpol (`instruments/standards.toml`).
    pub fn builtin() -> Result<Self, Error> {
        Self::from_toml_str(BUILTIN, Path::new("<built-in standards.toml>"))
    }

    /// Read and validate a standard-star file.
    pub fn load(path: &Path) -> Result<Self, Error> {
        let text = std::fs::read_to_string(path).map_err(|source| Error::Io { path: path.into(), source })?;
        Self::from_toml_str(&text, path)
    }

    /// Parse and validate; `path` only labels errors.
    pub fn from_toml_str(text: &str, path: &Path) -> Result<Self, Error> {
        if let Some((key, value)) = instrument::toml_numbers::first_non_finite(text) {
            return Err(Error::Parse { path: path.into(), message: format!("{key} = {value}: not a finite number") });
        }
        let s: Standards =
            toml::from_str(text).map_err(|e| Error::Parse { path: path.into(), message: e.to_string() })?;
        // A name (or alias) of two stars would make which star a frame shows depend on the order
        // of the file ([`Standards::star`] compares names as `norm` does).
        let mut names: Vec<(String, usize)> = vec![];
        for (i, star) in s.stars.iter().enumerate() {
            for n in std::iter::once(&star.name).chain(&star.aliases) {
                let key = norm(n);
                if let Some(&(_, j)) = names.iter().find(|(m, j)| *m == key && *j != i) {
                    let other = &s.stars[j].name;
                    return Err(Error::Invalid {
                        path: path.into(),
                        star: star.name.clone(),
                        band: "-".into(),
                        why: format!("the name '{n}' is also star {other}'s (names and aliases must be unique)"),
                    });
                }
                names.push((key, i));
            }
        }
        for star in &s.stars {
            if star.bands.is_empty() {
                return Err(Error::Invalid {
                    path: path.into(),
                    star: star.name.clone(),
                    band: "-".into(),
                    why: "no band values".into(),
                });
            }
            for b in &star.bands {
                let bad = |why: &str| Error::Invalid {
                    path: path.into(),
                    star: star.name.clone(),
                    band: b.band.clone(),
                    why: why.into(),
                };
                if !(b.p_percent.is_finite() && (0.0..100.0).contains(&b.p_percent)) {
                    return Err(bad(&format!("p_percent = {} must be in [0, 100)", b.p_percent)));
                }
                if !(b.sigma_p_percent.is_finite() && b.sigma_p_percent > 0.0) {
                    return Err(bad(&format!("sigma_p_percent = {} must be positive", b.sigma_p_percent)));
                }
                match (star.kind, b.chi_deg, b.sigma_chi_deg) {
                    (Kind::Polarized, Some(c), Some(sc)) => {
                        if !(c.is_finite() && (0.0..180.0).contains(&c)) {
                            return Err(bad(&format!("chi_deg = {c} must be in [0, 180)")));
                        }
                        if !(sc.is_finite() && sc > 0.0) {
                            return Err(bad(&format!("sigma_chi_deg = {sc} must be positive")));
                        }
                    }
                    (Kind::Polarized, _, _) => return Err(bad("a polarized standard needs chi_deg and sigma_chi_deg")),
                    (Kind::Unpolarized, None, None) => {}
                    (Kind::Unpolarized, _, _) => return Err(bad("an unpolarized standard has no chi_deg")),
                }
                if b.source.trim().is_empty() {
                    return Err(bad("every value must name its source"));
                }
            }
        }
        Ok(s)
    }

    /// Find a star by name or alias (case, spaces and underscores ignored).
    pub fn star(&self, name: &str) -> Result<&Star, Error> {
        let n = norm(name);
        self.stars.iter().find(|s| norm(&s.name) == n || s.aliases.iter().any(|a| norm(a) == n)).ok_or_else(|| {
            Error::UnknownStar {
                name: name.into(),
                known: self.stars.iter().map(|s| s.name.as_str()).collect::<Vec<_>>().join(", "),
            }
        })
    }
}

impl Star {
    /// The catalogued J2000 position (deg), when the list gives one: `ra` in hours, minutes,
    /// seconds and `dec` in degrees, minutes, seconds, separated by `:` or spaces.
    pub fn position_deg(&self) -> Option<(f64, f64)> {
        let sexa = |t: &str| -> Option<f64> {
            let t = t.trim();
            let neg = t.starts_with('-');
            let parts: Vec<f64> = t
                .trim_start_matches(['+', '-'])
                .split([':', ' '])
                .filter(|x| !x.is_empty())
                .map(|x| x.parse::<f64>().ok())
                .collect::<Option<Vec<_>>>()?;
            if parts.is_empty() || parts.len() > 3 {
                return None;
            }
            let v = parts.iter().zip([1.0, 60.0, 3600.0]).map(|(x, d)| x / d).sum::<f64>();
            Some(if neg { -v } else { v })
        };
        let ra = sexa(self.ra.as_deref()?)? * 15.0;
        let dec = sexa(self.dec.as_deref()?)?;
        ((0.0..360.0).contains(&ra) && (-90.0..=90.0).contains(&dec)).then_some((ra, dec))
    }

    /// The published value in `band` (case-insensitive; a Bessel alias such as "V_BESS" or
    /// "v_HIGH" matches its first letter when no exact band matches).
    pub fn band(&self, band: &str) -> Result<&BandValue, Error> {
        let exact = self.bands.iter().find(|b| b.band.eq_ignore_ascii_case(band));
        let first = || {
            let mut it = band.chars();
            let c = it.next()?.to_string();
            let rest = it.as_str();
            if rest.is_empty() || rest.starts_with('_') {
                self.bands.iter().find(|b| b.band.eq_ignore_ascii_case(&c))
            } else {
                None
            }
        };
        exact.or_else(first).ok_or_else(|| Error::UnknownBand {
            star: self.name.clone(),
            band: band.into(),
            known: self.bands.iter().map(|b| b.band.as_str()).collect::<Vec<_>>().join(", "),
        })
    }

    /// The intrinsic `(q, u)` expected in `band`. A null standard is `(0, 0)` with its
    /// published `P` counted as an unknown-direction systematic: `P^2 / 2 + sigma_P^2 / 2` per
    /// component. A polarized one is `P (cos 2chi, sin 2chi)` with the errors of `P` and `chi`
    /// propagated.
    pub fn expected(&self, band: &str) -> Result<Expected, Error> {
        let b = self.band(band)?;
        let p = b.p_percent / 100.0;
        let sp = b.sigma_p_percent / 100.0;
        Ok(match (b.chi_deg, b.sigma_chi_deg) {
            (Some(chi), Some(sc)) => {
                let (s2, c2) = (2.0 * chi.to_radians()).sin_cos();
                let sperp = 2.0 * p * sc.to_radians();
                Qu {
                    q: p * c2,
                    u: p * s2,
                    var_q: sp * sp * c2 * c2 + sperp * sperp * s2 * s2,
                    var_u: sp * sp * s2 * s2 + sperp * sperp * c2 * c2,
                    cov_qu: (sp * sp - sperp * sperp) * s2 * c2,
                }
            }
            _ => {
                let v = 0.5 * (p * p + sp * sp);
                Qu::new(0.0, 0.0, v, v, 0.0)
            }
        })
    }
}

/// A star's measured normalized Stokes parameters as the reduction gives them (before any
/// correction, chi as measured), with their covariance.
pub type MeasuredStar = Qu;

/// The outcome of validating a calibration on a standard star. The first eight fields are the
/// JSON contract of `instpol validate` (`schemas/validate.schema.json`).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Validation {
    /// The measured polarization (fraction) and angle (deg, [0, 180)), after the HWP zero-angle
    /// correction and before the instrumental one, with linearized errors.
    pub measured_p: f64,
    pub measured_chi_deg: f64,
    pub sigma_p: f64,
    pub sigma_chi_deg: f64,
    /// What the calibration predicts the star to look like there: `M_I(x, y)` applied to the
    /// star's expected intrinsic polarization (for a null standard: the instrumental `p`, `phi`).
    pub predicted_p: f64,
    pub predicted_chi_deg: f64,
    /// `sqrt(d^T C^-1 d)`, `d` = measured - predicted in `(q, u)`, `C` the sum of the
    /// measurement's covariance and the prediction's (calibration and star).
    #[serde(rename = "pull", alias = "residual_sigma")]
    pub residual_sigma: f64,
    /// Both residuals (this one and [`Self::corrected_residual_sigma`]) within the threshold.
    pub pass: bool,
    /// Error of the prediction (fraction): calibration and star, linearized.
    pub sigma_predicted_p: f64,
    /// The star after correction (exact inversion), and its distance from the expected
    /// intrinsic polarization (zero for a null standard) in units of the combined error.
    pub corrected_p: f64,
    pub corrected_chi_deg: f64,
    pub sigma_corrected_p: f64,
    pub expected_p: f64,
    #[serde(rename = "corrected_pull", alias = "corrected_residual_sigma")]
    pub corrected_residual_sigma: f64,
    pub threshold: f64,
    /// The position lay outside the calibrated field (only with extrapolation allowed).
    pub extrapolated: bool,
}

/// Mahalanobis distance of `(dq, du)` for covariance `[[a, c], [c, b]]`.
pub(crate) fn mahalanobis(dq: f64, du: f64, a: f64, b: f64, c: f64) -> Result<f64, Error> {
    let det = a * b - c * c;
    if !(det > 0.0) || !det.is_finite() {
        return Err(Error::SingularCovariance);
    }
    Ok(((b * dq * dq - 2.0 * c * dq * du + a * du * du) / det).max(0.0).sqrt())
}

/// `M_I(a)` applied to the intrinsic `(qs, us)`: the normalized `(q1, u1)` the star shows
/// through the instrumental polarization `a = (qi, ui)` (`eq:instpol`, the one `M_I`).
pub fn forward(qi: f64, ui: f64, qs: f64, us: f64) -> (f64, f64) {
    let (p, phi) = stokes::polarization(qi, ui);
    let s1 = mueller::partial_polarizer(p, phi) * mueller::stokes_qu(1.0, qs, us);
    (s1[1] / s1[0], s1[2] / s1[0])
}

/// Validate a calibration (`model`) on a standard star measured at `(x, y)` arcmin: compare the
/// measurement with the calibration's prediction there (`residual_sigma`) and the corrected
/// star with its expected intrinsic polarization (`corrected_residual_sigma`); pass when both
/// are within `threshold` (in sigma). `opts` carries the HWP zero angle and the extrapolation
/// policy (see [`crate::correction::correct`]). This is the check of section `sec:fors1`.
pub fn validate_star<M: FieldModel + ?Sized>(
    model: &M,
    x: f64,
    y: f64,
    measured: &MeasuredStar,
    expected: &Expected,
    opts: CorrectOptions,
    threshold: f64,
) -> Result<Validation, Error> {
    let cor = Corrector::new(model, CorrectOptions { method: correct::Method::Exact, ..opts });
    let (a, extrapolated) = cor.instrumental(x, y)?;
    // Measured at the plate; in the sky frame of the model, with its covariance turned alike.
    let sky = mueller::Frame::Plate.to_sky(measured, opts.zero_angle_deg);
    let Qu { q: q1, u: u1, var_q: vq1, var_u: vu1, cov_qu: cv1 } = sky;
    let e = sky.p_chi_with_errors();
    let (mp, msp, mchi, msc) = (e.p, e.sigma_p, e.chi, e.sigma_chi);
    // Prediction and its covariance: Jacobians of the forward map by central differences
    // (step 1e-7 on quantities of order 1e-2: truncation ~1e-14, rounding ~1e-9 relative).
    let (pq, pu) = forward(a.q, a.u, expected.q, expected.u);
    let h = 1e-7;
    let jac = |f: &dyn Fn(f64) -> (f64, f64)| {
        let (p1, p2) = (f(h), f(-h));
        ((p1.0 - p2.0) / (2.0 * h), (p1.1 - p2.1) / (2.0 * h))
    };
    let ja_q = jac(&|d| forward(a.q + d, a.u, expected.q, expected.u));
    let ja_u = jac(&|d| forward(a.q, a.u + d, expected.q, expected.u));
    let js_q = jac(&|d| forward(a.q, a.u, expected.q + d, expected.u));
    let js_u = jac(&|d| forward(a.q, a.u, expected.q, expected.u + d));
    let prop = |jq: (f64, f64), ju: (f64, f64), va: f64, vb: f64, cab: f64| {
        mueller::sandwich(&[[jq.0, ju.0], [jq.1, ju.1]], va, vb, cab)
    };
    let (aq, au, ac) = prop(ja_q, ja_u, a.var_q, a.var_u, a.cov_qu);
    let (sq, su, sc) = prop(js_q, js_u, expected.var_q, expected.var_u, expected.cov_qu);
    let (pvq, pvu, pcv) = (aq + sq, au + su, ac + sc);
    let (pp, psp, pchi, _) = correct::p_chi_with_errors(pq, pu, pvq, pvu, pcv);
    let residual_sigma = mahalanobis(q1 - pq, u1 - pu, vq1 + pvq, vu1 + pvu, cv1 + pcv)?;
    // Corrected star vs expected intrinsic polarization.
    let r = cor.correct(&Measurement::at(x, y, *measured, mueller::Frame::Plate))?;
    let corrected_residual_sigma = sigma_from(expected, &Qu::new(r.q0, r.u0, r.var_q0, r.var_u0, r.cov_qu0))?;
    Ok(Validation {
        measured_p: mp,
        measured_chi_deg: mchi.to_degrees(),
        sigma_p: msp,
        sigma_chi_deg: msc.to_degrees(),
        predicted_p: pp,
        predicted_chi_deg: pchi.to_degrees(),
        residual_sigma,
        pass: residual_sigma <= threshold && corrected_residual_sigma <= threshold,
        sigma_predicted_p: psp,
        corrected_p: r.p0,
        corrected_chi_deg: r.chi0.to_degrees(),
        sigma_corrected_p: r.sigma_p0,
        expected_p: expected.q.hypot(expected.u),
        corrected_residual_sigma,
        threshold,
        extrapolated,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn builtin_list_loads_and_finds_stars() {
        let s = Standards::builtin().unwrap();
        assert_eq!(s.star("hiltner652").unwrap().kind, Kind::Polarized);
        assert_eq!(s.star("HD 14069").unwrap().kind, Kind::Unpolarized);
        assert!(s.star("hd14069").is_ok());
        let e = s.star("Vega").unwrap_err().to_string();
        assert!(e.contains("Vega") && e.contains("Hiltner 652"), "{e}");
        let h = s.star("Hiltner 652").unwrap();
        assert_eq!(h.band("v").unwrap().p_percent, 6.25);
        assert_eq!(h.band("V_BESS").unwrap().p_percent, 6.25);
        assert!(h.band("B").is_err());
    }

    #[test]
    fn positions_in_degrees() {
        let s = Standards::builtin().unwrap();
        // HD 14069: 02:16:45.16 +07:41:11.1 (the list's strings, converted by hand).
        let (ra, dec) = s.star("HD 14069").unwrap().position_deg().unwrap();
        assert!((ra - (2.0 + 16.0 / 60.0 + 45.16 / 3600.0) * 15.0).abs() < 1e-12);
        assert!((dec - (7.0 + 41.0 / 60.0 + 11.1 / 3600.0)).abs() < 1e-12);
        // HD 64299's declination is negative in every part.
        let (_, dec) = s.star("HD 64299").unwrap().position_deg().unwrap();
        assert!((dec + (23.0 + 17.0 / 60.0 + 45.9 / 3600.0)).abs() < 1e-12);
        let mut star = s.star("HD 14069").unwrap().clone();
        star.ra = Some("25:00:00".into());
        assert_eq!(star.position_deg(), None);
        star.ra = None;
        assert_eq!(star.position_deg(), None);
    }

    #[test]
    fn unknown_keys_and_bad_values_are_errors_that_name_them() {
        let bad = "[[star]]\nname = \"X\"\nkind = \"polarized\"\ncolour = 1\n[[star.band]]\nband = \"V\"\np_percent = 1.0\nsigma_p_percent = 0.1\nchi_deg = 10.0\nsigma_chi_deg = 1.0\nsource = \"s\"\n";
        let e = Standards::from_toml_str(bad, Path::new("t.toml")).unwrap_err().to_string();
        assert!(e.contains("t.toml") && e.contains("colour"), "{e}");
        let bad = "[[star]]\nname = \"X\"\nkind = \"polarized\"\n[[star.band]]\nband = \"V\"\np_percent = 1.0\nsigma_p_percent = 0.1\nchi_deg = 190.0\nsigma_chi_deg = 1.0\nsource = \"s\"\n";
        let e = Standards::from_toml_str(bad, Path::new("t.toml")).unwrap_err().to_string();
        assert!(e.contains("star 'X' band V") && e.contains("chi_deg = 190"), "{e}");
    }

    /// The expected (q, u) of a polarized standard: P cos 2chi, with the covariance whose
    /// principal errors are sigma_P along and 2 P sigma_chi across the polarization direction.
    #[test]
    fn expected_values_from_published_p_chi() {
        let s = Standards::builtin().unwrap();
        let e = s.star("Hiltner 652").unwrap().expected("V").unwrap();
        let (p, chi) = stokes::polarization(e.q, e.u);
        assert!((p - 0.0625).abs() < 1e-15);
        assert!((chi.to_degrees() - 179.18).abs() < 1e-9);
        let tr = e.var_q + e.var_u;
        let want = 1e-8 + (2.0 * 0.0625 * 0.20f64.to_radians()).powi(2);
        assert!((tr - want).abs() < 1e-18 * 1e3, "{tr} vs {want}");
        let n = s.star("HD 64299").unwrap().expected("B").unwrap();
        assert_eq!((n.q, n.u), (0.0, 0.0));
        assert!((n.var_q - 0.5 * (0.00151f64.powi(2) + 0.00032f64.powi(2))).abs() < 1e-18);
    }
}
