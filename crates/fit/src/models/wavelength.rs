//! The wavelength law of section `sec:cause`: `p(lambda) / p(550 nm) = a + b lambda` (lambda in
//! nm; the paper's ray tracing gives `0.02 + 1.73e-3 lambda`), fitted across the radial models
//! of several filters.

use crate::models::radial::RadialModel;
use crate::{Error, Result};
use serde::{Deserialize, Serialize};

/// The fitted law and what went into it.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct WavelengthLaw {
    pub a: f64,
    pub b: f64,
    #[serde(rename = "sigma_a", alias = "a_err")]
    pub a_err: f64,
    #[serde(rename = "sigma_b", alias = "b_err")]
    pub b_err: f64,
    /// Per filter: wavelength (nm), mean `p` over the radius grid, its error, and the ratio
    /// to the fitted `p(550)`.
    pub lambda_nm: Vec<f64>,
    pub mean_p: Vec<f64>,
    #[serde(rename = "sigma_mean_p", alias = "mean_p_err")]
    pub mean_p_err: Vec<f64>,
    pub ratio: Vec<f64>,
    /// The radius range (arcmin) over which `p(r)` was averaged.
    #[serde(rename = "r_range_arcmin", alias = "r_range")]
    pub r_range: [f64; 2],
}

/// Calibrations of several filters for one wavelength law must be of one instrument, plate
/// and detector ([`crate::correction::setup::check_same_instrument`], each against the first;
/// their filters differ, as they should): `Err` names the two files and what differs.
pub fn check_one_instrument(cals: &[(&std::path::Path, &crate::Calibration)]) -> Result<()> {
    let setup = |c: &crate::Calibration| {
        crate::correction::setup::Setup::named(&c.instrument, &c.filter).with_product(c.provenance.product.as_ref())
    };
    let Some((first_path, first)) = cals.first() else { return Ok(()) };
    for (p, c) in &cals[1..] {
        crate::correction::setup::check_same_instrument(&setup(first), &setup(c)).map_err(|m| {
            Error::Input(format!(
                "{} and {} do not fit together: {m} (as data, then calibration); a wavelength law is of one instrument",
                first_path.display(),
                p.display()
            ))
        })?;
    }
    Ok(())
}

/// Fit `p(lambda) / p(550) = a + b lambda` (section `sec:cause`) to radial models at the given
/// wavelengths: each model's `p(r)` is averaged over `n` radii evenly spread in `r_range`
/// (arcmin), a straight line `A + B lambda` is fitted to the averages by weighted least squares,
/// and normalized so that the law is 1 at 550 nm (`a = A / p(550)`, `b = B / p(550)`).
/// With two filters the line passes through both and the errors come from theirs alone.
pub fn fit_wavelength_law(models: &[(f64, &RadialModel)], r_range: [f64; 2]) -> Result<WavelengthLaw> {
    if models.len() < 2 {
        return Err(Error::TooFewBins { used: models.len(), total: models.len(), needed: 2 });
    }
    if !(r_range[0] >= 0.0 && r_range[1] > r_range[0]) {
        return Err(Error::Input(format!("radius range {:?} arcmin is empty", r_range)));
    }
    let n = 32;
    let radii: Vec<f64> =
        (0..n).map(|j| r_range[0] + (r_range[1] - r_range[0]) * (j as f64 + 0.5) / n as f64).collect();
    let mut lam = vec![];
    let mut mp = vec![];
    let mut mpe = vec![];
    for (l, m) in models {
        if !(l.is_finite() && *l > 0.0) {
            return Err(Error::Input(format!("wavelength {l} nm is not a wavelength")));
        }
        // Gradient of the mean with respect to the coefficients: mean of r^k.
        let g: Vec<f64> = (0..m.coeffs.len())
            .map(|i| radii.iter().map(|r| r.powi((m.first_power + i) as i32)).sum::<f64>() / n as f64)
            .collect();
        let mean: f64 = g.iter().zip(&m.coeffs).map(|(a, c)| a * c).sum();
        let mut var = 0.0;
        for i in 0..g.len() {
            for j in 0..g.len() {
                var += g[i] * g[j] * m.cov_at(i, j);
            }
        }
        lam.push(*l);
        mp.push(mean);
        mpe.push(var.max(0.0).sqrt());
    }
    if lam.iter().all(|l| (l - lam[0]).abs() < 1e-9) {
        return Err(Error::Degenerate("all calibrations are at the same wavelength".into()));
    }
    // Weighted line; zero errors (noise-free models) mean equal weights.
    let use_w = mpe.iter().all(|e| *e > 0.0);
    let w: Vec<f64> = mpe.iter().map(|e| if use_w { 1.0 / (e * e) } else { 1.0 }).collect();
    let (mut s, mut sx, mut sy, mut sxx, mut sxy) = (0.0, 0.0, 0.0, 0.0, 0.0);
    for k in 0..lam.len() {
        s += w[k];
        sx += w[k] * lam[k];
        sy += w[k] * mp[k];
        sxx += w[k] * lam[k] * lam[k];
        sxy += w[k] * lam[k] * mp[k];
    }
    let det = s * sxx - sx * sx;
    let big_a = (sxx * sy - sx * sxy) / det;
    let big_b = (s * sxy - sx * sy) / det;
    let (mut vaa, mut vbb, mut vab) = (sxx / det, s / det, -sx / det);
    if !use_w {
        // Without errors the line's covariance is meaningless; report zeros.
        vaa = 0.0;
        vbb = 0.0;
        vab = 0.0;
    }
    let d = big_a + 550.0 * big_b;
    if !(d.abs() > 0.0) {
        return Err(Error::Degenerate("the fitted p(550 nm) is zero: cannot normalize the law".into()));
    }
    let (a, b) = (big_a / d, big_b / d);
    let (da_da, da_db) = (550.0 * big_b / (d * d), -550.0 * big_a / (d * d));
    let (db_da, db_db) = (-big_b / (d * d), big_a / (d * d));
    let a_err = (da_da * da_da * vaa + da_db * da_db * vbb + 2.0 * da_da * da_db * vab).max(0.0).sqrt();
    let b_err = (db_da * db_da * vaa + db_db * db_db * vbb + 2.0 * db_da * db_db * vab).max(0.0).sqrt();
    let ratio = mp.iter().map(|p| p / d).collect();
    Ok(WavelengthLaw { a, b, a_err, b_err, lambda_nm: lam, mean_p: mp, mean_p_err: mpe, ratio, r_range })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn recovers_the_papers_law_sec_cause() {
        // Scale the paper's V-band profile by the paper's law (normalized to 1 at 550 nm);
        // the fit must return the normalized coefficients.
        let law = |l: f64| 0.02 + 1.73e-3 * l;
        let v = [0.012e-2, 0.046e-2, 0.002e-2];
        let mk = |l: f64| RadialModel::new(1, v.iter().map(|c| c * law(l) / law(550.0)).collect(), [0.0, 0.0]);
        let (b, vv, i) = (mk(429.0), mk(554.0), mk(768.0));
        let fit = fit_wavelength_law(&[(429.0, &b), (554.0, &vv), (768.0, &i)], [0.5, 3.4]).unwrap();
        assert!((fit.a - 0.02 / law(550.0)).abs() < 1e-12, "{}", fit.a);
        assert!((fit.b - 1.73e-3 / law(550.0)).abs() < 1e-15, "{}", fit.b);
        assert!((fit.a + 550.0 * fit.b - 1.0).abs() < 1e-12);
        let same = fit_wavelength_law(&[(550.0, &b), (550.0, &vv)], [0.5, 3.0]);
        assert!(same.is_err());
    }
}
