//! Every star of a frame set in one run: detection on the first frame, o/e pairing through the
//! beam layout, and the photometry of each pair in every frame (re-centred apertures, exact
//! pixel weights, background removed vectorially), reduced by the one Stokes solver. Each row
//! carries the propagated errors and a scatter-based error (the propagated covariance scaled by
//! the modulation fit's reduced chi^2, as PCCDPACK/SOLVEPOL report the scatter of the `F_i`
//! about the fitted curve), and flags instead of silent omissions.

use crate::aperture::Weighting;
use crate::beams::BeamGeometry;
use crate::calib::ReadOptions;
use crate::detect::{detect_reusing, pair, DetectConfig, Source};
use crate::layout::layout_of_image;
use crate::photometry::{
    candidate_radii, check_placement, circular_solver, finish, finish_circular, layout_for, measure_frame, pick_radius,
    Aperture, ApertureRadius, FrameFacts, FrameFluxes, Partial, PhotOptions,
};
use crate::reduce::{DiskFrames, FrameSet, FrameSource};
use crate::Warning;
use crate::{Error, Unmeasurable};
use instrument::Instrument;
use rayon::prelude::*;
use std::path::{Path, PathBuf};

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
    /// Measure the stars even when their photometry is estimated beyond
    /// [`MAX_PIXEL_VISITS`] ([`photometry_work`]).
    #[serde(default)]
    pub force: bool,
}

/// The background annulus `(r_in, r_out)` (px) of `instpol catalog` and `instpol.catalog`
/// unless told otherwise.
pub const DEFAULT_ANNULUS_PX: (f64, f64) = (12.0, 20.0);

impl CatalogConfig {
    /// The settings of `instpol catalog` but the stars' expected FWHM and the aperture (what a
    /// night's catalog unit gives): detection at `DetectConfig`'s defaults, the annulus
    /// [`DEFAULT_ANNULUS_PX`], exact pixel weights, no kappa correction.
    pub fn with_detection(fwhm_px: f64, radius: ApertureRadius) -> Self {
        CatalogConfig {
            detect: DetectConfig { fwhm_px, ..Default::default() },
            radius,
            annulus: Some(DEFAULT_ANNULUS_PX),
            weighting: Weighting::Exact,
            kappa: stokes::KappaCorrection::None,
            force: false,
        }
    }
}

/// The most pixel visits a catalog's photometry makes unless told it may: about a minute of
/// one core. A detection threshold far below the noise (thousands of "stars") with an annulus
/// of a thousand pixels took hours, with no estimate.
pub const MAX_PIXEL_VISITS: f64 = 2e10;

/// The pixel visits of measuring `n_stars` stars in `n_frames` frames of `nx x ny` px with
/// `cfg`: each star's o and e image, each within the annulus's outer circle (or the aperture's,
/// at least 3 FWHM), no more than the detector.
pub fn photometry_work(cfg: &CatalogConfig, n_stars: usize, n_frames: usize, nx: usize, ny: usize) -> f64 {
    let fwhm = cfg.detect.fwhm_px;
    let r_ap = match cfg.radius {
        ApertureRadius::Px(r) => r,
        ApertureRadius::FwhmMultiple(k) => k * fwhm,
        ApertureRadius::BestSnr => 3.0 * fwhm,
    };
    let r = cfg.annulus.map_or(r_ap, |(_, b)| b).max(r_ap).max(3.0 * fwhm);
    let area = (std::f64::consts::PI * r * r).min((nx * ny) as f64);
    2.0 * n_stars as f64 * n_frames as f64 * area
}

impl Default for CatalogConfig {
    fn default() -> Self {
        Self {
            detect: DetectConfig::default(),
            radius: ApertureRadius::Px(8.0),
            annulus: Some((12.0, 20.0)),
            weighting: Weighting::Exact,
            kappa: stokes::KappaCorrection::None,
            force: false,
        }
    }
}

impl CatalogConfig {
    /// Refuse settings no star field can have (the CLI and the Python package both ask here):
    /// an aperture radius outside (0, 1000) px, a star width outside (0.5, 200) px, a
    /// threshold that is not a positive number of sigma, a sky annulus that is not
    /// `0 <= inner < outer` px, a known kappa outside (-1, 1) (`eq:kappa2`).
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
        if let Some((a, b)) = self.annulus {
            if !(a.is_finite() && b.is_finite() && a >= 0.0 && b > a) {
                return Err(Error::Invalid(format!("annulus ({a}, {b}) px: expected radii 0 <= inner < outer")));
            }
        }
        if let stokes::KappaCorrection::Known(k) = self.kappa {
            stokes::KappaCorrection::known(k).map_err(|e| Error::Invalid(format!("kappa {k}: {e}")))?;
        }
        let tol = self.detect.pair_tol_px;
        if !(tol.is_finite() && tol > 0.0 && tol <= 20.0) {
            return Err(Error::Invalid(format!("pair-tol {tol} px: expected a distance between 0 and 20 px")));
        }
        Ok(())
    }
}

/// An aperture radius to measure a star with, and whether the aperture fits where it is.
type Try = (f64, Result<(), Error>);

/// Row flags (bits).
pub mod flags {
    /// A pixel near the centre of either image reaches saturation: not measured.
    pub const SATURATED: u32 = 1;
    /// The star, its aperture or its e image reaches behind the focal-plane mask, off the
    /// detector or into the gap between chips: not measured.
    pub const MASK_EDGE: u32 = 2;
    /// Another source lies within two aperture radii of either image.
    pub const BLENDED: u32 = 4;
    /// The photometry failed for another reason (the message is in the row).
    pub const FAILED: u32 = 8;
    /// With repeated HWP positions: some exposure, measured on its own, disagrees with its
    /// repeats or lost light (`crate::photometry::ExposureCheck`); the star is measured, the
    /// exposures are in the row's `outlier_exposures`.
    pub const OUTLIER_EXPOSURE: u32 = 16;
    /// Its o or e image is also an image of another star (maskless layouts: a star whose o
    /// image falls on a neighbour's e image): the two overlap on the detector and no aperture
    /// separates them, so the star is not measured (its q, u would mix the two stars').
    pub const OVERLAP: u32 = 32;
    /// The flags under which a star is not measured.
    pub const NOT_MEASURED: u32 = SATURATED | OVERLAP;
    /// Names of the bits, for tables.
    pub fn names(f: u32) -> String {
        let mut v = Vec::new();
        for (b, n) in [
            (SATURATED, "saturated"),
            (MASK_EDGE, "mask_edge"),
            (BLENDED, "blended"),
            (FAILED, "failed"),
            (OUTLIER_EXPOSURE, "outlier_exposure"),
            (OVERLAP, "overlap"),
        ] {
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
    /// With repeated HWP positions ([`check_exposures`]): the exposures (0-based, in the order
    /// the frames were given) flagged for this star; empty otherwise.
    pub outlier_exposures: Vec<usize>,
    /// Through a quarter-wave plate: `V/I` (IAU sign) and its error (`stokes::circular`); the
    /// linear quantities above are then NaN (the plate's 2- and 4-position sets do not
    /// determine them). `None` (and not written) for a half-wave plate.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub v: Option<f64>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub sigma_v: Option<f64>,
    /// The o image's sky position (deg) through the celestial WCS of the first exposure's file
    /// holding it ([`sky_positions`]); `None` (and not written) when that file has no WCS this
    /// reads.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub ra_deg: Option<f64>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub dec_deg: Option<f64>,
}

/// The camera transform a two-camera catalog was measured with.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct CameraTransform {
    /// `[a, b, c, d, e, f]`: `(x', y') = (a x + b y + c, d x + e y + f)`.
    pub transform: [f64; 6],
    /// Measured from star pairs: the fit's RMS residual (px); `None` when the instrument file
    /// gave the transform.
    pub residual_rms_px: Option<f64>,
    pub pairs: Option<usize>,
}

/// The catalog and what was found but not measured.
#[derive(Debug, Clone, serde::Serialize)]
pub struct Catalog {
    pub hwp_deg: Vec<f64>,
    pub filter: String,
    pub chi_offset_deg: f64,
    pub oe_offset_px: Option<(f64, f64)>,
    /// Two cameras: the transform from o camera to (turned) e camera pixels `[a, b, c, d, e,
    /// f]`, and when it was measured from the frames' stars, its RMS residual (px) and the
    /// star pairs it rests on (absent for other layouts).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub camera_transform: Option<CameraTransform>,
    /// A quarter-wave plate's zero angle (deg) added to the plate angles: the rows carry `V/I`
    /// ([`Row::v`]). Absent for a half-wave plate.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub qwp_zero_angle_deg: Option<f64>,
    pub rows: Vec<Row>,
    /// Sources without a partner image (their positions).
    pub unpaired: Vec<(f64, f64)>,
    /// Why each of [`Catalog::unpaired`] has no partner, in the same order.
    pub unpaired_why: Vec<crate::detect::Unpaired>,
    /// How far the unpaired sources' other images sit from the layout's prediction: median
    /// `(dx, dy)` px and how many agree with it within 1 px (`detect::unpaired_shift`).
    pub unpaired_shift_px: Option<(f64, f64, usize)>,
    pub n_sources: usize,
    /// Each frame's shift and rotation against the first, measured from the measured stars'
    /// o-image centroids (`crate::align`); empty with fewer than three measured stars.
    pub alignment: Vec<FrameAlignment>,
    /// With repeated HWP positions ([`check_exposures`]): each exposure and how many stars
    /// flag it; `None` when no position repeats (nothing to compare an exposure with).
    pub exposures: Option<Vec<ExposureSummary>>,
    /// Each exposure's file (a chip instrument's: its first chip file) and HWP angle (deg), in
    /// the order the frames were given: what undoing a telescope exposure by exposure needs
    /// (their headers' parallactic angles). Set by [`catalog_files`]; empty otherwise.
    #[serde(skip)]
    pub frames: Vec<(PathBuf, f64)>,
    /// What the catalog is: instrument, filter, plate, the sky frame of its rows' `q, u`, the
    /// detector (set by [`catalog_files`]; written into its table by [`Catalog::to_table`]).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub product: Option<crate::provenance::Product>,
    /// How the files given were grouped into exposures, for an instrument whose chips come one
    /// per file (set by [`catalog_files`]; absent otherwise).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub grouping: Option<crate::calib::Grouping>,
}

/// One exposure across the catalog's stars (the per-exposure checks of [`check_exposures`]).
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct ExposureSummary {
    /// 0-based, in the order the frames were given.
    pub index: usize,
    pub file: String,
    pub hwp_deg: f64,
    /// Stars measured in it, and those that flag it.
    pub n_stars: usize,
    pub n_stars_flagged: usize,
    /// Median over the stars of their light in this exposure over their median exposure's.
    pub median_transparency: f64,
    /// Flagged by at least half the stars measured in it (a fault of the exposure, not of
    /// one star's aperture).
    pub outlier: bool,
}

/// One frame's alignment against the first (JSON and the catalog's report).
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct FrameAlignment {
    pub hwp_deg: f64,
    /// Shift of the stars' centroid (px).
    pub dx_px: f64,
    pub dy_px: f64,
    /// Rotation about the stars' centroid (deg, counter-clockwise in pixels) and its error.
    pub rotation_deg: f64,
    pub sigma_rotation_deg: f64,
    pub scale: f64,
    /// rms residual of the stars about the similarity transform (px, per coordinate).
    pub rms_px: f64,
    pub n_stars: usize,
    /// The rotation exceeds [`ROTATION_SIGNIFICANT_SIGMA`] times its error.
    pub rotation_significant: bool,
}

/// A rotation beyond this many sigma is reported as measured (below, the frames are taken as
/// shifted only).
pub const ROTATION_SIGNIFICANT_SIGMA: f64 = 5.0;

/// Every frame's similarity transform against the first from the stars' o centroids per frame
/// (`centres[star][frame] = [x_o, y_o, x_e, y_e]`).
pub fn frame_alignment(hwp_deg: &[f64], centres: &[&Vec<[f64; 4]>]) -> Vec<FrameAlignment> {
    if centres.len() < 3 {
        return vec![];
    }
    let from: Vec<(f64, f64)> = centres.iter().map(|c| (c[0][0], c[0][1])).collect();
    hwp_deg
        .iter()
        .enumerate()
        .filter_map(|(i, &h)| {
            let to: Vec<(f64, f64)> =
                centres.iter().map(|c| c.get(i).map_or((f64::NAN, f64::NAN), |v| (v[0], v[1]))).collect();
            let t = crate::align::similarity(&from, &to)?;
            Some(FrameAlignment {
                hwp_deg: h,
                dx_px: t.dx,
                dy_px: t.dy,
                rotation_deg: t.rotation.to_degrees(),
                sigma_rotation_deg: t.sigma_rotation.to_degrees(),
                scale: t.scale,
                rms_px: t.rms_px,
                n_stars: t.n_stars,
                rotation_significant: i > 0 && t.rotation_significant(ROTATION_SIGNIFICANT_SIGMA),
            })
        })
        .collect()
}

impl Catalog {
    /// Turn every row's `q, u` (with their covariance and scatter-based errors) and `chi` by
    /// the instrument's position angle on the sky `pa_deg`: from the instrument's frame into the
    /// celestial one, north through east (`mueller::Frame::Celestial`). `P` and the errors of
    /// `P` and `chi` do not change under a turn.
    pub fn turn_onto_sky(&mut self, pa_deg: f64) {
        let frame = mueller::Frame::Celestial { zero_angle_deg: self.chi_offset_deg, position_angle_deg: pa_deg };
        for r in &mut self.rows {
            let qu = mueller::Qu::from_sigmas(r.q, r.u, r.sigma_q, r.sigma_u, r.cov_qu);
            let t = frame.onto_sky(&qu);
            // The scatter-based errors are the propagated ones times one factor (`Row`).
            let k = if r.sigma_q > 0.0 { r.sigma_q_scatter / r.sigma_q } else { f64::NAN };
            (r.q, r.u, r.cov_qu) = (t.q, t.u, t.cov_qu);
            (r.sigma_q, r.sigma_u) = (t.var_q.sqrt(), t.var_u.sqrt());
            (r.sigma_q_scatter, r.sigma_u_scatter) = (k * r.sigma_q, k * r.sigma_u);
            r.chi_deg = mueller::fold_pi((r.chi_deg + pa_deg).to_radians()).to_degrees();
        }
    }

    /// The catalog as a table (one row per paired star; `f_0`, `f_1`, ... the `F_i` of each
    /// HWP angle), with units (`pix`, `arcmin`, `deg`, `ct` for photo-electrons, the FITS standard having no electron unit; q, u and their errors are
    /// dimensionless fractions), for [`crate::table::Table::write`] in any format.
    pub fn to_table(&self) -> crate::table::Table {
        use crate::table::{Column, Table};
        let r = &self.rows;
        let col = |g: fn(&Row) -> f64| r.iter().map(g).collect::<Vec<f64>>();
        let fr = |name: &str, g: fn(&Row) -> f64, d: &str| Column::f64(name, None, d, col(g));
        let mut c = vec![
            Column::i64("id", "star number", r.iter().map(|x| x.id as i64).collect()),
            Column::f64("x", Some("pix"), "o image x in the first frame (0-based)", col(|x| x.x)),
            Column::f64("y", Some("pix"), "o image y in the first frame (0-based)", col(|x| x.y)),
            Column::f64("x_e", Some("pix"), "e image x (0-based)", col(|x| x.x_e)),
            Column::f64("y_e", Some("pix"), "e image y (0-based)", col(|x| x.y_e)),
            Column::f64("x_arcmin", Some("arcmin"), "x from the detector centre", col(|x| x.x_arcmin)),
            Column::f64("y_arcmin", Some("arcmin"), "y from the detector centre", col(|x| x.y_arcmin)),
            Column::f64("fwhm_px", Some("pix"), "star FWHM", col(|x| x.fwhm_px)),
            Column::f64("aperture_px", Some("pix"), "aperture radius used", col(|x| x.aperture_px)),
            Column::f64("flux_e", Some("ct"), "mean f_O + f_E over the HWP angles, photo-electrons", col(|x| x.flux_e)),
            fr("q", |x| x.q, "Q/I (dimensionless fraction)"),
            fr("u", |x| x.u, "U/I (dimensionless fraction)"),
            fr("sigma_q", |x| x.sigma_q, "1-sigma error of q"),
            fr("sigma_u", |x| x.sigma_u, "1-sigma error of u"),
            fr("cov_qu", |x| x.cov_qu, "covariance of q and u"),
            fr("p", |x| x.p, "polarization degree (fraction)"),
            fr("sigma_p", |x| x.sigma_p, "1-sigma error of p"),
            Column::f64(
                "chi_deg",
                Some("deg"),
                "polarization angle, HWP zero angle (and any position angle on the sky) added",
                col(|x| x.chi_deg),
            ),
            Column::f64(
                crate::table::ZERO_ANGLE_COLUMN,
                Some("deg"),
                "HWP zero angle already applied to q, u, chi (instpol correct applies only the calibration's difference)",
                vec![self.chi_offset_deg; r.len()],
            ),
            Column::f64("sigma_chi_deg", Some("deg"), "1-sigma error of chi", col(|x| x.sigma_chi_deg)),
            fr("a0", |x| x.a0, "a0 of the modulation fit"),
            fr("kappa", |x| x.kappa.unwrap_or(f64::NAN), "kappa of the modulation fit (NaN: not fitted)"),
            fr(
                "kappa_applied",
                |x| x.kappa_applied.unwrap_or(f64::NAN),
                "Wollaston kappa applied to the fluxes (NaN: none)",
            ),
            fr("chi2_mod", |x| x.chi2_mod, "modulation chi^2"),
            Column::i64("dof_mod", "degrees of freedom of chi2_mod", r.iter().map(|x| x.dof_mod as i64).collect()),
            fr("sigma_q_scatter", |x| x.sigma_q_scatter, "scatter-based error of q"),
            fr("sigma_u_scatter", |x| x.sigma_u_scatter, "scatter-based error of u"),
            Column::text(
                "flags",
                "saturated|mask_edge|blended|failed|outlier_exposure",
                r.iter().map(|x| flags::names(x.flags)).collect(),
            ),
            Column::text("note", "why a star was not measured", r.iter().map(|x| x.note.clone()).collect()),
            Column::i64(
                "n_outlier_exposures",
                "exposures flagged for this star (repeated HWP positions; 0 otherwise)",
                r.iter().map(|x| x.outlier_exposures.len() as i64).collect(),
            ),
            Column::text(
                "outlier_exposures",
                "0-based indices (frames in the order given) of the flagged exposures, ';'-separated",
                r.iter()
                    .map(|x| x.outlier_exposures.iter().map(|i| i.to_string()).collect::<Vec<_>>().join(";"))
                    .collect(),
            ),
        ];
        if self.qwp_zero_angle_deg.is_some() {
            // Through a quarter-wave plate: V/I, the linear columns above being NaN.
            let v = |g: fn(&Row) -> Option<f64>| r.iter().map(|x| g(x).unwrap_or(f64::NAN)).collect::<Vec<f64>>();
            c.push(Column::f64("v", None, "V/I (dimensionless fraction, IAU sign)", v(|x| x.v)));
            c.push(Column::f64("sigma_v", None, "1-sigma error of v", v(|x| x.sigma_v)));
        }
        if let Some(pa) = self.product.as_ref().and_then(|p| p.position_angle_deg) {
            // On a rotator: the position angle the rows were turned by, beside the zero angle.
            let at = c.iter().position(|x| x.name == crate::table::ZERO_ANGLE_COLUMN).map_or(c.len(), |i| i + 1);
            let what = "instrument's position angle on the sky already applied to q, u, chi (north through east)";
            c.insert(at, Column::f64(crate::table::SKY_PA_COLUMN, Some("deg"), what, vec![pa; r.len()]));
        }
        if r.iter().any(|x| x.ra_deg.is_some()) {
            // The frames' celestial WCS: columns only when a row has a position.
            let v = |g: fn(&Row) -> Option<f64>| r.iter().map(|x| g(x).unwrap_or(f64::NAN)).collect::<Vec<f64>>();
            c.insert(3, Column::f64("ra_deg", Some("deg"), "o image RA from the frame's WCS", v(|x| x.ra_deg)));
            c.insert(4, Column::f64("dec_deg", Some("deg"), "o image Dec from the frame's WCS", v(|x| x.dec_deg)));
        }
        for i in 0..self.hwp_deg.len() {
            let v = r.iter().map(|x| x.f.get(i).copied().unwrap_or(f64::NAN)).collect();
            c.push(Column::f64(&format!("f_{i}"), None, &format!("F_i (eq:F) at HWP {} deg", self.hwp_deg[i]), v));
        }
        Table { product: self.product.clone(), ..Table::new(c) }
    }
}

/// The catalog of frame files and the warnings of their reading (those of
/// [`FrameSet::from_frames`]); `on_read` is called once per exposure read (a progress bar).
/// Without repeated HWP positions the frames are read one at a time ([`DiskFrames`]); with
/// repeats every exposure is also measured alone ([`check_exposures`]), which needs them all
/// in memory.
pub fn catalog_files(
    paths: &[PathBuf],
    inst: &Instrument,
    opts: &ReadOptions,
    cfg: &CatalogConfig,
    on_read: Box<dyn Fn() + Send + Sync>,
) -> Result<(Catalog, Vec<Warning>), Error> {
    let mut disk = DiskFrames::open(paths, inst, opts, true)?;
    let theta: Vec<f64> = disk.exposure_angles_deg().iter().map(|a| a.to_radians()).collect();
    let exposures = disk.exposures();
    let (mut cat, mut warnings) = if stokes::repeats::has_repeats(&theta) {
        drop(disk);
        let frames = crate::reduce::read_frames_with(paths, inst, opts, &on_read)?;
        let singles = frames.clone();
        let set = FrameSet::from_frames(frames, inst, true)?;
        let mut cat = catalog(&set, inst, cfg)?;
        check_exposures(&mut cat, &singles, &set, inst, cfg)?;
        (cat, set.warnings)
    } else {
        disk.set_on_read(on_read);
        let cat = catalog_of(&disk, inst, cfg)?;
        (cat, disk.bad_pixel_warnings()?)
    };
    cat.grouping = crate::calib::Grouping::of(inst, opts, paths.len(), exposures.len());
    if let Some((first, _)) = exposures.first() {
        let xy: Vec<(f64, f64)> = cat.rows.iter().map(|r| (r.x, r.y)).collect();
        for (r, sky) in cat.rows.iter_mut().zip(sky_positions(paths, first, inst, opts, &xy)) {
            (r.ra_deg, r.dec_deg) = (sky.map(|s| s.0), sky.map(|s| s.1));
        }
    }
    cat.frames = exposures;
    // On a rotator: the rows onto the sky, north through east, by the set's one position angle.
    let firsts: Vec<&Path> = cat.frames.iter().map(|(p, _)| p.as_path()).collect();
    let frame = match crate::sky_angle::of_set(&firsts, inst)? {
        Some(pa) => {
            cat.turn_onto_sky(pa);
            mueller::Frame::Celestial { zero_angle_deg: cat.chi_offset_deg, position_angle_deg: pa }
        }
        None => mueller::Frame::Sky { zero_angle_deg: cat.chi_offset_deg },
    };
    cat.product = Some(crate::provenance::Product::of_instrument(inst, &cat.filter, Some(frame)));
    warnings.extend(zero_angle_warning(inst, &cat.filter));
    warnings.extend(pairing_warning(&cat, inst, cfg.detect.pair_tol_px));
    if let Some(CameraTransform { transform: t, residual_rms_px: Some(rms), pairs: Some(n) }) = cat.camera_transform {
        warnings.push(Warning {
            file: None,
            message: format!(
                "camera transform measured from {n} star pairs: x' = {:.5} x + {:.5} y + {:.3}, y' = {:.5} x + {:.5} y + {:.3} px, residual RMS {rms:.3} px",
                t[0], t[1], t[2], t[3], t[4], t[5]
            ),
        });
    }
    Ok((cat, warnings))
}

/// The sky positions (RA, Dec deg) of detector pixels `xy` through the celestial WCS of the
/// exposure whose (first) file is `first` among `paths`: each pixel in the file of the chip
/// that holds it (an instrument without chips: the frame itself), shifted by the chip's place
/// and prescan. `None` for a pixel no chip holds, a file without a WCS this reads (a TAN
/// projection, [`crate::wcs::CelestialWcs::sky_of_pixel`]), or a chip whose prescan is given by
/// a keyword or whose file is another size than its chip.
pub fn sky_positions(
    paths: &[PathBuf],
    first: &Path,
    inst: &Instrument,
    opts: &ReadOptions,
    xy: &[(f64, f64)],
) -> Vec<Option<(f64, f64)>> {
    let inst = &*opts.instrument(inst);
    // Each chip's file of the first exposure, its place and prescan.
    let chips = crate::calib::first_exposure_chips(paths, first, inst);
    let number = |v: &Option<instrument::NumberOrKeyword>| match v {
        None => Some(0.0),
        Some(instrument::NumberOrKeyword::Number(n)) => Some(*n),
        Some(instrument::NumberOrKeyword::Keyword(_)) => None,
    };
    let placed: Vec<_> = chips
        .into_iter()
        .map(|(c, path)| {
            let (prx, pry) = (number(&c.prescan_x)?, number(&c.prescan_y)?);
            let (ovx, ovy) = (number(&c.overscan_x)?, number(&c.overscan_y)?);
            let (w, (nx, ny)) = crate::wcs::celestial_wcs_in(&path).ok()??;
            let size = (prx + c.size_px[0] as f64 + ovx, pry + c.size_px[1] as f64 + ovy);
            (size == (nx as f64, ny as f64)).then_some((c, prx, pry, w))
        })
        .collect();
    xy.iter()
        .map(|&(x, y)| {
            placed.iter().flatten().find_map(|(c, prx, pry, w)| {
                let (u, v) = (x - c.origin_px[0] as f64, y - c.origin_px[1] as f64);
                let inside = u >= -0.5 && v >= -0.5 && u < c.size_px[0] as f64 - 0.5 && v < c.size_px[1] as f64 - 0.5;
                inside.then(|| w.sky_of_pixel(u + prx, v + pry)).flatten()
            })
        })
        .collect()
}

/// How far from its predicted place an unpaired source's other image is looked for
/// ([`Catalog::unpaired_shift_px`]): a few FWHM, beyond any pairing tolerance in use.
const UNPAIRED_REACH_PX: f64 = 8.0;

/// The warning when many unpaired sources share one shift from the layout's prediction beyond
/// the pairing tolerance `tol` (at least three of them, and at least a quarter as many as the
/// pairs found): the instrument file's o/e offset does not fit these frames.
pub fn pairing_warning(cat: &Catalog, inst: &Instrument, tol: f64) -> Option<Warning> {
    let (dx, dy, n) = cat.unpaired_shift_px?;
    let pairs = cat.rows.len();
    if n < 3 || 4 * n < pairs || dx.hypot(dy) <= tol {
        return None;
    }
    let message = format!(
        "{n} unpaired sources have their other image at ({dx:+.2}, {dy:+.2}) px from where instrument {}'s o/e offset puts it \
         ({pairs} stars paired within the {tol} px tolerance): the instrument file's offset does not fit these frames (filter {}); \
         correct its throw_terms or oe_offset_px, or pair with --pair-tol {:.1}",
        inst.name,
        cat.filter,
        (dx.hypot(dy) + 1.0).ceil()
    );
    Some(Warning { file: None, message })
}

/// The warning for chi values of `filter` when the instrument file gives no zero angle.
pub fn zero_angle_warning(inst: &Instrument, filter: &str) -> Option<Warning> {
    // A quarter-wave plate measures no chi: its zero angle (qwp_zero_angle_deg, 0 when absent)
    // enters the demodulation, not a turn of chi.
    if inst.polarimetry.plate == instrument::Plate::QuarterWave {
        return None;
    }
    let f = inst.filter(filter).ok()?;
    f.zero_angle_warning(&inst.name).map(|message| Warning { file: None, message })
}

/// Build the catalog of `set` (frames in memory; see [`catalog_of`]).
pub fn catalog(set: &FrameSet, inst: &Instrument, cfg: &CatalogConfig) -> Result<Catalog, Error> {
    catalog_of(set, inst, cfg)
}

/// The quarter-wave plate's demodulation and zero angle, when the instrument has one (`None`
/// for a half-wave plate): every star's V/I is one demodulation, refused here, before any star
/// is measured, when the plate angles do not determine V or the plate turned.
fn circular_plate<S: FrameSource>(src: &S, inst: &Instrument) -> Result<Option<(stokes::CircularSolver, f64)>, Error> {
    match inst.polarimetry.plate {
        instrument::Plate::HalfWave => Ok(None),
        instrument::Plate::QuarterWave => {
            if src.hwp_sweep_deg() != 0.0 {
                return Err(Error::Invalid(format!(
                    "the frames' plate swept {} deg during each exposure: a turning quarter-wave plate is not modelled",
                    src.hwp_sweep_deg()
                )));
            }
            let zero = inst.filter(src.filter()).map_or(0.0, |f| f.qwp_zero_angle_deg());
            Ok(Some((circular_solver(src.angles_deg(), zero)?, zero)))
        }
    }
}

/// Refuse a measurement of `n_pairs` stars in `n` frames of `nx` x `ny` px that would take
/// more than [`MAX_PIXEL_VISITS`], unless forced.
fn check_work(cfg: &CatalogConfig, n_pairs: usize, n: usize, nx: usize, ny: usize) -> Result<(), Error> {
    let work = photometry_work(cfg, n_pairs, n, nx, ny);
    if work > MAX_PIXEL_VISITS && !cfg.force {
        return Err(Error::Invalid(format!(
            "{n_pairs} stars paired at a threshold of {} sigma, each measured in {n} frames within {} px: about {work:.1e} pixel visits (limit {MAX_PIXEL_VISITS:.0e}, about a minute of one core): raise the threshold, shrink the annulus, or force it (--force, force=True)",
            cfg.detect.threshold_sigma,
            cfg.annulus.map_or(String::from("the aperture"), |(_, b)| format!("an annulus of {b}")),
        )));
    }
    Ok(())
}

impl CameraTransform {
    /// The transform a two-camera geometry was measured with (`None` for one camera, or when
    /// none was set).
    fn of(g: &BeamGeometry) -> Option<Self> {
        let c = g.cameras.as_ref()?;
        Some(CameraTransform {
            transform: c.transform?,
            residual_rms_px: c.measured.map(|m| m.0),
            pairs: c.measured.map(|m| m.1),
        })
    }
}

/// Build the catalog of the frames of `src`: the layout and the sources from the first
/// angle's frame, then every star measured in every frame, one frame at a time (so that frames
/// read from disk are read once each and need not all be held), and each star reduced.
pub fn catalog_of<S: FrameSource>(src: &S, inst: &Instrument, cfg: &CatalogConfig) -> Result<Catalog, Error> {
    // The beam layout of the frames' filter (its own throw, when the instrument gives one).
    let inst = &*inst.for_filter(src.filter());
    let (nx, ny, n) = (src.nx(), src.ny(), src.angles_deg().len());
    let files = src.files();
    if n == 0 || files.iter().any(|f| f.is_empty()) {
        return Err(Error::NoFrames);
    }
    let nexp = files[0].len() as f64;
    let mut dcfg = cfg.detect;
    dcfg.saturation = src.conversion().det().2 * nexp;
    let mut spare = Vec::new();
    let (g, sources) = src.with_frame(0, |first| -> Result<(BeamGeometry, Vec<Source>), Error> {
        let g = layout_of_image(first, nx, ny, &files[0][0], inst)?;
        let sources = detect_reusing(first, &g, &dcfg, &mut spare);
        Ok((g, sources))
    })??;
    // The detection's work images take the measuring pass's frames.
    src.recycle(spare);
    let (pairs, unpaired) = pair(&sources, &g, dcfg.pair_tol_px);
    check_work(cfg, pairs.len(), n, nx, ny)?;
    // The unpaired sources and where the layout puts their e images, for the overlap test.
    let unpaired_e: Vec<(&Source, Option<(f64, f64)>)> =
        unpaired.iter().map(|&k| (&sources[k], g.e_position(sources[k].x, sources[k].y))).collect();
    let detected = Detected { sources: &sources, g: &g, unpaired_e: &unpaired_e, pair_tol_px: dcfg.pair_tol_px };
    let chi_off = inst.filter(src.filter()).map(|f| f.chi_offset_deg()).unwrap_or(0.0);
    let opts = PhotOptions { weighting: cfg.weighting, recentre: true, kappa: cfg.kappa };
    let circular = circular_plate(src, inst)?;
    let planned: Vec<(Row, Result<Vec<Try>, Error>)> =
        pairs.par_iter().enumerate().map(|(id, pr)| plan_star(id, pr, &detected, inst, cfg, &opts)).collect();
    let by_star = measure_every_frame(src, &planned, &g, cfg, &opts)?;
    // Each star reduced at each radius (the first failing frame, in angle order, is its error,
    // as when it is measured alone), its radius chosen, its row filled.
    let reduce = Reduce { src, circular: &circular, cfg, opts: &opts, chi_off };
    let measured: Vec<(Row, Option<Vec<[f64; 4]>>)> =
        planned.into_par_iter().zip(by_star).map(|((row, tries), frames)| reduce.star(row, tries, frames)).collect();
    let good: Vec<&Vec<[f64; 4]>> = measured.iter().filter_map(|(_, c)| c.as_ref()).collect();
    let alignment = frame_alignment(src.angles_deg(), &good);
    let rows: Vec<Row> = measured.into_iter().map(|(r, _)| r).collect();
    Ok(Catalog {
        hwp_deg: src.angles_deg().to_vec(),
        filter: src.filter().to_string(),
        chi_offset_deg: chi_off,
        oe_offset_px: g.oe_offset,
        camera_transform: CameraTransform::of(&g),
        qwp_zero_angle_deg: circular.as_ref().map(|c| c.1),
        rows,
        unpaired: unpaired.iter().map(|&k| (sources[k].x, sources[k].y)).collect(),
        unpaired_why: crate::detect::Unpaired::of(&sources, &g, &unpaired),
        unpaired_shift_px: crate::detect::unpaired_shift(&sources, &unpaired, &g, UNPAIRED_REACH_PX),
        n_sources: sources.len(),
        alignment,
        exposures: None,
        product: None,
        grouping: None,
        frames: vec![],
    })
}

/// What the first frame's detection found: every source, the layout, the unpaired sources
/// with where the layout puts their e images, and the pairing tolerance.
struct Detected<'a> {
    sources: &'a [Source],
    g: &'a BeamGeometry,
    unpaired_e: &'a [(&'a Source, Option<(f64, f64)>)],
    pair_tol_px: f64,
}

/// A star's measurements in every frame, at each of its candidate radii (`None` where the
/// aperture does not fit): `[frame][radius]`.
type StarFrames = Vec<Vec<Option<Result<FrameFluxes, Error>>>>;

/// A star's row as far as the detection tells (its flags: saturated, blended, overlapping),
/// and the aperture radii to measure it with, each with its placement checked (nothing to
/// measure when saturated or overlapping).
fn plan_star(
    id: usize,
    pr: &crate::detect::Pair,
    d: &Detected,
    inst: &Instrument,
    cfg: &CatalogConfig,
    opts: &PhotOptions,
) -> (Row, Result<Vec<Try>, Error>) {
    let (sources, g) = (d.sources, d.g);
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
    // (The box test first: it is exact and spares the hypot of far sources.)
    let near = |s: &Source, skip: [usize; 2]| {
        sources.iter().enumerate().any(|(k, t)| {
            (t.x - s.x).abs() < blend_r
                && (t.y - s.y).abs() < blend_r
                && !skip.contains(&k)
                && (t.x - s.x).hypot(t.y - s.y) < blend_r
        })
    };
    if near(so, [pr.o, pr.e]) || near(se, [pr.o, pr.e]) {
        flags |= flags::BLENDED;
    }
    if crate::detect::shared_image(g, d.unpaired_e, (so.x, so.y), (se.x, se.y), d.pair_tol_px).is_some() {
        flags |= flags::OVERLAP;
    }
    let mut row = detected_row(id + 1, so, se, (xa, ya), flags);
    if flags & flags::SATURATED != 0 {
        row.note = "saturated: not measured".into();
        return (row, Ok(vec![]));
    }
    if flags & flags::OVERLAP != 0 {
        row.note = "its image overlaps another star's other image: not measured".into();
        return (row, Ok(vec![]));
    }
    // The detection's FWHM of the o image, or the expected one if it could not be measured.
    let fwhm = if so.fwhm_px.is_finite() && so.fwhm_px > 0.0 { so.fwhm_px } else { cfg.detect.fwhm_px };
    let tries = candidate_radii(so.x, so.y, cfg.radius, fwhm, cfg.annulus).map(|radii| {
        radii
            .into_iter()
            .map(|r| {
                let ap = Aperture { radius_px: r, annulus: cfg.annulus };
                (r, check_placement(g, so.x, so.y, &ap, opts))
            })
            .collect()
    });
    (row, tries)
}

/// The row of star `id` (its o image `so`, e image `se`, field position `arcmin`) as detected:
/// every measured value NaN until it is measured.
fn detected_row(id: usize, so: &Source, se: &Source, arcmin: (f64, f64), flags: u32) -> Row {
    let nan = f64::NAN;
    Row {
        id,
        x: so.x,
        y: so.y,
        x_e: se.x,
        y_e: se.y,
        x_arcmin: arcmin.0,
        y_arcmin: arcmin.1,
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
        outlier_exposures: vec![],
        v: None,
        sigma_v: None,
        ra_deg: None,
        dec_deg: None,
    }
}

/// Every planned star measured in every frame, the frames in parallel and each read once:
/// by star, `[star][frame][radius]`.
fn measure_every_frame<S: FrameSource>(
    src: &S,
    planned: &[(Row, Result<Vec<Try>, Error>)],
    g: &BeamGeometry,
    cfg: &CatalogConfig,
    opts: &PhotOptions,
) -> Result<Vec<StarFrames>, Error> {
    let (nx, ny, n) = (src.nx(), src.ny(), src.angles_deg().len());
    let files = src.files();
    let chips = src.chips();
    // The last detector row each star's measurement can read: its centroid window (within
    // 2r + 5 of the detection), apertures and annuli about o and e centres that each lie
    // within r of where the detection and the layout put them, with a margin. Stars are
    // measured in that order while a frame's rows arrive, so their pixels are still in cache
    // (read from memory afterwards, the apertures' pixels were a third of the measuring time).
    let rb = cfg.annulus.map_or(0.0, |a| a.1);
    let last_row: Vec<usize> = planned
        .iter()
        .map(|(row, tries)| {
            let r = tries.as_ref().map_or(0.0, |t| t.iter().map(|t| t.0).fold(0.0, f64::max));
            let ye = g.e_position(row.x, row.y).map_or(f64::INFINITY, |p| p.1);
            let last = row.y.max(ye) + 3.0 * r + rb + 16.0;
            if last.is_finite() && last < ny as f64 {
                last.ceil() as usize
            } else {
                ny
            }
        })
        .collect();
    let mut order: Vec<usize> = (0..planned.len()).collect();
    order.sort_by_key(|&s| last_row[s]);
    // Every star in each frame: the frames in parallel, each read once.
    let per_frame: Vec<StarFrames> = (0..n)
        .into_par_iter()
        .map(|i| {
            let facts = FrameFacts {
                conversion: src.conversion(),
                nexp: files[i].len(),
                file: &files[i][0],
                hwp_deg: src.angles_deg()[i],
                chips: &chips[i],
            };
            let mut out: StarFrames = planned.iter().map(|_| vec![]).collect();
            let mut next = 0;
            src.with_frame_rows(i, &mut |data| {
                let ready = data.len() / nx.max(1);
                let first = next;
                while next < order.len() && (last_row[order[next]] < ready || ready >= ny) {
                    next += 1;
                }
                // The stars whose rows are in, measured in parallel too: a thread whose frames
                // are done takes stars of another's (16 frames on 2 threads ended with one
                // frame measured alone).
                let measured: Vec<(usize, Vec<Option<Result<FrameFluxes, Error>>>)> = order[first..next]
                    .par_iter()
                    .filter_map(|&s| {
                        let (row, tries) = &planned[s];
                        let (Ok(t), true) = (tries, row.flags & flags::NOT_MEASURED == 0) else { return None };
                        let m = t
                            .iter()
                            .map(|(r, placed)| {
                                let ap = Aperture { radius_px: *r, annulus: cfg.annulus };
                                placed.is_ok().then(|| measure_frame(data, g, row.x, row.y, &ap, opts, &facts))
                            })
                            .collect();
                        Some((s, m))
                    })
                    .collect();
                for (s, m) in measured {
                    out[s] = m;
                }
            })?;
            Ok(out)
        })
        .collect::<Result<_, Error>>()?;
    // By star: [star][frame][radius].
    let mut by_star: Vec<StarFrames> = planned.iter().map(|_| Vec::with_capacity(n)).collect();
    for frame in per_frame {
        for (s, v) in frame.into_iter().enumerate() {
            by_star[s].push(v);
        }
    }
    Ok(by_star)
}

/// What reducing a star's frames takes: the frames (their angles, sweep and files), the
/// quarter-wave plate's demodulation if any, the options, and the filter's zero angle.
struct Reduce<'a, S> {
    src: &'a S,
    circular: &'a Option<(stokes::CircularSolver, f64)>,
    cfg: &'a CatalogConfig,
    opts: &'a PhotOptions,
    chi_off: f64,
}

impl<S: FrameSource> Reduce<'_, S> {
    /// A star reduced at each radius (the first failing frame, in angle order, is its error),
    /// its radius chosen and its row filled; with its centres in each frame when measured.
    fn star(&self, mut row: Row, tries: Result<Vec<Try>, Error>, frames: StarFrames) -> (Row, Option<Vec<[f64; 4]>>) {
        if row.flags & flags::NOT_MEASURED != 0 {
            return (row, None);
        }
        let (x, y) = (row.x, row.y);
        let (src, files, n) = (self.src, self.src.files(), self.src.angles_deg().len());
        let result = tries.and_then(|tries| {
            let mut per_try: Vec<Vec<Result<FrameFluxes, Error>>> =
                tries.iter().map(|_| Vec::with_capacity(n)).collect();
            for f in frames {
                for (k, r) in f.into_iter().enumerate() {
                    if let Some(r) = r {
                        per_try[k].push(r);
                    }
                }
            }
            let tried = tries
                .into_iter()
                .zip(per_try)
                .map(|((r, placed), m)| {
                    let ph = placed.and_then(|()| {
                        let m: Vec<FrameFluxes> = m.into_iter().collect::<Result<_, _>>()?;
                        let part = Partial::from_frames(src.angles_deg(), src.hwp_sweep_deg(), &m);
                        match self.circular {
                            None => finish(part, files, x, y, self.opts).map(|p| Measured::Linear(Box::new(p))),
                            Some((solver, zero)) => {
                                finish_circular(part, files, x, y, solver, *zero).map(Measured::Circular)
                            }
                        }
                    });
                    (r, ph)
                })
                .collect();
            pick_radius(self.cfg.radius, tried)
        });
        let mut centres = None;
        match result {
            Ok((Measured::Circular(ph), radius)) => {
                centres = Some(ph.centres.clone());
                row.aperture_px = radius;
                let n = ph.f_o.len();
                row.flux_e = ph.f_o.iter().zip(&ph.f_e).map(|(a, b)| a + b).sum::<f64>() / n as f64;
                row.f = ph.f_o.iter().zip(&ph.f_e).map(|(&o, &e)| stokes::normalized_difference(o, e)).collect();
                row.v = Some(ph.circular.v);
                row.sigma_v = Some(ph.circular.sigma_v());
            }
            Ok((Measured::Linear(ph), radius)) => {
                centres = Some(ph.centres.clone());
                fill_linear(&mut row, &ph, radius, self.chi_off);
            }
            Err(e) => {
                row.flags |= match &e {
                    Error::Unmeasurable { why: Unmeasurable::MaskEdge, .. } => flags::MASK_EDGE,
                    Error::Unmeasurable { why: Unmeasurable::Saturated, .. } => flags::SATURATED,
                    _ => flags::FAILED,
                };
                row.note = e.to_string();
            }
        }
        (row, centres)
    }
}

/// A star's row filled from its reduction through a half-wave plate at aperture `radius`:
/// `(q, u)` in the sky's frame (turned by the filter's zero angle `chi_off`), `P`, `chi`, the
/// modulation's chi^2 and the errors scaled by it.
fn fill_linear(row: &mut Row, ph: &crate::photometry::StarPhotometry, radius: f64, chi_off: f64) {
    row.aperture_px = radius;
    let r = &ph.reduction;
    let n = r.n;
    row.flux_e = ph.f_o.iter().zip(&ph.f_e).map(|(a, b)| a + b).sum::<f64>() / n as f64;
    row.f = r.f.clone();
    // In the sky's frame: the filter's HWP zero angle turns q, u as it turns chi.
    let (sky, chi_deg) = r.in_sky_frame(chi_off);
    row.q = sky.q;
    row.u = sky.u;
    row.sigma_q = sky.var_q.sqrt();
    row.sigma_u = sky.var_u.sqrt();
    row.cov_qu = sky.cov_qu;
    row.p = r.p;
    row.sigma_p = r.sigma_p;
    row.chi_deg = chi_deg;
    // Undetermined (NaN, as every command reports it) where P is at the noise.
    row.sigma_chi_deg = r.sigma_chi_deg_reported().unwrap_or(f64::NAN);
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
    let scale = if dof > 0 { (chi2 / dof as f64).sqrt() } else { f64::NAN };
    row.sigma_q_scatter = row.sigma_q * scale;
    row.sigma_u_scatter = row.sigma_u * scale;
}

/// A star measured at one radius: through a half-wave plate (`q`, `u`) or a quarter-wave
/// plate (`V/I`).
enum Measured {
    Linear(Box<crate::photometry::StarPhotometry>),
    Circular(crate::photometry::CircularPhotometry),
}

impl crate::photometry::Fluxes for Measured {
    fn fluxes(&self) -> (&[f64], &[f64], &[f64], &[f64]) {
        match self {
            Measured::Linear(p) => p.fluxes(),
            Measured::Circular(p) => p.fluxes(),
        }
    }
}

/// Check every measured star of `cat` exposure by exposure (as `photometry` does for one
/// star): `frames` are the exposures `set` was summed from, in the order given.
/// Each star is measured in each exposure alone with its own aperture, its repeats compared
/// through `stokes::repeats` (`crate::photometry::exposure_checks`); a star with a flagged
/// exposure gets [`flags::OUTLIER_EXPOSURE`] and the exposures' indices, and the catalog a
/// summary per exposure. Nothing is done when no HWP position repeats, nor through a
/// quarter-wave plate (the checks compare linear reductions). Flagged exposures stay
/// in the sum (a change common to both beams cancels in `F`): this reports, it does not cut.
pub fn check_exposures(
    cat: &mut Catalog,
    frames: &[crate::frame::Frame],
    set: &FrameSet,
    inst: &Instrument,
    cfg: &CatalogConfig,
) -> Result<(), Error> {
    use crate::photometry::{exposure_checks, single_exposures, Aperture, EXPOSURE_OUTLIER_SIGMA};
    let theta: Vec<f64> = frames.iter().map(|f| f.hwp_deg.to_radians()).collect();
    // The exposures' checks compare linear reductions: not made through a quarter-wave plate.
    if !stokes::repeats::has_repeats(&theta) || cat.qwp_zero_angle_deg.is_some() {
        return Ok(());
    }
    let g: BeamGeometry = layout_for(set, inst)?;
    let singles = single_exposures(frames, set);
    let opts = PhotOptions { weighting: cfg.weighting, recentre: true, kappa: cfg.kappa };
    let checks: Vec<Option<Vec<crate::photometry::ExposureCheck>>> = cat
        .rows
        .par_iter()
        .map(|r| {
            if !(r.q.is_finite() && r.aperture_px.is_finite()) {
                return None;
            }
            let ap = Aperture { radius_px: r.aperture_px, annulus: cfg.annulus };
            // A star the whole set measures but one exposure cannot (shifted off the mask) is
            // left unchecked rather than failing the catalog.
            exposure_checks(&singles, &g, r.x, r.y, &ap, &opts, EXPOSURE_OUTLIER_SIGMA).ok()
        })
        .collect();
    let mut summary: Vec<ExposureSummary> = frames
        .iter()
        .enumerate()
        .map(|(i, f)| ExposureSummary {
            index: i,
            file: f.path.display().to_string(),
            hwp_deg: f.hwp_deg,
            n_stars: 0,
            n_stars_flagged: 0,
            median_transparency: f64::NAN,
            outlier: false,
        })
        .collect();
    let mut trans: Vec<Vec<f64>> = vec![vec![]; frames.len()];
    for (row, ch) in cat.rows.iter_mut().zip(&checks) {
        let Some(ch) = ch else { continue };
        for (i, e) in ch.iter().enumerate() {
            summary[i].n_stars += 1;
            trans[i].push(e.transparency);
            if e.outlier {
                summary[i].n_stars_flagged += 1;
                row.outlier_exposures.push(i);
            }
        }
        if !row.outlier_exposures.is_empty() {
            row.flags |= flags::OUTLIER_EXPOSURE;
        }
    }
    for (s, mut t) in summary.iter_mut().zip(trans) {
        t.retain(|x| x.is_finite());
        if !t.is_empty() {
            s.median_transparency = stokes::stats::robust::median(&mut t, stokes::stats::robust::Middle::Mean);
        }
        s.outlier = s.n_stars > 0 && 2 * s.n_stars_flagged >= s.n_stars;
    }
    cat.exposures = Some(summary);
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The settings no star field can have are refused by the one check both faces call,
    /// naming the setting: a sky annulus that is not `0 <= inner < outer` and a known kappa
    /// outside (-1, 1), NaN and infinities included; the defaults and a valid setting pass.
    #[test]
    fn impossible_settings_are_refused_by_name() {
        let ok = CatalogConfig { annulus: Some((12.0, 20.0)), ..CatalogConfig::default() };
        assert!(ok.check().is_ok() && CatalogConfig::default().check().is_ok());
        for a in [(f64::NAN, 20.0), (12.0, f64::INFINITY), (20.0, 12.0), (-1.0, 5.0), (8.0, 8.0)] {
            let e = CatalogConfig { annulus: Some(a), ..ok }.check().unwrap_err().to_string();
            assert!(e.contains("annulus"), "{a:?}: {e}");
        }
        for k in [f64::NAN, f64::NEG_INFINITY, 1.0, -1.0, 3.0] {
            let e = CatalogConfig { kappa: stokes::KappaCorrection::Known(k), ..ok }.check().unwrap_err();
            assert!(e.to_string().contains("kappa"), "{k}: {e}");
        }
        assert!(CatalogConfig { kappa: stokes::KappaCorrection::Known(0.03), ..ok }.check().is_ok());
    }
}
