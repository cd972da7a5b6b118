//! The HWP zero angle from polarized standards: the angle to add to a measured `chi`
//! (`eq:polang`) so that it becomes the star's catalogued one (the chromatic zero angle of a
//! super-achromatic HWP and the instrument's rotation, section `sec:HWP`), and the sense of
//! the angle (whether the instrument measures `chi` counter-clockwise on the sky, as the IAU
//! does, or mirrored).
//!
//! Angles of linear polarization live on a circle of period 180 deg, so offsets are averaged as
//! the directions `2 d`, weighted by `1 / sigma^2`; the error of the mean is `1 / sqrt(sum w)`.
//! With two or more standards of different `chi`, the sense is the one with the smaller
//! chi^2 (`chi_true = offset + chi_meas` for the IAU sense, `offset - chi_meas` mirrored); with
//! one standard, or standards of one `chi`, it cannot be told and is reported so.
//!
//! With several standards the scatter is checked: the chi^2 of the offsets about their mean,
//! each star's pull (its residual over the residual's own error, `sigma_i^2 - 1 / sum w`, since
//! the mean contains the star), a scatter-based error (the propagated one times
//! `sqrt(chi^2 / dof)`, the Birge ratio) beside the propagated one, and the star that disagrees
//! (the largest pull beyond [`OUTLIER_PULL`], with three or more stars: with two, either could
//! be the wrong one).

/// One standard: measured and catalogued `chi` (rad) with their 1-sigma errors (rad).
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct StandardChi {
    pub chi_measured: f64,
    pub sigma_measured: f64,
    pub chi_catalogue: f64,
    pub sigma_catalogue: f64,
}

/// The sense of the instrument's angle.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Sense {
    /// `chi_true = offset + chi_measured` fits better (counter-clockwise, as the IAU).
    Iau,
    /// `chi_true = offset - chi_measured` fits better: the instrument's angles are mirrored.
    Mirrored,
    /// One standard, or standards sharing one `chi`: the sense cannot be told.
    Undetermined,
}

/// The zero angle from a set of standards.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct ZeroAngle {
    /// The angle to add to a measured `chi` (rad, in (-pi/2, pi/2]), for the IAU sense (or the
    /// mirrored one when `sense` says so).
    pub offset: f64,
    pub sigma: f64,
    /// chi^2 of the offsets about their mean and its degrees of freedom.
    pub chi2: f64,
    pub dof: usize,
    pub sense: Sense,
    /// chi^2 of the other sense (for the record), when the sense was decided.
    pub chi2_other_sense: Option<f64>,
    /// Each standard's own offset (rad).
    pub offsets: Vec<f64>,
    /// Each standard's residual about the mean over its error (0 for a single star).
    pub pulls: Vec<f64>,
    /// The propagated error scaled by `sqrt(chi2 / dof)` (rad), with two or more standards.
    pub sigma_scatter: Option<f64>,
    /// Index (into the standards given) of the star whose pull exceeds [`OUTLIER_PULL`], the
    /// largest one, with three or more standards.
    pub outlier: Option<usize>,
}

/// A standard whose offset lies further than this (in sigma of its residual) from the mean of
/// the others is named as an outlier.
pub const OUTLIER_PULL: f64 = 3.0;

pub use mueller::wrap_half_pi;

/// Weighted circular mean (period pi) of offsets `d` with weights `w`, and its chi^2.
fn mean_offset(d: &[f64], w: &[f64]) -> (f64, f64) {
    let (s, c) =
        d.iter().zip(w).fold((0.0, 0.0), |(s, c), (&a, &wi)| (s + wi * (2.0 * a).sin(), c + wi * (2.0 * a).cos()));
    let m = wrap_half_pi(0.5 * s.atan2(c));
    let chi2 = d.iter().zip(w).map(|(&a, &wi)| wi * wrap_half_pi(a - m).powi(2)).sum();
    (m, chi2)
}

/// The zero angle and sense from `stds` (see the module docs). `None` when no standard has a
/// finite, positive error.
pub fn zero_angle(stds: &[StandardChi]) -> Option<ZeroAngle> {
    let ok: Vec<&StandardChi> = stds
        .iter()
        .filter(|s| {
            let v = s.sigma_measured.powi(2) + s.sigma_catalogue.powi(2);
            s.chi_measured.is_finite() && s.chi_catalogue.is_finite() && v.is_finite() && v > 0.0
        })
        .collect();
    if ok.is_empty() {
        return None;
    }
    let w: Vec<f64> = ok.iter().map(|s| 1.0 / (s.sigma_measured.powi(2) + s.sigma_catalogue.powi(2))).collect();
    let iau: Vec<f64> = ok.iter().map(|s| wrap_half_pi(s.chi_catalogue - s.chi_measured)).collect();
    let mir: Vec<f64> = ok.iter().map(|s| wrap_half_pi(s.chi_catalogue + s.chi_measured)).collect();
    let (m_iau, c_iau) = mean_offset(&iau, &w);
    let (m_mir, c_mir) = mean_offset(&mir, &w);
    // The sense is decidable only when the catalogued angles differ (by more than their errors).
    let spread = ok.iter().map(|s| wrap_half_pi(s.chi_catalogue - ok[0].chi_catalogue).abs()).fold(0.0, f64::max);
    let sig_max = ok.iter().map(|s| s.sigma_catalogue.max(s.sigma_measured)).fold(0.0, f64::max);
    let decidable = ok.len() >= 2 && spread > 5.0 * sig_max;
    let (sense, offset, chi2, offsets, other) = if !decidable {
        (Sense::Undetermined, m_iau, c_iau, iau, None)
    } else if c_iau <= c_mir {
        (Sense::Iau, m_iau, c_iau, iau, Some(c_mir))
    } else {
        (Sense::Mirrored, m_mir, c_mir, mir, Some(c_iau))
    };
    let sw: f64 = w.iter().sum();
    let sigma = 1.0 / sw.sqrt();
    let dof = ok.len() - 1;
    let pulls: Vec<f64> = offsets
        .iter()
        .zip(&w)
        .map(|(&d, &wi)| {
            let v = 1.0 / wi - 1.0 / sw;
            if v > 0.0 {
                wrap_half_pi(d - offset) / v.sqrt()
            } else {
                0.0
            }
        })
        .collect();
    let sigma_scatter = (dof > 0).then(|| sigma * (chi2 / dof as f64).sqrt());
    // Map the worst pull back to the index among all standards given (non-finite ones skipped).
    let idx: Vec<usize> =
        stds.iter().enumerate().filter(|(_, s)| ok.iter().any(|o| std::ptr::eq(*o, *s))).map(|(i, _)| i).collect();
    let outlier = if ok.len() >= 3 {
        let (k, worst) =
            pulls.iter().enumerate().map(|(k, p)| (k, p.abs())).fold((0, 0.0), |a, b| if b.1 > a.1 { b } else { a });
        (worst > OUTLIER_PULL).then(|| idx[k])
    } else {
        None
    };
    Some(ZeroAngle { offset, sigma, chi2, dof, sense, chi2_other_sense: other, offsets, pulls, sigma_scatter, outlier })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn d(x: f64) -> f64 {
        x.to_radians()
    }

    /// Offsets that straddle the 180-deg wrap average to the right angle (a naive mean of
    /// 89 and -89 deg would give 0), and the weights and error are the textbook ones.
    #[test]
    fn offsets_across_the_wrap() {
        let s = [
            StandardChi {
                chi_measured: d(10.0),
                sigma_measured: d(0.5),
                chi_catalogue: d(99.0),
                sigma_catalogue: d(0.1),
            },
            StandardChi {
                chi_measured: d(10.0),
                sigma_measured: d(0.5),
                chi_catalogue: d(101.0),
                sigma_catalogue: d(0.1),
            },
        ];
        let z = zero_angle(&s).unwrap();
        assert!((z.offset.to_degrees().abs() - 90.0).abs() < 1e-9, "{}", z.offset.to_degrees());
        let sig1 = (0.5f64.powi(2) + 0.1f64.powi(2)).sqrt();
        assert!((z.sigma.to_degrees() - sig1 / 2f64.sqrt()).abs() < 1e-12);
        assert_eq!(z.sense, Sense::Undetermined);
    }

    /// Three standards of different chi seen through a mirrored instrument with a 41.3 deg
    /// zero angle: the mirrored sense wins by a wide chi^2 margin and the offset comes back.
    #[test]
    fn mirrored_sense_is_recognized() {
        let off = 41.3;
        let s: Vec<StandardChi> = [12.0, 77.0, 140.0]
            .iter()
            .map(|&c: &f64| StandardChi {
                chi_measured: d(wrap_half_pi(d(off - c)).to_degrees().rem_euclid(180.0)),
                sigma_measured: d(0.3),
                chi_catalogue: d(c),
                sigma_catalogue: d(0.2),
            })
            .collect();
        let z = zero_angle(&s).unwrap();
        assert_eq!(z.sense, Sense::Mirrored);
        assert!((z.offset.to_degrees() - off).abs() < 1e-9);
        assert!(z.chi2 < 1e-12 && z.chi2_other_sense.unwrap() > 100.0);
        assert!(z.outlier.is_none() && z.sigma_scatter.unwrap() < 1e-9);
    }

    /// Four standards, one catalogued 3 deg off: its pull is the textbook
    /// `(d - mean) / sqrt(sigma^2 - 1/sum w)` (mean of four equal weights: residual 3 * 3/4 deg,
    /// error sigma sqrt(3/4)), it is named, the others are not, and the scatter-based error is
    /// the propagated one times sqrt(chi2 / 3).
    #[test]
    fn a_discrepant_standard_is_named() {
        let off = 10.0;
        let chis = [20.0, 60.0, 100.0, 150.0];
        let s: Vec<StandardChi> = chis
            .iter()
            .enumerate()
            .map(|(k, &c): (usize, &f64)| StandardChi {
                chi_measured: d(c - off),
                sigma_measured: d(0.3),
                chi_catalogue: d(c + if k == 2 { 3.0 } else { 0.0 }),
                sigma_catalogue: d(0.4),
            })
            .collect();
        let z = zero_angle(&s).unwrap();
        assert_eq!(z.sense, Sense::Iau);
        assert_eq!(z.outlier, Some(2));
        let sig = 0.5f64; // hypot(0.3, 0.4)
                          // The weighted mean on the circle (equal weights), written out here.
        let ds = [off, off, off + 3.0, off];
        let (sn, cs) = ds
            .iter()
            .fold((0.0, 0.0), |(a, b), x: &f64| (a + (2.0 * x.to_radians()).sin(), b + (2.0 * x.to_radians()).cos()));
        let mean = 0.5 * sn.atan2(cs).to_degrees();
        assert!((mean - (off + 0.75)).abs() < 0.01, "close to the arithmetic mean for a small spread");
        assert!((z.offset.to_degrees() - mean).abs() < 1e-9);
        let want = (off + 3.0 - mean) / (sig * 0.75f64.sqrt());
        assert!((z.pulls[2] - want).abs() < 1e-9, "{} vs {want}", z.pulls[2]);
        assert!(z.pulls.iter().enumerate().all(|(k, p)| k == 2 || p.abs() < OUTLIER_PULL));
        let chi2: f64 = ds.iter().map(|x| (x - mean).powi(2) / (sig * sig)).sum();
        assert!((z.chi2 - chi2).abs() < 1e-9 * chi2, "{} vs {chi2}", z.chi2);
        let birge = z.sigma * (z.chi2 / 3.0).sqrt();
        assert!((z.sigma_scatter.unwrap() - birge).abs() < 1e-15);
        assert!((z.sigma.to_degrees() - sig / 2.0).abs() < 1e-12);
    }
}
