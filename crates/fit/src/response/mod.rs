//! The instrument's constant response from standard stars, as the MOPTOP, RoboPol and SPARC4
//! reductions calibrate it: the instrumental `(q0, u0)` from unpolarized standards, then the
//! polarimetric efficiency and the angle offset from polarized ones, `(q0, u0)` taken off
//! first. The model is [`field::ConstantResponse`]:
//!
//! ```text
//! (q, u)_measured = (q0, u0) + eta R(-k) (q, u)_catalogue
//! ```
//!
//! in the instrument's sky frame (the zero angle the standards' rows carry; a celestial row is
//! turned back by its position angle on the sky first, and so is its catalogued angle, since
//! `(q0, u0)` is fixed to the instrument, not to the sky). The signs are the zero angle's
//! (`fit::zeroangle`): `k` is the angle to add to a measured `chi`, catalogue less measured,
//! so a star's measured angle is its catalogued one less `k`; `eta` is measured `P` over
//! catalogued `P`.
//!
//! - `(q0, u0)`: the mean of the unpolarized standards' `(q, u)` weighted by their inverse
//!   covariances, `(sum C_i^-1)^-1 sum C_i^-1 m_i`, its covariance `(sum C_i^-1)^-1`; the
//!   judge of conditioning ([`crate::conditioning::judge`]) decides whether they determine it.
//! - `k`: the zero angle of the polarized standards' angles after `(q0, u0)` is taken off
//!   ([`crate::zeroangle::ZeroAngleReport::combine`]: the circular mean, outliers named and left
//!   out, the sense checked: a mirrored instrument is refused, the model turns angles and does
//!   not mirror them).
//! - `eta`: [`crate::zeroangle::efficiency`] of the same stars.
//!
//! Every polarized standard shares the one `(q0, u0)` taken off it, so the errors of `eta` and
//! `k` carry its covariance as well, through the derivatives of the whole fit with respect to
//! `(q0, u0)` (central differences of the same computation); the 4 x 4 covariance of
//! `(q0, u0, eta, k)` (`k` in rad) holds those correlations.
//!
//! Its calibration file is [`cal`].

pub mod cal;

use crate::correction::correct::Measurement;
use crate::zeroangle::{Efficiency, MeasuredStandard, Sense, ZeroAngleReport};
use field::ConstantResponse;
use mueller::Qu;
use nalgebra::{DMatrix, Matrix2, Vector2};

/// What a standard is known to be: unpolarized (catalogued `P = 0`), or polarized with its
/// catalogued `P` (fraction) and angle (deg, north through east) and their errors.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Truth {
    Unpolarized,
    Polarized { p: f64, sigma_p: f64, chi_deg: f64, sigma_chi_deg: f64 },
}

/// One standard: its name, its measurement (in the frame its row says) and what it is.
#[derive(Debug, Clone, PartialEq)]
pub struct Standard {
    pub label: String,
    pub measured: Measurement,
    pub truth: Truth,
}

/// Why standards do not give the response; each names the star or what is missing.
#[derive(Debug, thiserror::Error)]
pub enum Error {
    #[error("no unpolarized standard (catalogued P = 0): the instrumental (q0, u0) needs at least one")]
    NoUnpolarized,
    #[error("no polarized standard: the efficiency and the angle offset need at least one star of catalogued P > 0")]
    NoPolarized,
    #[error("standard {label}: catalogued P = {p} with an angle: a polarized standard needs P > 0 (give a star of P = 0 as unpolarized)")]
    ZeroCatalogueP { label: String, p: f64 },
    #[error("standard {label}: {what}")]
    Bad { label: String, what: String },
    #[error("the unpolarized standards do not determine (q0, u0): {0}")]
    Undetermined(#[from] crate::conditioning::Undetermined),
    #[error("the polarized standards' angles: {0}")]
    ZeroAngle(#[from] crate::zeroangle::Error),
    #[error("the polarized standards' angles run mirrored (chi_catalogue = offset - chi_measured fits better): a constant response turns angles and cannot mirror them; check the instrument's sense")]
    Mirrored,
    #[error("no polarized standard has a measured P with a finite error")]
    NoEfficiency,
}

/// An unpolarized standard's row of the result: its `(q, u)` in the instrument's frame and its
/// residual about `(q0, u0)` in units of its errors.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct UnpolarizedRow {
    pub label: String,
    pub q: f64,
    pub u: f64,
    pub sigma_q: f64,
    pub sigma_u: f64,
    pub pull_q: f64,
    pub pull_u: f64,
}

/// The fitted response ([`fit`]).
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct ResponseFit {
    pub response: ConstantResponse,
    /// Covariance of `(q0, u0, efficiency, offset)`, row-major, the offset in rad.
    pub covariance: [[f64; 4]; 4],
    /// The HWP zero angle (deg) of the instrument's sky frame the response lives in (the one
    /// the standards' rows carry; 0 for rows at the plate).
    pub hwp_chi_offset_deg: f64,
    pub sigma_q0: f64,
    pub sigma_u0: f64,
    pub sigma_efficiency: f64,
    pub sigma_offset_deg: f64,
    /// chi^2 of the unpolarized standards about `(q0, u0)` and its degrees of freedom.
    pub chi2_unpolarized: f64,
    pub dof_unpolarized: usize,
    pub unpolarized: Vec<UnpolarizedRow>,
    /// The polarized standards' angles and the offset, as `instpol zero-angle` reports them
    /// (its `zero_angle_deg` is the offset), with the efficiency beside it.
    pub polarized: ZeroAngleReport,
}

/// The `(q, u)` of `m` in the sky frame of the zero angle `z` (deg), a celestial row turned
/// back by its position angle.
fn in_frame(m: &Measurement, z: f64) -> Qu {
    m.frame.to_sky(&m.qu, z)
}

/// The inverse covariance of a standard's `(q, u)`, refused (naming it) when not positive
/// definite.
fn weight(label: &str, qu: &Qu) -> Result<Matrix2<f64>, Error> {
    let c = Matrix2::new(qu.var_q, qu.cov_qu, qu.cov_qu, qu.var_u);
    let det = c.determinant();
    if !(qu.var_q > 0.0 && qu.var_u > 0.0 && det > 0.0 && det.is_finite()) {
        return Err(Error::Bad {
            label: label.into(),
            what: format!(
                "the covariance of its (q, u) (var_q {:e}, var_u {:e}, cov_qu {:e}) is not positive definite: a standard needs finite, non-zero errors",
                qu.var_q, qu.var_u, qu.cov_qu
            ),
        });
    }
    Ok(c.try_inverse().unwrap_or_else(Matrix2::zeros))
}

/// A residual over the square root of its variance, 0 where that variance is 0 (one star).
fn pull(r: f64, v: f64) -> f64 {
    if v > 0.0 {
        r / v.sqrt()
    } else {
        0.0
    }
}

/// `(q0, u0)` with its covariance from the unpolarized standards (module docs), their rows
/// and chi^2.
fn instrumental(unpol: &[(&Standard, Qu)]) -> Result<(Vector2<f64>, Matrix2<f64>, f64, Vec<UnpolarizedRow>), Error> {
    let mut w_sum = Matrix2::zeros();
    let mut b = Vector2::zeros();
    let mut design = DMatrix::zeros(2 * unpol.len(), 2);
    for (k, (s, qu)) in unpol.iter().enumerate() {
        let w = weight(&s.label, qu)?;
        w_sum += w;
        b += w * Vector2::new(qu.q, qu.u);
        // The whitened design rows: the Cholesky factor of the weight (each datum's residual
        // over its errors), the two parameters' columns.
        let l = w.cholesky().map(|c| c.l().transpose()).unwrap_or_else(Matrix2::zeros);
        design.view_mut((2 * k, 0), (2, 2)).copy_from(&l);
    }
    crate::conditioning::judge(
        &design,
        &crate::conditioning::Words::new(
            vec!["q0".into(), "u0".into()],
            "give unpolarized standards measured in both q and u with finite errors",
        ),
    )?;
    let cov = w_sum.try_inverse().ok_or_else(|| Error::Bad {
        label: "the unpolarized standards".into(),
        what: "their summed weight cannot be inverted".into(),
    })?;
    let c = cov * b;
    let mut chi2 = 0.0;
    let rows = unpol
        .iter()
        .map(|(s, qu)| {
            let r = Vector2::new(qu.q - c[0], qu.u - c[1]);
            chi2 += (r.transpose() * weight(&s.label, qu).unwrap_or_else(|_| Matrix2::zeros()) * r)[0];
            UnpolarizedRow {
                label: s.label.clone(),
                q: qu.q,
                u: qu.u,
                sigma_q: qu.sigma_q(),
                sigma_u: qu.sigma_u(),
                // A residual about a mean it is part of varies by its variance less the mean's.
                pull_q: pull(r[0], qu.var_q - cov[(0, 0)]),
                pull_u: pull(r[1], qu.var_u - cov[(1, 1)]),
            }
        })
        .collect();
    Ok((c, cov, chi2, rows))
}

/// The offset report and the efficiency of the polarized standards with `c = (q0, u0)` taken
/// off (their `(q, u)` in the frame `z`).
fn turn_and_efficiency(
    filter: &str,
    pol: &[(&Standard, Qu)],
    c: Vector2<f64>,
) -> Result<(ZeroAngleReport, Efficiency), Error> {
    let mut rows = Vec::with_capacity(pol.len());
    for (s, qu) in pol {
        let Truth::Polarized { p, sigma_p, chi_deg, sigma_chi_deg } = s.truth else { continue };
        let d = Qu { q: qu.q - c[0], u: qu.u - c[1], ..*qu };
        let e = d.p_chi_with_errors();
        // The catalogued angle in the instrument's frame, as the measured one is.
        let pa = s.measured.frame.position_angle_deg().unwrap_or(0.0);
        let mut m = MeasuredStandard::from_frames(
            s.label.clone(),
            (s.measured.x, s.measured.y),
            (e.p, e.sigma_p),
            (e.chi, e.sigma_chi),
            mueller::fold_pi((chi_deg - pa).to_radians()).to_degrees(),
            sigma_chi_deg,
            None,
        )?;
        m.p_catalogue = Some(p);
        m.sigma_p_catalogue = Some(sigma_p);
        rows.push(m);
    }
    let (report, _) = ZeroAngleReport::combine(filter.to_string(), rows)?;
    if report.sense == Sense::Mirrored {
        return Err(Error::Mirrored);
    }
    let eff = report.efficiency.ok_or(Error::NoEfficiency)?;
    Ok((report, eff))
}

/// The constant response from `standards` (module docs), for the filter `filter` (named in the
/// offset report).
pub fn fit(filter: &str, standards: &[Standard]) -> Result<ResponseFit, Error> {
    for s in standards {
        crate::correction::correct::check_measurement(&s.measured)
            .map_err(|e| Error::Bad { label: s.label.clone(), what: e.to_string() })?;
        if let Truth::Polarized { p, sigma_p, chi_deg, sigma_chi_deg } = s.truth {
            if p == 0.0 {
                return Err(Error::ZeroCatalogueP { label: s.label.clone(), p });
            }
            if !(p > 0.0 && p <= 1.0 && sigma_p >= 0.0 && chi_deg.is_finite() && (0.0..90.0).contains(&sigma_chi_deg)) {
                return Err(Error::Bad {
                    label: s.label.clone(),
                    what: format!("catalogued P = {p} +- {sigma_p} (a fraction in (0, 1]) and chi = {chi_deg} +- {sigma_chi_deg} deg (an error in [0, 90)) are not a polarized standard's"),
                });
            }
        }
    }
    // The frame: the zero angle the first row carries (0 at the plate).
    let z = standards.first().and_then(|s| s.measured.frame.zero_angle_deg()).unwrap_or(0.0);
    let split = |want_pol: bool| -> Vec<(&Standard, Qu)> {
        standards
            .iter()
            .filter(|s| matches!(s.truth, Truth::Polarized { .. }) == want_pol)
            .map(|s| (s, in_frame(&s.measured, z)))
            .collect()
    };
    let (unpol, pol) = (split(false), split(true));
    if unpol.is_empty() {
        return Err(Error::NoUnpolarized);
    }
    if pol.is_empty() {
        return Err(Error::NoPolarized);
    }
    let (c, cov_c, chi2, rows) = instrumental(&unpol)?;
    let (report, eff) = turn_and_efficiency(filter, &pol, c)?;
    let offset = report.zero_angle_deg.to_radians();
    // d(eta, k)/d(q0, u0) by central differences of the same fit (module docs).
    let h = 1e-7;
    let mut g = [[0.0; 2]; 2];
    for (j, dv) in [Vector2::new(h, 0.0), Vector2::new(0.0, h)].into_iter().enumerate() {
        let (rp, ep) = turn_and_efficiency(filter, &pol, c + dv)?;
        let (rm, em) = turn_and_efficiency(filter, &pol, c - dv)?;
        g[0][j] = (ep.efficiency - em.efficiency) / (2.0 * h);
        g[1][j] = mueller::wrap_half_pi((rp.zero_angle_deg - rm.zero_angle_deg).to_radians()) / (2.0 * h);
    }
    let mut cov = [[0.0; 4]; 4];
    for a in 0..2 {
        for b in 0..2 {
            cov[a][b] = cov_c[(a, b)];
        }
    }
    // (eta, k) = f(stars) + G c: Cov = own + G C G^T; Cov(c, (eta, k)) = C G^T.
    let own = [eff.sigma_efficiency.powi(2), report.sigma_zero_angle_deg.to_radians().powi(2)];
    for a in 0..2 {
        for b in 0..2 {
            let mut v = 0.0;
            for i in 0..2 {
                for j in 0..2 {
                    v += g[a][i] * cov_c[(i, j)] * g[b][j];
                }
            }
            cov[2 + a][2 + b] = v + if a == b { own[a] } else { 0.0 };
        }
        for i in 0..2 {
            let v: f64 = (0..2).map(|j| cov_c[(i, j)] * g[a][j]).sum();
            cov[i][2 + a] = v;
            cov[2 + a][i] = v;
        }
    }
    Ok(ResponseFit {
        response: ConstantResponse { q0: c[0], u0: c[1], efficiency: eff.efficiency, offset_deg: offset.to_degrees() },
        hwp_chi_offset_deg: z,
        sigma_q0: cov[0][0].sqrt(),
        sigma_u0: cov[1][1].sqrt(),
        sigma_efficiency: cov[2][2].sqrt(),
        sigma_offset_deg: cov[3][3].sqrt().to_degrees(),
        covariance: cov,
        chi2_unpolarized: chi2,
        dof_unpolarized: 2 * unpol.len() - 2,
        unpolarized: rows,
        polarized: report,
    })
}

impl Truth {
    /// What the standards list says a star is in `filter`: unpolarized, or polarized with its
    /// published `P` (percent in the list, a fraction here) and angle.
    pub fn of_star(star: &crate::standards::Star, filter: &str) -> Result<Self, crate::standards::Error> {
        let b = star.band(filter)?;
        Ok(match (star.kind, b.chi_deg, b.sigma_chi_deg) {
            (crate::standards::Kind::Polarized, Some(chi_deg), Some(sigma_chi_deg)) => {
                Truth::Polarized { p: b.p_percent / 100.0, sigma_p: b.sigma_p_percent / 100.0, chi_deg, sigma_chi_deg }
            }
            _ => Truth::Unpolarized,
        })
    }
}

/// A standard's row in a catalog table (`instpol catalog`'s, any format `skyfield::table`
/// reads): the measured row nearest `(x, y)` (0-based px of the o image, columns `x`, `y`)
/// within `radius_px`, its `q, u, sigma_q, sigma_u` (and `cov_qu` when present) in the frame
/// the table says ([`skyfield::table::Table::frame`]), at its `x_arcmin, y_arcmin` when given;
/// and the setup the table records (`None` for a table of other software). Refused, naming the
/// file: no row within the radius (the nearest said), two rows within it, a row not measured.
pub fn catalog_standard(
    path: &std::path::Path,
    (x, y): (f64, f64),
    radius_px: f64,
) -> crate::Result<(Measurement, Option<crate::correction::setup::Setup>)> {
    let t = skyfield::table::Table::read(path, None)?;
    let bad = |what: String| crate::Error::BadFile { path: path.to_path_buf(), what };
    let (xs, ys) = (t.numbers("x", path)?, t.numbers("y", path)?);
    let mut near: Vec<(f64, usize)> = xs
        .iter()
        .zip(&ys)
        .enumerate()
        .map(|(i, (a, b))| ((a - x).hypot(b - y), i))
        .filter(|d| d.0.is_finite())
        .collect();
    near.sort_by(|a, b| a.0.total_cmp(&b.0));
    let Some(&(d, i)) = near.first() else { return Err(bad("no row with a position x, y".into())) };
    if d > radius_px {
        return Err(bad(format!(
            "no star within {radius_px} px of ({x}, {y}): the nearest, {}, is {d:.1} px away",
            t.row_label(i)
        )));
    }
    if let Some(&(d2, j)) = near.get(1).filter(|n| n.0 <= radius_px) {
        return Err(bad(format!(
            "{} and {} both lie within {radius_px} px of ({x}, {y}) ({d:.1} and {d2:.1} px): give the position more closely",
            t.row_label(i),
            t.row_label(j)
        )));
    }
    let col = |k: &str| -> crate::Result<f64> { Ok(t.numbers(k, path)?[i]) };
    let opt = |k: &str, or: f64| -> crate::Result<f64> {
        if t.column(k).is_some() {
            col(k)
        } else {
            Ok(or)
        }
    };
    let (q, u, sq, su) = (col("q")?, col("u")?, col("sigma_q")?, col("sigma_u")?);
    if !(q.is_finite() && u.is_finite()) {
        return Err(bad(format!(
            "{}: the star at ({x}, {y}) was not measured (q, u empty: a flagged star)",
            t.row_label(i)
        )));
    }
    let qu = Qu::from_sigmas(q, u, sq, su, opt("cov_qu", 0.0)?);
    let m = Measurement::at(opt("x_arcmin", xs[i])?, opt("y_arcmin", ys[i])?, qu, t.frame(path)?);
    Ok((m, t.product.as_ref().and_then(crate::correction::setup::Setup::of_product)))
}

/// The one instrument and filter of standards' catalogs (`setups`: each catalog's name and
/// what it records) and of the caller's `instrument`, `filter` (given for catalogs that record
/// none): catalogs that disagree with each other or with what was given are refused, naming
/// both ([`crate::correction::setup::check_compatible`], which refuses a quarter-wave plate's rows too).
pub fn one_setup(
    setups: &[(String, Option<crate::correction::setup::Setup>)],
    instrument: Option<&str>,
    filter: Option<&str>,
) -> Result<crate::correction::setup::Setup, String> {
    let recorded = setups.iter().find_map(|(_, s)| s.clone());
    let given = |r: Option<&crate::correction::setup::Setup>| crate::correction::setup::Setup {
        instrument: instrument.map(str::to_string).or(r.map(|s| s.instrument.clone())).unwrap_or_default(),
        filter: filter.map(str::to_string).or(r.map(|s| s.filter.clone())).unwrap_or_default(),
        plate: Some("half_wave".into()),
        ..r.cloned().unwrap_or_default()
    };
    let one = given(recorded.as_ref());
    if one.instrument.is_empty() || one.filter.is_empty() {
        return Err("the catalogs do not say which instrument and filter they were measured with: give them (instrument and filter)".into());
    }
    for (name, s) in setups {
        if let Some(s) = s {
            crate::correction::setup::check_compatible(s, Some(&one))
                .map_err(|m| format!("{name} and the other standards do not fit together: {m}"))?;
        }
    }
    Ok(one)
}

/// The summary of a fit as `instpol efficiency --json` prints it (`schemas/efficiency.schema.json`).
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct Summary {
    pub instrument: String,
    pub filter: String,
    pub hwp_chi_offset_deg: f64,
    /// The instrumental `(q0, u0)` (named as `instpol correct` names the instrumental
    /// polarization it removes) with its errors and covariance.
    pub q_inst: f64,
    pub sigma_q_inst: f64,
    pub u_inst: f64,
    pub sigma_u_inst: f64,
    pub cov_qu_inst: f64,
    pub efficiency: f64,
    pub sigma_efficiency: f64,
    pub offset_deg: f64,
    pub sigma_offset_deg: f64,
    pub chi2_dof_unpolarized: Option<f64>,
    pub chi2_dof_efficiency: Option<f64>,
    pub chi2_dof_offset: Option<f64>,
    pub unpolarized: Vec<UnpolarizedRow>,
    pub polarized: Vec<PolarizedRow>,
    /// The file written, if any.
    pub output: Option<String>,
    /// What the standards' catalogs record of their instrument file and detector, and the
    /// run's inputs: the response file's product.
    pub product: skyfield::provenance::Product,
}

/// A polarized standard's row of the [`Summary`]: measured (with `(q0, u0)` taken off, in the
/// instrument's frame) against catalogued.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct PolarizedRow {
    pub label: String,
    pub p_measured: Option<f64>,
    pub sigma_p_measured: Option<f64>,
    pub p_catalogue: Option<f64>,
    pub chi_measured_deg: f64,
    pub chi_catalogue_deg: f64,
    pub offset_deg: f64,
    pub pull: f64,
    pub excluded: bool,
}

impl ResponseFit {
    /// The summary for the standards' `setup` ([`one_setup`]), with the file written
    /// (`output`).
    pub fn summary(&self, setup: &crate::correction::setup::Setup, output: Option<String>) -> Summary {
        let r = &self.polarized;
        Summary {
            instrument: setup.instrument.clone(),
            filter: setup.filter.clone(),
            product: setup.product().with_run_inputs(),
            hwp_chi_offset_deg: self.hwp_chi_offset_deg,
            q_inst: self.response.q0,
            sigma_q_inst: self.sigma_q0,
            u_inst: self.response.u0,
            sigma_u_inst: self.sigma_u0,
            cov_qu_inst: self.covariance[0][1],
            efficiency: self.response.efficiency,
            sigma_efficiency: self.sigma_efficiency,
            offset_deg: self.response.offset_deg,
            sigma_offset_deg: self.sigma_offset_deg,
            chi2_dof_unpolarized: (self.dof_unpolarized > 0)
                .then(|| self.chi2_unpolarized / self.dof_unpolarized as f64),
            chi2_dof_efficiency: r.efficiency.and_then(|e| e.chi2_dof),
            chi2_dof_offset: r.chi2_dof,
            unpolarized: self.unpolarized.clone(),
            polarized: r
                .standards
                .iter()
                .map(|s| PolarizedRow {
                    label: s.measured.label.clone(),
                    p_measured: s.measured.p_measured,
                    sigma_p_measured: s.measured.sigma_p_measured,
                    p_catalogue: s.measured.p_catalogue,
                    chi_measured_deg: s.measured.chi_measured_deg,
                    chi_catalogue_deg: s.measured.chi_catalogue_deg,
                    offset_deg: s.offset_deg,
                    pull: s.pull,
                    excluded: s.excluded,
                })
                .collect(),
            output,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use mueller::Frame;

    /// A measurement of `(q, u)` with errors `s` in the sky frame of zero angle 2 deg.
    fn meas(q: f64, u: f64, s: f64) -> Measurement {
        Measurement::at(0.0, 0.0, Qu::from_sigmas(q, u, s, s, 0.0), Frame::Sky { zero_angle_deg: 2.0 })
    }

    /// What the instrument measures of a star of `p`, `chi` (deg), written out here: `chi - k`
    /// for the angle, `eta p` for the degree, `(q0, u0)` added.
    fn seen(p: f64, chi: f64, (q0, u0, eta, k): (f64, f64, f64, f64)) -> (f64, f64) {
        let a = 2.0 * (chi - k).to_radians();
        (q0 + eta * p * a.cos(), u0 + eta * p * a.sin())
    }

    fn polarized(label: &str, p: f64, chi: f64, truth: (f64, f64, f64, f64), s: f64) -> Standard {
        let (q, u) = seen(p, chi, truth);
        Standard {
            label: label.into(),
            measured: meas(q, u, s),
            truth: Truth::Polarized { p, sigma_p: 0.0005, chi_deg: chi, sigma_chi_deg: 0.1 },
        }
    }

    fn unpolarized(label: &str, q: f64, u: f64, s: f64) -> Standard {
        Standard { label: label.into(), measured: meas(q, u, s), truth: Truth::Unpolarized }
    }

    /// Exact data give the exact parameters: (q0, u0) = (0.003, -0.002) from two unpolarized
    /// stars measured at it, efficiency 0.9 and offset 4 deg from three polarized stars of
    /// different angles; the error of (q0, u0) is sigma / sqrt 2 for two stars of error sigma
    /// (their mean), and the frame is the rows'.
    #[test]
    fn exact_data_give_the_exact_parameters() {
        let truth = (0.003, -0.002, 0.9, 4.0);
        let stds = vec![
            unpolarized("HD 1", 0.003, -0.002, 0.0004),
            unpolarized("HD 2", 0.003, -0.002, 0.0004),
            polarized("A", 0.04, 30.0, truth, 0.0003),
            polarized("B", 0.05, 100.0, truth, 0.0003),
            polarized("C", 0.03, 150.0, truth, 0.0003),
        ];
        let f = fit("R", &stds).unwrap();
        let r = f.response;
        assert!((r.q0 - 0.003).abs() < 1e-15 && (r.u0 + 0.002).abs() < 1e-15, "{r:?}");
        assert!((r.efficiency - 0.9).abs() < 1e-12, "{r:?}");
        assert!((r.offset_deg - 4.0).abs() < 1e-9, "{r:?}");
        assert!((f.sigma_q0 - 0.0004 / 2f64.sqrt()).abs() < 1e-15 && f.chi2_unpolarized < 1e-20);
        assert_eq!(f.hwp_chi_offset_deg, 2.0);
        assert!(f.sigma_efficiency > 0.0 && f.sigma_offset_deg > 0.0);
    }

    /// Efficiency 1, offset 0 and no (q0, u0) make the correction the identity: a star is given
    /// back as measured, its covariance unchanged when the parameters' is zero; with efficiency
    /// 0.8 the covariance of a round error is divided by 0.8^2 (the turn keeps it round).
    #[test]
    fn identity_and_the_covariance_of_the_inverse() {
        let cal = |eta: f64, k: f64| crate::response::cal::ResponseCal {
            instrument: "X".into(),
            filter: "R".into(),
            plate: "half_wave".into(),
            hwp_chi_offset_deg: 2.0,
            response: ConstantResponse { q0: 0.0, u0: 0.0, efficiency: eta, offset_deg: k },
            covariance: [[0.0; 4]; 4],
            n_unpolarized: 1,
            n_polarized: 1,
            product: None,
        };
        let m = meas(0.02, -0.01, 0.001);
        let c = cal(1.0, 0.0).correct(&m).unwrap();
        assert_eq!((c.q0, c.u0, c.var_q0, c.var_u0, c.cov_qu0), (0.02, -0.01, 1e-6, 1e-6, 0.0));
        let (q, u) = seen(0.05, 70.0, (0.0, 0.0, 0.8, 10.0));
        let c = cal(0.8, 10.0).correct(&meas(q, u, 0.001)).unwrap();
        assert!((c.p0 - 0.05).abs() < 1e-15 && (c.chi0.to_degrees() - 70.0).abs() < 1e-9, "{c:?}");
        assert!((c.var_q0 - 1e-6 / 0.64).abs() < 1e-18 && c.cov_qu0.abs() < 1e-20, "{c:?}");
    }

    /// No unpolarized standard, no polarized one, and polarized standards catalogued at P = 0
    /// are refused by name.
    #[test]
    fn refusals() {
        let truth = (0.0, 0.0, 0.9, 0.0);
        let pol = polarized("A", 0.04, 30.0, truth, 0.0003);
        assert!(matches!(fit("R", std::slice::from_ref(&pol)), Err(Error::NoUnpolarized)));
        let unp = unpolarized("HD 1", 0.0, 0.0, 0.0004);
        assert!(matches!(fit("R", std::slice::from_ref(&unp)), Err(Error::NoPolarized)));
        let zero = Standard {
            truth: Truth::Polarized { p: 0.0, sigma_p: 0.0001, chi_deg: 30.0, sigma_chi_deg: 0.1 },
            ..pol.clone()
        };
        let e = fit("R", &[unp.clone(), zero]).unwrap_err();
        assert!(matches!(&e, Error::ZeroCatalogueP { label, .. } if label == "A"), "{e}");
        // A standard with a zero error does not determine anything: named.
        let flat = unpolarized("HD 9", 0.0, 0.0, 0.0);
        let e = fit("R", &[flat, pol]).unwrap_err().to_string();
        assert!(e.contains("HD 9"), "{e}");
    }
}
