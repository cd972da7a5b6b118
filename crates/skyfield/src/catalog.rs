//! Every star of a frame set in one run: detection on the first frame, o/e pairing through the
//! beam layout, and the photometry of each pair in every frame (re-centred apertures, exact
//! pixel weights, background removed vectorially), reduced by the one Stokes solver. Each row
//! carries the propagated errors and a scatter-based error (the propagated covariance scaled by
//! the modulation fit's reduced chi^2, as PCCDPACK/SOLVEPOL report the scatter of the `F_i`
//! about the fitted curve), and flags instead of silent omissions.

use crate::aperture::Weighting;
use crate::beams::BeamGeometry;
use crate::detect::{detect, pair, DetectConfig, Source};
use crate::photometry::{layout_for, photometry_sized, ApertureRadius, PhotOptions};
use crate::reduce::FrameSet;
use crate::Error;
use instrument::Instrument;
use rayon::prelude::*;

/// Catalog settings.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct CatalogConfig {
    pub detect: DetectConfig,
    /// The aperture radius: fixed, a multiple of each star's FWHM, or its best S/N.
    pub radius: ApertureRadius,
    /// Background annulus `(r_in, r_out)` (px); `None`: no background subtraction.
    pub annulus: Option<(f64, f64)>,
    pub weighting: Weighting,
    /// The Wollaston imbalance, per star: as measured, known, or estimated and applied.
    #[serde(default)]
    pub kappa: stokes::KappaCorrection,
}

impl Default for CatalogConfig {
    fn default() -> Self {
        Self {
            detect: DetectConfig::default(),
            radius: ApertureRadius::Px(8.0),
            annulus: Some((12.0, 20.0)),
            weighting: Weighting::Exact,
            kappa: stokes::KappaCorrection::None,
        }
    }
}

impl CatalogConfig {
    /// Refuse settings no star field can have (the CLI and the Python package both ask here):
    /// an aperture radius outside (0, 1000) px, a star width outside (0.5, 200) px, a
    /// threshold that is not a positive number of sigma.
    pub fn check(&self) -> Result<(), Error> {
        let (w, t) = (self.detect.fwhm_px, self.detect.threshold_sigma);
        match self.radius {
            ApertureRadius::Px(r) if !(r.is_finite() && r > 0.0 && r < 1000.0) => {
                return Err(Error::Invalid(format!("aperture {r} px: expected a radius between 0 and 1000 px")));
            }
            ApertureRadius::FwhmMultiple(k) if !(k.is_finite() && k > 0.0 && k <= 20.0) => {
                return Err(Error::Invalid(format!("aperture {k} FWHM: expected a multiple between 0 and 20")));
            }
            _ => {}
        }
        if !(w.is_finite() && w > 0.5 && w < 200.0) {
            return Err(Error::Invalid(format!("fwhm {w} px: expected a star width between 0.5 and 200 px")));
        }
        if !(t.is_finite() && t > 0.0) {
            return Err(Error::Invalid(format!("threshold {t}: must be a positive number of sigma")));
        }
        Ok(())
    }
}

/// Row flags (bits).
pub mod flags {
    /// A pixel near the centre of either image reaches saturation: not measured.
    pub const SATURATED: u32 = 1;
    /// The aperture reaches behind the focal-plane mask or off the detector: not measured.
    pub const MASK_EDGE: u32 = 2;
    /// Another source lies within two aperture radii of either image.
    pub const BLENDED: u32 = 4;
    /// The photometry failed for another reason (the message is in the row).
    pub const FAILED: u32 = 8;
    /// Names of the bits, for tables.
    pub fn names(f: u32) -> String {
        let mut v = Vec::new();
        for (b, n) in [(SATURATED, "saturated"), (MASK_EDGE, "mask_edge"), (BLENDED, "blended"), (FAILED, "failed")] {
            if f & b != 0 {
                v.push(n);
            }
        }
        v.join("|")
    }
}

/// One star of the catalog. Quantities are NaN where the star was not measured (see `flags`).
#[derive(Debug, Clone, serde::Serialize)]
pub struct Row {
    pub id: usize,
    /// o image position in the first frame (px, 0-based) and in arcmin from the centre.
    pub x: f64,
    pub y: f64,
    pub x_e: f64,
    pub y_e: f64,
    pub x_arcmin: f64,
    pub y_arcmin: f64,
    pub fwhm_px: f64,
    /// Aperture radius used (px).
    pub aperture_px: f64,
    /// Mean `f_O + f_E` over the HWP angles (e-).
    pub flux_e: f64,
    /// `F_i` per HWP angle (`eq:F`).
    pub f: Vec<f64>,
    pub q: f64,
    pub u: f64,
    pub sigma_q: f64,
    pub sigma_u: f64,
    pub cov_qu: f64,
    pub p: f64,
    pub sigma_p: f64,
    /// `chi` (deg, [0, 180)), the instrument's HWP zero angle of the filter added.
    pub chi_deg: f64,
    pub sigma_chi_deg: f64,
    pub a0: f64,
    /// Mean `kappa_j` (`eq:kappa2`) of the reduced `F_i` (after any correction).
    pub kappa: Option<f64>,
    /// The kappa applied to the fluxes before the reduction (none, known or estimated).
    pub kappa_applied: Option<f64>,
    /// Modulation chi^2 of the `F_i` about `Q cos 4 theta + U sin 4 theta` and its degrees of
    /// freedom.
    pub chi2_mod: f64,
    pub dof_mod: usize,
    /// Scatter-based errors: the propagated ones times `sqrt(chi2_mod / dof)` (equal to them
    /// on average for photon-limited data; larger when the frames vary more than photons do).
    pub sigma_q_scatter: f64,
    pub sigma_u_scatter: f64,
    pub flags: u32,
    pub note: String,
}

/// The catalog and what was found but not measured.
#[derive(Debug, Clone, serde::Serialize)]
pub struct Catalog {
    pub hwp_deg: Vec<f64>,
    pub filter: String,
    pub chi_offset_deg: f64,
    pub oe_offset_px: Option<(f64, f64)>,
    pub rows: Vec<Row>,
    /// Sources without a partner image (their positions).
    pub unpaired: Vec<(f64, f64)>,
    pub n_sources: usize,
}

/// Build the catalog of `set`.
pub fn catalog(set: &FrameSet, inst: &Instrument, cfg: &CatalogConfig) -> Result<Catalog, Error> {
    let g: BeamGeometry = layout_for(set, inst)?;
    let first = set.data.first().ok_or(Error::NoFrames)?;
    let nexp = set.files[0].len() as f64;
    let mut dcfg = cfg.detect;
    dcfg.saturation = set.conversion.det().2 * nexp;
    let sources: Vec<Source> = detect(first, &g, &dcfg);
    let (pairs, unpaired) = pair(&sources, &g, dcfg.pair_tol_px);
    let chi_off = inst.filter(&set.filter).map(|f| f.hwp_chi_offset_deg).unwrap_or(0.0);
    let opts = PhotOptions { weighting: cfg.weighting, recentre: true, kappa: cfg.kappa };
    // Stars are measured independently: in parallel, in catalog order.
    let rows: Vec<Row> = pairs
        .par_iter()
        .enumerate()
        .map(|(id, pr)| {
            let (so, se) = (&sources[pr.o], &sources[pr.e]);
            let (xa, ya) = inst.pixel_to_arcmin(so.x, so.y);
            let mut flags = 0;
            if so.saturated || se.saturated {
                flags |= flags::SATURATED;
            }
            // Blended: another source within two aperture radii (the radius this star will get;
            // for the best-S/N choice, its largest candidate's typical 2 FWHM).
            let r_nominal = match cfg.radius {
                ApertureRadius::Px(r) => r,
                ApertureRadius::FwhmMultiple(k) => k * so.fwhm_px,
                ApertureRadius::BestSnr => 2.0 * so.fwhm_px,
            };
            let blend_r = 2.0 * if r_nominal.is_finite() { r_nominal } else { 2.0 * cfg.detect.fwhm_px };
            let near = |s: &Source, skip: [usize; 2]| {
                sources.iter().enumerate().any(|(k, t)| !skip.contains(&k) && (t.x - s.x).hypot(t.y - s.y) < blend_r)
            };
            if near(so, [pr.o, pr.e]) || near(se, [pr.o, pr.e]) {
                flags |= flags::BLENDED;
            }
            let nan = f64::NAN;
            let mut row = Row {
                id: id + 1,
                x: so.x,
                y: so.y,
                x_e: se.x,
                y_e: se.y,
                x_arcmin: xa,
                y_arcmin: ya,
                fwhm_px: so.fwhm_px,
                aperture_px: nan,
                flux_e: nan,
                f: vec![],
                q: nan,
                u: nan,
                sigma_q: nan,
                sigma_u: nan,
                cov_qu: nan,
                p: nan,
                sigma_p: nan,
                chi_deg: nan,
                sigma_chi_deg: nan,
                a0: nan,
                kappa: None,
                kappa_applied: None,
                chi2_mod: nan,
                dof_mod: 0,
                sigma_q_scatter: nan,
                sigma_u_scatter: nan,
                flags,
                note: String::new(),
            };
            if flags & flags::SATURATED != 0 {
                row.note = "saturated: not measured".into();
                return row;
            }
            // The detection's FWHM of the o image, or the expected one if it could not be measured.
            let fwhm = if so.fwhm_px.is_finite() && so.fwhm_px > 0.0 { so.fwhm_px } else { cfg.detect.fwhm_px };
            match photometry_sized(set, &g, so.x, so.y, cfg.radius, fwhm, cfg.annulus, &opts) {
                Ok((ph, radius)) => {
                    row.aperture_px = radius;
                    let r = &ph.reduction;
                    let n = r.n;
                    row.flux_e = ph.f_o.iter().zip(&ph.f_e).map(|(a, b)| a + b).sum::<f64>() / n as f64;
                    row.f = r.f.clone();
                    // In the sky's frame: the filter's HWP zero angle turns q, u as it turns chi.
                    let sky = r.qu.rotated(chi_off.to_radians());
                    row.q = sky.q;
                    row.u = sky.u;
                    row.sigma_q = sky.var_q.sqrt();
                    row.sigma_u = sky.var_u.sqrt();
                    row.cov_qu = sky.cov_qu;
                    row.p = r.p;
                    row.sigma_p = r.sigma_p;
                    row.chi_deg = (r.chi.to_degrees() + chi_off).rem_euclid(180.0);
                    row.sigma_chi_deg = r.sigma_chi.to_degrees();
                    row.a0 = r.a0;
                    row.kappa = r.kappa_mean;
                    row.kappa_applied = ph.kappa_applied;
                    // Modulation chi^2: F_i about a_0 + Q cos 4theta + U sin 4theta (a_0 is fitted
                    // too, as the Wollaston's transmission offset makes one).
                    let chi2: f64 = r
                        .theta
                        .iter()
                        .zip(&r.f)
                        .zip(&r.sigma_f)
                        .map(|((t, f), s)| {
                            let m = r.a0 + r.qu.q * (4.0 * t).cos() + r.qu.u * (4.0 * t).sin();
                            ((f - m) / s).powi(2)
                        })
                        .sum();
                    let dof = n.saturating_sub(3);
                    row.chi2_mod = chi2;
                    row.dof_mod = dof;
                    let scale = if dof > 0 { (chi2 / dof as f64).sqrt() } else { nan };
                    row.sigma_q_scatter = row.sigma_q * scale;
                    row.sigma_u_scatter = row.sigma_u * scale;
                }
                Err(e) => {
                    let m = e.to_string();
                    row.flags |= if m.contains("behind the mask") || m.contains("off the") {
                        flags::MASK_EDGE
                    } else if m.contains("saturated") {
                        flags::SATURATED
                    } else {
                        flags::FAILED
                    };
                    row.note = m;
                }
            }
            row
        })
        .collect();
    Ok(Catalog {
        hwp_deg: set.angles_deg.clone(),
        filter: set.filter.clone(),
        chi_offset_deg: chi_off,
        oe_offset_px: g.oe_offset,
        rows,
        unpaired: unpaired.iter().map(|&k| (sources[k].x, sources[k].y)).collect(),
        n_sources: sources.len(),
    })
}
