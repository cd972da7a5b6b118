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
}

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
    Some(ZeroAngle { offset, sigma: 1.0 / sw.sqrt(), chi2, dof: ok.len() - 1, sense, chi2_other_sense: other, offsets })
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
    }
}
