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
//! each star's pull against the weighted circular mean of the OTHERS (leave-one-out: its
//! residual over `sqrt(sigma_i^2 + 1 / sum_{k != i} w_k)`, so a grossly wrong star cannot hide
//! by dragging the mean toward itself), a scatter-based error (the propagated one times
//! `sqrt(chi^2 / dof)`, the Birge ratio) beside the propagated one, and the star that disagrees
//! (the largest pull beyond [`OUTLIER_PULL`], with three or more stars: with two, either could
//! be the wrong one). Such a star is left out and the mean, the sense, the errors and the
//! pulls are found again from the rest, as long as more than half the stars remain: a star
//! catalogued 80 deg off (a misidentification) is named and does not move the result.

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
    /// largest one, with three or more standards (the first of `excluded`).
    pub outlier: Option<usize>,
    /// Indices (into the standards given) of the stars left out of the mean, worst first; the
    /// offset, errors, chi^2 and sense are those of the others. `offsets` and `pulls` still
    /// hold every star (an excluded star's pull is against the mean of the kept ones).
    pub excluded: Vec<usize>,
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

/// One sense's offsets `d` (all usable stars) with weights `w`, the worst disagreeing star left
/// out at a time (leave-one-out pull beyond [`OUTLIER_PULL`], while three or more remain and
/// more than half would stay).
struct Clipped {
    kept: Vec<usize>,
    excluded: Vec<usize>,
    mean: f64,
    chi2: f64,
    pulls: Vec<f64>,
}

fn clip(d: &[f64], w: &[f64]) -> Clipped {
    let mut kept: Vec<usize> = (0..d.len()).collect();
    let mut excluded = Vec::new();
    loop {
        let (mean, chi2) = mean_offset(
            &kept.iter().map(|&k| d[k]).collect::<Vec<f64>>(),
            &kept.iter().map(|&k| w[k]).collect::<Vec<f64>>(),
        );
        let pulls = loo_pulls(&kept, d, w);
        if kept.len() >= 3 && 2 * (kept.len() - 1) > d.len() {
            let (k, worst) =
                kept.iter().map(|&k| (k, pulls[k].abs())).fold((0, 0.0), |a, b| if b.1 > a.1 { b } else { a });
            if worst > OUTLIER_PULL {
                kept.retain(|&j| j != k);
                excluded.push(k);
                continue;
            }
        }
        return Clipped { kept, excluded, mean, chi2, pulls };
    }
}

/// Leave-one-out pulls: each star's offset against the weighted circular mean of the kept
/// stars other than itself, over `sqrt(1/w_i + 1/sum_{kept, k != i} w_k)` (0 with no other).
fn loo_pulls(kept: &[usize], d: &[f64], w: &[f64]) -> Vec<f64> {
    (0..d.len())
        .map(|i| {
            let others: Vec<usize> = kept.iter().copied().filter(|&k| k != i).collect();
            if others.is_empty() {
                return 0.0;
            }
            let wo: Vec<f64> = others.iter().map(|&k| w[k]).collect();
            let (m, _) = mean_offset(&others.iter().map(|&k| d[k]).collect::<Vec<f64>>(), &wo);
            let v = 1.0 / w[i] + 1.0 / wo.iter().sum::<f64>();
            wrap_half_pi(d[i] - m) / v.sqrt()
        })
        .collect()
}

/// The zero angle and sense from `stds` (see the module docs). `None` when no standard has a
/// finite, positive error.
///
/// Each sense is fitted with its own outliers left out (a wrong star can make the wrong sense
/// look better while it is in); the sense is the one whose kept stars scatter less (reduced
/// chi^2), decided only when the kept stars' catalogued angles differ by more than five times
/// their largest error. `chi2_other_sense` is the other sense's chi^2 over its own kept stars.
pub fn zero_angle(stds: &[StandardChi]) -> Option<ZeroAngle> {
    // Indices (into `stds`) of the usable standards.
    let idx: Vec<usize> = stds
        .iter()
        .enumerate()
        .filter(|(_, s)| {
            let v = s.sigma_measured.powi(2) + s.sigma_catalogue.powi(2);
            s.chi_measured.is_finite() && s.chi_catalogue.is_finite() && v.is_finite() && v > 0.0
        })
        .map(|(i, _)| i)
        .collect();
    if idx.is_empty() {
        return None;
    }
    let ok: Vec<&StandardChi> = idx.iter().map(|&i| &stds[i]).collect();
    let w: Vec<f64> = ok.iter().map(|s| 1.0 / (s.sigma_measured.powi(2) + s.sigma_catalogue.powi(2))).collect();
    let iau: Vec<f64> = ok.iter().map(|s| wrap_half_pi(s.chi_catalogue - s.chi_measured)).collect();
    let mir: Vec<f64> = ok.iter().map(|s| wrap_half_pi(s.chi_catalogue + s.chi_measured)).collect();
    let (ci, cm) = (clip(&iau, &w), clip(&mir, &w));
    // The sense can be told only when the kept stars' catalogued angles differ.
    let decidable = |c: &Clipped| {
        let c0 = ok[c.kept[0]].chi_catalogue;
        let spread = c.kept.iter().map(|&k| wrap_half_pi(ok[k].chi_catalogue - c0).abs()).fold(0.0, f64::max);
        let sig_max = c.kept.iter().map(|&k| ok[k].sigma_catalogue.max(ok[k].sigma_measured)).fold(0.0, f64::max);
        c.kept.len() >= 2 && spread > 5.0 * sig_max
    };
    let reduced = |c: &Clipped| c.chi2 / (c.kept.len().max(2) - 1) as f64;
    let (sense, best, offsets, other) = if !decidable(&ci) {
        (Sense::Undetermined, ci, iau, None)
    } else if !decidable(&cm) || reduced(&ci) <= reduced(&cm) {
        let o = cm.chi2;
        (Sense::Iau, ci, iau, Some(o))
    } else {
        let o = ci.chi2;
        (Sense::Mirrored, cm, mir, Some(o))
    };
    let sw: f64 = best.kept.iter().map(|&k| w[k]).sum();
    let sigma = 1.0 / sw.sqrt();
    let dof = best.kept.len() - 1;
    let sigma_scatter = (dof > 0).then(|| sigma * (best.chi2 / dof as f64).sqrt());
    let excluded: Vec<usize> = best.excluded.iter().map(|&k| idx[k]).collect();
    Some(ZeroAngle {
        offset: best.mean,
        sigma,
        chi2: best.chi2,
        dof,
        sense,
        chi2_other_sense: other,
        offsets,
        pulls: best.pulls,
        sigma_scatter,
        outlier: excluded.first().copied(),
        excluded,
    })
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

    /// Four standards, one catalogued 3 deg off: its leave-one-out pull is the textbook
    /// `(d - mean of the others) / sqrt(sigma^2 + sigma^2 / 3)` (the three others agree
    /// exactly: residual 3 deg), it is named and left out, the others are not, and the result
    /// is the three others' (offset exact, chi^2 0, error sigma / sqrt 3).
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
        assert_eq!(z.excluded, vec![2]);
        let sig = 0.5f64; // hypot(0.3, 0.4)
        let want = 3.0 / (sig * (1.0 + 1.0 / 3.0f64).sqrt());
        assert!((z.pulls[2] - want).abs() < 1e-9, "{} vs {want}", z.pulls[2]);
        assert!(z.pulls.iter().enumerate().all(|(k, p)| k == 2 || p.abs() < 1e-9), "{:?}", z.pulls);
        assert!((z.offset.to_degrees() - off).abs() < 1e-9);
        assert!(z.chi2 < 1e-18 && z.dof == 2);
        assert!((z.sigma.to_degrees() - sig / 3f64.sqrt()).abs() < 1e-12);
        assert!(z.sigma_scatter.unwrap() < 1e-9);
    }

    /// Three good standards (offset 41.3 deg, errors 0.3 deg, one measured 0.2 deg off so the
    /// mean is not exact) and one catalogued 80 deg off: the bad one is named and left out,
    /// and the offset is the three good ones' weighted mean (written out here), within its
    /// error of the truth. A plain mean with the bad star would be ~10 deg away and would
    /// make the good stars the outliers.
    #[test]
    fn a_star_80_deg_off_does_not_drag_the_mean() {
        let off = 41.3;
        let rows = [(15.0, 0.0, 0.0), (70.0, 0.2, 0.0), (125.0, 0.0, 0.0), (160.0, 0.0, 80.0)];
        let s: Vec<StandardChi> = rows
            .iter()
            .map(|&(c, dm, dc): &(f64, f64, f64)| StandardChi {
                chi_measured: d((c - off + dm).rem_euclid(180.0)),
                sigma_measured: d(0.3),
                chi_catalogue: d((c + dc).rem_euclid(180.0)),
                sigma_catalogue: d(0.1),
            })
            .collect();
        let z = zero_angle(&s).unwrap();
        assert_eq!(z.outlier, Some(3), "{z:?}");
        assert_eq!(z.excluded, vec![3]);
        assert_eq!(z.sense, Sense::Iau);
        let mean = off - 0.2 / 3.0; // equal weights, small angles: the arithmetic mean
        assert!((z.offset.to_degrees() - mean).abs() < 1e-4, "{} vs {mean}", z.offset.to_degrees());
        assert!((z.offset.to_degrees() - off).abs() < 3.0 * z.sigma.to_degrees());
        assert!(z.pulls[3].abs() > 100.0 && z.pulls[..3].iter().all(|p| p.abs() < 1.0), "{:?}", z.pulls);
        // With two stars nothing is left out: either could be the wrong one.
        let z2 = zero_angle(&s[2..]).unwrap();
        assert!(z2.excluded.is_empty() && z2.outlier.is_none());
    }
}
