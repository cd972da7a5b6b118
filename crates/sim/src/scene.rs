//! The scene file (TOML): what is on the sky, which instrument looks at it, and which
//! instrument effects to apply. Validated on load; unknown keys are errors that name the key.
//!
//! Units: fluxes and surface brightness in electrons *per exposure* (the total `I` of both
//! beams, i.e. what an ideal instrument would put in `f_O + f_E`); polarization degrees as
//! **fractions** (`p = 0.0174` for the paper's 1.74%; only the radial polynomial of the
//! instrumental field is given in percent, as the paper prints it, and its key says so:
//! `coeffs_percent`); angles in degrees; positions in pixels (0-based, o-image = sky
//! coordinates, see `skyfield::beams`) or arcmin from the detector centre (`coords`).
//! Relative file paths are taken from the scene file's folder.
//!
//! ```toml
//! instrument = "fors1"          # built-in name or path to an instrument TOML
//! filter = "V"
//! hwp_angles_deg = [0, 22.5, 45, 67.5]   # default: the optimal N = 4 set
//! # hwp_motion = { sweep_deg = 22.5 }      # a plate turning during each exposure, centred
//! #                                        # on its angle (substeps = 64: by sub-steps)
//! exposure_s = 300              # written to EXPTIME only
//! seed = 42
//!
//! [output]
//! bitpix = 16                   # 16 (raw-like unsigned, default), -32 or -64
//! # Instruments whose [format] has chips (FORS2, EFOSC2) get raw chip files, as they read out:
//! # raw_bias_adu = 220          # bias level (default: the format's raw_bias_adu, else 200)
//! # raw_scan_px = [0, 0, 5, 5]  # pre/overscan sizes where the format names a keyword
//! # bias_frames = 5             # bias frames, written when no overscan removes the bias
//!
//! [sky]
//! brightness_e = 20000          # e-/px per exposure at the detector centre
//! p = 0.0174                    # fraction
//! chi_deg = -53.8
//! # v = 0.01                    # circular polarization V/I (fraction, IAU sign; default 0)
//! gradient_e_per_arcmin = [0, 0]   # optional linear gradient along x, y
//!
//! [[stars]]
//! x = 3.0
//! y = -3.0
//! coords = "arcmin"             # or "pixel"
//! flux_e = 2e6
//! p = 0.0
//! chi_deg = 0
//! # v = 0.01                  # circular polarization V/I (fraction, IAU sign; default 0)
//! fwhm_arcsec = 0.8
//! psf = "gaussian"              # or "moffat" (with moffat_beta, default 2.5)
//!
//! [effects]
//! photon_noise = true
//! read_noise = true             # the instrument's read noise; or read_noise_e = 4.0
//! saturation = true
//! instpol = { kind = "radial", coeffs_percent = [0, 0.012, 0.046, 0.002] }
//! wollaston = { t = 0.51, s = 0.49, delta_alpha_deg = 0 }
//! post_analyzer = { b = 0.004, phi_deg = 30 }
//! # qwp_zero_angle_deg = 1.5  # a quarter-wave plate's axis offset (plate = "quarter_wave")
//! flat = { pixel_rms_o = 0.01, pixel_rms_e = 0.012, large_scale_o = 0.02, large_scale_e = 0.03 }
//! cosmic_rays = { rate_per_frame = 50 }
//!
//! [telescope]                   # optional: a Nasmyth M3 in front (mueller::telescope::BandModel)
//! metal = "aluminium"           # built-in table or a lambda,n,k file
//! factor = 0.86                 # Wiersema factor on n, k (default 1)
//! overlayer_thickness_nm = 0    # alumina over-layer (default 0)
//! offset_deg = 40               # the instrument's angle zero (default 0)
//! rotator_deg = 0               # rotator / adapter angle (default 0, mueller::telescope::Track)
//! dec_deg = -30                 # the target's declination
//! ha_start_deg = 15             # hour angle at the first exposure's start; the next ones
//! overhead_s = 30               #   follow every exposure_s + overhead_s (sidereal rate)
//! # hour_angles_deg = [...]     # or the start of each exposure, one per HWP angle
//! # site_latitude_deg = -29.26  # default: the instrument's [telescope] site_latitude_deg
//! ```

use crate::Error;
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};

/// The HWP angles (deg) of a scene that gives none: the optimal N = 4 set.
pub fn default_angles() -> Vec<f64> {
    vec![0.0, 22.5, 45.0, 67.5]
}
fn one() -> f64 {
    1.0
}
fn is_zero(x: &f64) -> bool {
    *x == 0.0
}
fn default_bitpix() -> i32 {
    16
}
/// The Moffat profile's `beta` of a star that gives none (a typical seeing-limited value).
pub const DEFAULT_MOFFAT_BETA: f64 = 2.5;

fn default_beta() -> f64 {
    DEFAULT_MOFFAT_BETA
}
fn default_bin() -> usize {
    10
}
fn default_cr_energy() -> f64 {
    20000.0
}
fn default_cr_size() -> usize {
    2
}

/// A whole scene.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Scene {
    /// Built-in instrument name or path to an instrument TOML.
    pub instrument: String,
    pub filter: String,
    /// HWP angles (deg); default the optimal N = 4 set.
    #[serde(default = "default_angles")]
    pub hwp_angles_deg: Vec<f64>,
    /// Exposure time (s): written to the header; fluxes are per exposure already.
    #[serde(default = "one")]
    pub exposure_s: f64,
    #[serde(default)]
    pub seed: u64,
    #[serde(default)]
    pub output: Output,
    pub sky: Option<Sky>,
    #[serde(default)]
    pub stars: Vec<Star>,
    #[serde(default)]
    pub extended: Vec<Extended>,
    #[serde(default)]
    pub effects: Effects,
    /// Pointing offsets `[dx, dy]` (px) of each frame, one per HWP angle (the telescope moves a
    /// little between exposures): the stars move by them on the detector. Empty: none.
    #[serde(default)]
    pub frame_shifts_px: Vec<[f64; 2]>,
    /// The telescope in front of the instrument (a Nasmyth M3 turned by each exposure's
    /// parallactic-angle track); absent: none.
    #[serde(default)]
    pub telescope: Option<TelescopeSpec>,
    /// A half-wave plate that turns during each exposure; absent: it stands still.
    #[serde(default)]
    pub hwp_motion: Option<HwpMotion>,
    /// The instrument's position angle on the sky (deg, north through east) on a rotator: the
    /// sky's, stars' and extended sources' `chi_deg` are then the sky's, and the instrument sees
    /// each at `chi - sky_pa_deg` ([`Scene::seen_by_instrument`]); the frames carry the angle
    /// under the instrument's `[polarimetry.sky_angle]` keyword (its sense and offset undone).
    /// Positions stay as given, on the detector. Absent: the instrument's frame is the sky's.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub sky_pa_deg: Option<f64>,
}

/// A half-wave plate turning uniformly during each exposure: exposure `k` sweeps `sweep_deg`
/// centred on `hwp_angles_deg[k]`. Its fluxes are the plate's matrix averaged over the motion
/// (`mueller::Hwp::matrix_swept`, the closed form), or with `substeps > 0` the mean of the
/// fixed plate's fluxes at that many equal sub-steps of the range (midpoints): the same motion
/// integrated the other way. Frames carry the range under the instrument's
/// `[polarimetry.rotation]` keywords.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct HwpMotion {
    pub sweep_deg: f64,
    #[serde(default)]
    pub substeps: u32,
}

fn default_metal() -> String {
    "aluminium".into()
}

/// Sidereal rate of the hour angle (deg per second of time): 360 deg per 86164.0905 s.
pub const HA_DEG_PER_S: f64 = 360.0 / 86164.0905;

/// The telescope of a scene: the mirror of `mueller::telescope::BandModel` (metal table, factor,
/// alumina over-layer, angle offset), the site and the target, and when each exposure starts.
/// Every source's Stokes vector passes through the mirror's matrix averaged over its
/// exposure's parallactic-angle track (`BandModel::matrix_track`), before the instrumental
/// field; frames carry the angles under the instrument's `[telescope]` keywords.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TelescopeSpec {
    /// `aluminium` / `silver` (built-in tables) or a `lambda,n,k` table file (micron).
    #[serde(default = "default_metal")]
    pub metal: String,
    /// Factor on the metal's `n` and `k` (Wiersema et al. 2018).
    #[serde(default = "one")]
    pub factor: f64,
    /// Alumina over-layer (nm).
    #[serde(default)]
    pub overlayer_thickness_nm: f64,
    /// The instrument's angle zero (deg): `R(offset + rotator) M3(plane at 90 deg - q)`.
    #[serde(default)]
    pub offset_deg: f64,
    /// Rotator / adapter angle (deg, `mueller::telescope::Track::rotator`), written to the
    /// instrument's rotator keyword.
    #[serde(default)]
    pub rotator_deg: f64,
    /// Site latitude (deg); default: the instrument's `[telescope] site_latitude_deg`.
    #[serde(default)]
    pub site_latitude_deg: Option<f64>,
    /// The target's declination (deg).
    pub dec_deg: f64,
    /// Hour angle (deg, positive west) at the start of the first exposure; exposure `k` starts
    /// `k (exposure_s + overhead_s)` seconds later.
    #[serde(default)]
    pub ha_start_deg: Option<f64>,
    /// Seconds between the end of one exposure and the start of the next (with `ha_start_deg`).
    #[serde(default)]
    pub overhead_s: f64,
    /// Hour angle (deg) at the start of each exposure, one per HWP angle (instead of
    /// `ha_start_deg`).
    #[serde(default)]
    pub hour_angles_deg: Vec<f64>,
}

impl TelescopeSpec {
    /// Hour angles (deg) at the start and end of exposure `k` of an `exposure_s` scene.
    pub fn hour_angles(&self, k: usize, exposure_s: f64) -> (f64, f64) {
        let start = match self.hour_angles_deg.get(k) {
            Some(h) => *h,
            None => self.ha_start_deg.unwrap_or(0.0) + k as f64 * (exposure_s + self.overhead_s) * HA_DEG_PER_S,
        };
        (start, start + exposure_s * HA_DEG_PER_S)
    }
}

/// How frames are written.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Output {
    /// 16 (unsigned 16-bit, rounded, like raw CCD frames), -32 or -64.
    #[serde(default = "default_bitpix")]
    pub bitpix: i32,
    /// File name prefix.
    #[serde(default = "default_prefix")]
    pub prefix: String,
    /// Chip instruments (a `[format]` with chips): the raw files' bias level (ADU). Default:
    /// the format's `raw_bias_adu`, else [`DEFAULT_RAW_BIAS_ADU`].
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub raw_bias_adu: Option<f64>,
    /// Chip instruments: `[prescan x, overscan x, prescan y, overscan y]` (binned px) written
    /// where the format reads a size from a keyword. Default [`DEFAULT_RAW_SCAN_PX`].
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub raw_scan_px: Option<[usize; 4]>,
    /// Chip instruments with a chip whose bias no overscan removes: how many bias frames to
    /// write for a master bias (default [`DEFAULT_BIAS_FRAMES`]; at least 3 for its clipping).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub bias_frames: Option<usize>,
    /// Archive-like files (a night as an archive delivers it): frame `k` is named
    /// `<INSTRUMENT>.<UTC start to the millisecond>` as ESO's archive names raw files
    /// (`FORS2.2019-03-04T01:02:03.456`, a chip instrument's chip files adding `_<chip>`), and
    /// carries its start as `MJD-OBS`. Absent: files are named by `prefix`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub archive: Option<Archive>,
    /// More keywords written on every file, over the simulator's own of the same name (an
    /// archive's frame type, target name and pointing: `"HIERARCH ESO DPR TYPE" = "BIAS"`,
    /// `RA = 150.0`).
    #[serde(default, skip_serializing_if = "std::collections::BTreeMap::is_empty")]
    pub keywords: std::collections::BTreeMap<String, Keyword>,
    /// The exposure number of frame 0 (frames count up from it; chip instruments write it to
    /// the format's `exposure_keywords`). Default 1.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub first_exposure_no: Option<i64>,
}

/// When an archive-like night's frames start ([`Output::archive`]).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Archive {
    /// Frame 0's start (MJD, UTC).
    pub start_mjd: f64,
    /// Seconds from one frame's start to the next's.
    pub cadence_s: f64,
}

/// A header keyword's value in [`Output::keywords`].
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(untagged)]
pub enum Keyword {
    Number(f64),
    Text(String),
}

/// Raw files' bias level when neither the scene nor the format gives one: a pedestal that
/// keeps the read noise of an empty pixel above the 16-bit floor (no instrument's value).
pub const DEFAULT_RAW_BIAS_ADU: f64 = 200.0;
/// Pre/overscan sizes of keyword-declared regions: FORS2's standard 2x2 read-out, 5 prescan
/// and 5 overscan rows, no columns (ESO QC "FORS2 Pipeline: General Information").
pub const DEFAULT_RAW_SCAN_PX: [usize; 4] = [0, 0, 5, 5];
/// Bias frames written for a master bias: enough for a per-pixel sigma clip.
pub const DEFAULT_BIAS_FRAMES: usize = 5;

fn default_prefix() -> String {
    "frame".into()
}

impl Default for Output {
    fn default() -> Self {
        Self {
            bitpix: 16,
            prefix: default_prefix(),
            raw_bias_adu: None,
            raw_scan_px: None,
            bias_frames: None,
            archive: None,
            keywords: Default::default(),
            first_exposure_no: None,
        }
    }
}

/// The sky background: constant, or with a linear gradient; one polarization.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Sky {
    /// Surface brightness at the detector centre (e-/px per exposure, both beams).
    pub brightness_e: f64,
    /// Polarization degree (fraction).
    #[serde(default)]
    pub p: f64,
    #[serde(default)]
    pub chi_deg: f64,
    /// Circular polarization `V/I` (fraction, IAU sign, as a star's `v`), the same over the
    /// sky; `p^2 + v^2 <= 1`. It reaches the beams through the plate's fourth column (a
    /// quarter-wave plate's modulation of `V`).
    #[serde(default, skip_serializing_if = "is_zero")]
    pub v: f64,
    /// Linear gradient (e-/px per arcmin along detector x and y).
    #[serde(default)]
    pub gradient_e_per_arcmin: Option<[f64; 2]>,
}

/// Coordinates of a position.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Coords {
    /// 0-based pixels of the o image (= sky coordinates).
    Pixel,
    /// Arcmin from the detector centre.
    Arcmin,
}

/// Point-spread function shape.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "lowercase")]
pub enum Psf {
    #[default]
    Gaussian,
    Moffat,
}

/// A star.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Star {
    pub x: f64,
    pub y: f64,
    pub coords: Coords,
    /// Total flux (e- per exposure, both beams).
    pub flux_e: f64,
    #[serde(default)]
    pub p: f64,
    #[serde(default)]
    pub chi_deg: f64,
    /// Circular polarization `V/I` (fraction, IAU sign: `V > 0` for counter-clockwise rotation
    /// of the electric vector as seen by the observer); `p^2 + v^2 <= 1`.
    #[serde(default, skip_serializing_if = "is_zero")]
    pub v: f64,
    pub fwhm_arcsec: f64,
    #[serde(default)]
    pub psf: Psf,
    #[serde(default = "default_beta")]
    pub moffat_beta: f64,
}

/// Profile of an extended source.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Profile {
    /// `I(r) = i_e exp(-b_n ((r/r_e)^(1/n) - 1))`.
    Sersic,
    /// Sersic with `n = 1`.
    Exponential,
    /// A FITS image of the detector's size (e-/px per exposure, o coordinates).
    Image,
}

/// An extended source with one polarization.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Extended {
    pub profile: Profile,
    #[serde(default)]
    pub x: f64,
    #[serde(default)]
    pub y: f64,
    #[serde(default = "default_coords_arcmin")]
    pub coords: Coords,
    /// Effective radius (arcsec) of the analytic profiles.
    #[serde(default)]
    pub r_e_arcsec: f64,
    /// Sersic index (analytic `sersic` only).
    #[serde(default = "one")]
    pub sersic_n: f64,
    /// Surface brightness at `r_e` (e-/px per exposure).
    #[serde(default)]
    pub i_e: f64,
    #[serde(default = "one")]
    pub axis_ratio: f64,
    #[serde(default)]
    pub pa_deg: f64,
    #[serde(default)]
    pub p: f64,
    #[serde(default)]
    pub chi_deg: f64,
    /// FITS image (profile = "image").
    #[serde(default)]
    pub image: Option<PathBuf>,
}

fn default_coords_arcmin() -> Coords {
    Coords::Arcmin
}

/// The instrumental polarization field `M_I(p(x,y), phi(x,y))` before the HWP.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "lowercase", deny_unknown_fields)]
pub enum InstPolSpec {
    /// `p(r) = sum_k c_k r^k` percent (r in arcmin from `centre_arcmin`), `phi` = polar angle
    /// of the position (+ `phi_offset_deg`): the paper's radial pattern.
    Radial {
        coeffs_percent: Vec<f64>,
        #[serde(default)]
        centre_arcmin: [f64; 2],
        #[serde(default)]
        phi_offset_deg: f64,
    },
    /// Q/I and U/I maps (FITS; a 2-D image, or a cube whose first plane holds the values, as
    /// in the FORS2 INLA maps); map pixel `(i, j)` covers detector pixels
    /// `[bin_px i, bin_px (i+1))` x `[bin_px j, bin_px (j+1))`; NaN or outside: no
    /// instrumental polarization.
    Map {
        q_file: PathBuf,
        u_file: PathBuf,
        #[serde(default = "default_bin")]
        bin_px: usize,
    },
    /// A ray tracer's field file (`instpol raytrace --field-out`, format `instpol-field-v1`,
    /// see `mueller::raytrace`): p interpolated linearly in radius (constant beyond the
    /// ends), angle radial plus the tabulated offset, about `centre_arcmin`.
    Raytrace {
        file: PathBuf,
        #[serde(default)]
        centre_arcmin: [f64; 2],
    },
}

/// Wollaston prism parameters (`eq:WP` when `s = 1 - t`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct WollastonSpec {
    pub t: f64,
    /// Default `1 - t`.
    #[serde(default)]
    pub s: Option<f64>,
    #[serde(default)]
    pub delta_alpha_deg: f64,
}

/// A harmonic HWP defect.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct HarmonicSpec {
    pub amplitude: f64,
    #[serde(default)]
    pub phase_deg: f64,
}

/// Post-analyzer optics `M_PA(A, B, C, phi)` (section `sec:postwp`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PostAnalyzerSpec {
    pub b: f64,
    #[serde(default)]
    pub phi_deg: f64,
    #[serde(default = "one")]
    pub a: f64,
    #[serde(default = "one")]
    pub c: f64,
}

/// Flat-field errors left in the frames (multiplicative gains), different in the two beams:
/// pixel-to-pixel Gaussian rms and a smooth large-scale pattern of the given amplitude.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, Default)]
#[serde(deny_unknown_fields)]
pub struct FlatSpec {
    #[serde(default)]
    pub pixel_rms_o: f64,
    #[serde(default)]
    pub pixel_rms_e: f64,
    #[serde(default)]
    pub large_scale_o: f64,
    #[serde(default)]
    pub large_scale_e: f64,
}

/// Cosmic-ray hits.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CosmicSpec {
    /// Mean number of hits per frame (Poisson).
    pub rate_per_frame: f64,
    /// Charge per hit (e-), spread over a `size_px` square.
    #[serde(default = "default_cr_energy")]
    pub energy_e: f64,
    #[serde(default = "default_cr_size")]
    pub size_px: usize,
}

/// Which instrument effects to apply. Anything absent is not computed at all.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, Default)]
#[serde(deny_unknown_fields)]
pub struct Effects {
    pub instpol: Option<InstPolSpec>,
    /// A stressed collimator lens: a retardance field applied after `instpol` ([`crate::stress`]).
    pub stressed_lens: Option<crate::stress::StressedLensSpec>,
    /// The instrument's constant response as standards calibrate it (`[effects.constant_response]`,
    /// `q0`, `u0`, `efficiency`, `offset_deg`: [`field::ConstantResponse`]): an element of the
    /// chain after `instpol` and before the stressed lens, the same over the field, so that
    /// every star shows `(q0, u0) + efficiency R(-offset) (q, u)` in the instrument's sky frame.
    pub constant_response: Option<field::ConstantResponse>,
    /// A tilted half-wave plate, applied as its equivalent block ([`crate::hwp_causes`]).
    pub tilted_hwp: Option<crate::hwp_causes::TiltedHwpSpec>,
    /// A wedged half-wave plate, applied as its equivalent block ([`crate::hwp_causes`]).
    pub wedged_hwp: Option<crate::hwp_causes::WedgedHwpSpec>,
    pub wollaston: Option<WollastonSpec>,
    pub hwp_retardance_error_deg: Option<f64>,
    /// HWP chromatic zero angle (deg, the correction instruments tabulate: added to measured chi).
    pub hwp_chi_offset_deg: Option<f64>,
    /// Take the zero angle from the instrument's filter table instead (a quarter-wave plate's
    /// `qwp_zero_angle_deg`).
    #[serde(default)]
    pub hwp_chi_offset_from_filter: bool,
    /// A quarter-wave plate's zero angle (deg): its fast axis at the frame's plate angle plus
    /// this (`[polarimetry] plate = "quarter_wave"` only).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub qwp_zero_angle_deg: Option<f64>,
    pub dust: Option<HarmonicSpec>,
    pub pleochroism: Option<HarmonicSpec>,
    pub post_analyzer: Option<PostAnalyzerSpec>,
    pub flat: Option<FlatSpec>,
    #[serde(default)]
    pub photon_noise: bool,
    /// Add the instrument's read noise.
    #[serde(default)]
    pub read_noise: bool,
    /// Read noise (e-) overriding the instrument's (implies read noise).
    pub read_noise_e: Option<f64>,
    /// Gain (e-/ADU) overriding the instrument's.
    pub gain_e_per_adu: Option<f64>,
    /// Clip at the instrument's saturation level.
    #[serde(default)]
    pub saturation: bool,
    pub cosmic_rays: Option<CosmicSpec>,
    /// Frame-to-frame transparency (and exposure-time) noise: every frame's light times
    /// `1 + rms n`, `n` standard normal, one draw per frame. Both beams scale together, so
    /// `F_i` (`eq:F`) does not see it: the dual-beam method's reason to be.
    pub transparency_rms: Option<f64>,
}

impl Scene {
    /// Parse and validate scene TOML; `path` labels errors and anchors relative file paths.
    pub fn from_toml_str(text: &str, path: &Path) -> Result<Self, Error> {
        if let Some((key, value)) = instrument::toml_numbers::first_non_finite(text) {
            return Err(Error::Scene { path: path.into(), message: format!("{key} = {value}: not a finite number") });
        }
        let mut s: Scene =
            toml::from_str(text).map_err(|e| Error::Scene { path: path.into(), message: e.to_string() })?;
        let base = path.parent().unwrap_or(Path::new(""));
        s.resolve_paths(base);
        s.validate(path)?;
        s.validate_sky_pa(path)?;
        Ok(s)
    }

    /// A scene built as a value, checked as a scene file is ([`Scene::from_toml_str`]) and
    /// returned; `label` names it in errors. Its file paths are taken as they are.
    pub fn checked(self, label: &Path) -> Result<Self, Error> {
        self.validate(label)?;
        self.validate_sky_pa(label)?;
        Ok(self)
    }

    /// The scene as the instrument sees it on its rotator: every `chi_deg` (sky, stars,
    /// extended sources) less the instrument's position angle on the sky `sky_pa_deg`, so that
    /// the one chain of the simulator renders what reaches the instrument; `sky_pa_deg` is
    /// kept (the frames' headers say it), and [`Scene::on_sky`] is the way back.
    pub fn seen_by_instrument(&self) -> Scene {
        self.turned(-self.sky_pa_deg.unwrap_or(0.0))
    }

    /// The inverse of [`Scene::seen_by_instrument`]: the scene's angles on the sky again.
    pub fn on_sky(&self) -> Scene {
        self.turned(self.sky_pa_deg.unwrap_or(0.0))
    }

    /// Every `chi_deg` turned by `deg`, folded into [0, 180).
    fn turned(&self, deg: f64) -> Scene {
        let mut s = self.clone();
        if deg == 0.0 {
            return s;
        }
        let turn = |chi: &mut f64| *chi = mueller::fold_pi((*chi + deg).to_radians()).to_degrees();
        if let Some(sky) = &mut s.sky {
            turn(&mut sky.chi_deg);
        }
        s.stars.iter_mut().for_each(|st| turn(&mut st.chi_deg));
        s.extended.iter_mut().for_each(|e| turn(&mut e.chi_deg));
        s
    }

    /// The checks of `sky_pa_deg`: a finite angle, an instrument that says where its frames
    /// carry the angle (`[polarimetry.sky_angle]`), and no `[telescope]` (whose `offset_deg` and
    /// `rotator_deg` turn the sky into the instrument already: one turn, given once).
    fn validate_sky_pa(&self, path: &Path) -> Result<(), Error> {
        let Some(pa) = self.sky_pa_deg else { return Ok(()) };
        let bad = |why: String| {
            Err(Error::Invalid { path: path.into(), key: "sky_pa_deg".into(), value: pa.to_string(), why })
        };
        if !pa.is_finite() {
            return bad("must be a finite angle in degrees".into());
        }
        if self.telescope.is_some() {
            return bad(
                "a [telescope] turns the sky into the instrument by its offset_deg and rotator_deg already: give the \
                 instrument's angle there, not twice"
                    .into(),
            );
        }
        let inst = instrument::Instrument::load(&self.instrument)?;
        if inst.polarimetry.sky_angle.is_none() {
            return bad(format!(
                "instrument {} does not say where its frames carry their position angle on the sky \
                 ([polarimetry.sky_angle]): the frames could not tell it",
                inst.name
            ));
        }
        Ok(())
    }

    /// Read and validate a scene file.
    pub fn from_file(path: &Path) -> Result<Self, Error> {
        let text = std::fs::read_to_string(path)
            .map_err(|e| Error::Scene { path: path.into(), message: format!("cannot read: {e}") })?;
        Self::from_toml_str(&text, path)
    }

    fn resolve_paths(&mut self, base: &Path) {
        let fix = |p: &mut PathBuf| {
            if p.is_relative() {
                *p = base.join(&*p);
            }
        };
        let inst = base.join(&self.instrument);
        if inst.is_file() && Path::new(&self.instrument).is_relative() {
            self.instrument = inst.to_string_lossy().into_owned();
        }
        for e in &mut self.extended {
            if let Some(p) = &mut e.image {
                fix(p);
            }
        }
        match &mut self.effects.instpol {
            Some(InstPolSpec::Map { q_file, u_file, .. }) => {
                fix(q_file);
                fix(u_file);
            }
            Some(InstPolSpec::Raytrace { file, .. }) => fix(file),
            _ => {}
        }
        if let Some(t) = &mut self.telescope {
            if mueller::mirror::MetalTable::builtin(&t.metal).is_err() && Path::new(&t.metal).is_relative() {
                t.metal = base.join(&t.metal).to_string_lossy().into_owned();
            }
        }
    }

    fn validate(&self, path: &Path) -> Result<(), Error> {
        let inst = instrument::Instrument::load(&self.instrument)?;
        inst.filter(&self.filter)?;
        self.validate_plate(&inst, path)?;
        self.validate_elements(path)?;
        self.validate_layout(&inst, path)?;
        self.validate_output(path)?;
        self.validate_sources(path)?;
        self.validate_effects(&inst, path)?;
        // Frames are written as OUT/PREFIX_NN_hwpA.fits: the prefix is a plain file-name part,
        // so a scene cannot put files outside the output folder the user named.
        let pre = &self.output.prefix;
        if pre.is_empty() || pre.contains(['/', '\\', '\0']) || pre.starts_with('.') || Path::new(pre).is_absolute() {
            return Err(invalid(
                path,
                "output.prefix",
                format!("{pre:?}"),
                "must be a plain file-name part (no '/', '\\', '..', not starting with '.', not empty): frames are written inside --out",
            ));
        }
        if let Some(t) = &self.telescope {
            self.validate_telescope(t, &inst, path)?;
        }
        if let Some(InstPolSpec::Radial { coeffs_percent, .. }) = &self.effects.instpol {
            if coeffs_percent.iter().any(|c| !c.is_finite()) {
                return Err(invalid(
                    path,
                    "effects.instpol.coeffs_percent",
                    format!("{coeffs_percent:?}"),
                    "must be finite numbers",
                ));
            }
        }
        Ok(())
    }

    /// The plate's checks: its angles in degrees, its motion (a sweep below 180 deg, a bounded
    /// number of substeps), what a quarter-wave plate does not take, angles that determine what
    /// the plate measures, and a rotor that reads its range from a position.
    fn validate_plate(&self, inst: &instrument::Instrument, path: &Path) -> Result<(), Error> {
        let bad = |key: &str, value: String, why: &str| Err(invalid(path, key, value, why));
        if let Err(e) = stokes::check_degrees(&self.hwp_angles_deg) {
            return bad("hwp_angles_deg", format!("{:?}", self.hwp_angles_deg), &format!("{e}: give degrees"));
        }
        // A plate turning through several turns repeats its positions: each position once.
        let mut th: Vec<f64> = self.hwp_angles_deg.iter().map(|a| a.to_radians()).collect();
        if self.hwp_motion.is_some() {
            let mut seen: Vec<f64> = vec![];
            th.retain(|t| {
                let new = !seen.contains(t);
                seen.push(*t);
                new
            });
        }
        let sweeps = match &self.hwp_motion {
            Some(m) => {
                if !(m.sweep_deg.is_finite() && m.sweep_deg.abs() < 180.0) {
                    return bad(
                        "hwp_motion.sweep_deg",
                        m.sweep_deg.to_string(),
                        "must be a plate angle range in degrees, below 180",
                    );
                }
                if m.substeps > 100_000 {
                    return bad("hwp_motion.substeps", m.substeps.to_string(), "at most 100000");
                }
                vec![m.sweep_deg.to_radians(); th.len()]
            }
            None => vec![0.0; th.len()],
        };
        if inst.polarimetry.plate == instrument::Plate::QuarterWave {
            let qwp_bad = |key: &str, value: String| {
                bad(
                    key,
                    value,
                    &format!(
                        "instrument {} has a quarter-wave plate (plate = \"quarter_wave\"), which this does not apply to: \
                         its zero angle is qwp_zero_angle_deg (here or the filter's, hwp_chi_offset_from_filter), it stands \
                         still, and the simulator carries (I, Q, U) through a telescope, not V",
                        inst.name
                    ),
                )
            };
            if let Some(c) = self.effects.hwp_chi_offset_deg {
                return qwp_bad("effects.hwp_chi_offset_deg", c.to_string());
            }
            if let Some(m) = &self.hwp_motion {
                return qwp_bad("hwp_motion", m.sweep_deg.to_string());
            }
            if self.telescope.is_some() {
                return qwp_bad("telescope", "set".into());
            }
            if let Err(e) = stokes::CircularSolver::new(&th) {
                return bad("hwp_angles_deg", format!("{:?}", self.hwp_angles_deg), &e.to_string());
            }
        } else if let Some(z) = self.effects.qwp_zero_angle_deg {
            return bad(
                "effects.qwp_zero_angle_deg",
                z.to_string(),
                &format!("instrument {} has a half-wave plate: its zero angle is hwp_chi_offset_deg", inst.name),
            );
        }
        if let Some(z) = self.effects.qwp_zero_angle_deg.filter(|z| !(z.is_finite() && z.abs() <= 90.0)) {
            return bad("effects.qwp_zero_angle_deg", z.to_string(), "must be an angle in degrees within +-90");
        }
        // A half-wave plate's angles must determine q and u (a quarter-wave plate's V, above).
        let linear = inst.polarimetry.plate == instrument::Plate::HalfWave;
        match stokes::StokesSolver::with_sweeps(&th, &sweeps) {
            Err(e @ stokes::Error::NoModulation { .. }) if linear => {
                let d = self.hwp_motion.as_ref().map_or(0.0, |m| m.sweep_deg);
                return bad("hwp_motion.sweep_deg", d.to_string(), &e.to_string());
            }
            Err(e) if linear => return bad("hwp_angles_deg", format!("{:?}", self.hwp_angles_deg), &e.to_string()),
            _ => {}
        }
        if let (None, Some(r)) = (&self.hwp_motion, &inst.polarimetry.rotation) {
            if r.by_position() {
                return bad(
                    "hwp_motion",
                    "(none)".into(),
                    &format!(
                        "instrument {} reads its plate's range from a rotor position: give the motion, \
                         hwp_motion = {{ sweep_deg = {} }}",
                        inst.name,
                        360.0 / r.positions_per_turn as f64
                    ),
                );
            }
        }
        if let (Some(m), Some(r)) = (&self.hwp_motion, &inst.polarimetry.rotation) {
            if r.by_position() {
                for &a in &self.hwp_angles_deg {
                    if let Err(why) = rotor_position(r, a, m.sweep_deg) {
                        return bad("hwp_angles_deg", a.to_string(), &why);
                    }
                }
            }
        }
        Ok(())
    }

    /// The optical elements a scene names, each by its own rule (the first refusal), then the
    /// exposure time and the frames' shifts (one per plate angle, at most 100 px).
    fn validate_elements(&self, path: &Path) -> Result<(), Error> {
        let bad = |key: &str, value: String, why: &str| Err(invalid(path, key, value, why));
        let fx = &self.effects;
        let elements = [
            ("effects.constant_response", fx.constant_response.map(|r| (format!("{r:?}"), r.unphysical()))),
            ("effects.stressed_lens", fx.stressed_lens.as_ref().map(|e| (format!("{e:?}"), e.validate().err()))),
            ("effects.tilted_hwp", fx.tilted_hwp.as_ref().map(|e| (format!("{e:?}"), e.validate().err()))),
            ("effects.wedged_hwp", fx.wedged_hwp.as_ref().map(|e| (format!("{e:?}"), e.validate().err()))),
        ];
        let refused = elements.into_iter().find_map(|(k, c)| c.and_then(|(v, why)| Some((k, v, why?))));
        if let Some((key, value, why)) = refused {
            return bad(key, value, &why);
        }
        if !(self.exposure_s.is_finite() && self.exposure_s > 0.0) {
            return bad("exposure_s", self.exposure_s.to_string(), "must be positive");
        }
        if !self.frame_shifts_px.is_empty() {
            if self.frame_shifts_px.len() != self.hwp_angles_deg.len() {
                return bad(
                    "frame_shifts_px",
                    format!("{} shifts", self.frame_shifts_px.len()),
                    &format!("give one [dx, dy] per HWP angle ({})", self.hwp_angles_deg.len()),
                );
            }
            if let Some(s) = self.frame_shifts_px.iter().find(|s| !(s[0].abs() <= 100.0 && s[1].abs() <= 100.0)) {
                return bad(
                    "frame_shifts_px",
                    format!("[{}, {}]", s[0], s[1]),
                    "each shift must be finite and at most 100 px",
                );
            }
        }
        Ok(())
    }

    /// What a two-camera or maskless beam layout cannot simulate: an extended or varying sky,
    /// an instrumental field on the sky, and the geometry the instrument file must give.
    fn validate_layout(&self, inst: &instrument::Instrument, path: &Path) -> Result<(), Error> {
        let bad = |key: &str, value: String, why: &str| Err(invalid(path, key, value, why));
        if inst.polarimetry.layout == instrument::Layout::TwoCameras {
            let why = "a two-camera scene takes a uniform sky and stars (an extended or varying sky would need each camera's \
                       pixels mapped through the camera transform, which is not modelled)";
            if self.sky.as_ref().is_some_and(|s| s.gradient_e_per_arcmin.is_some()) {
                return bad("sky.gradient_e_per_arcmin", "set".into(), why);
            }
            if !self.extended.is_empty() {
                return bad("extended", format!("{} sources", self.extended.len()), why);
            }
            if self.effects.instpol.is_some() && self.sky.is_some() {
                return bad(
                    "effects.instpol",
                    "set".into(),
                    "a two-camera scene applies an instrumental field to its stars only: remove [sky] or the field",
                );
            }
            if inst.polarimetry.cameras.as_ref().is_some_and(|c| c.transform.is_none()) {
                return bad(
                    "instrument",
                    self.instrument.clone(),
                    "simulating two cameras needs the camera transform in [polarimetry.cameras] (where the e images fall)",
                );
            }
        }
        if inst.polarimetry.layout == instrument::Layout::Maskless {
            let why = "a maskless scene takes a uniform sky and stars (the overlapping o and e images of an extended or varying sky are not modelled)";
            if self.sky.as_ref().is_some_and(|s| s.gradient_e_per_arcmin.is_some()) {
                return bad("sky.gradient_e_per_arcmin", "set".into(), why);
            }
            if !self.extended.is_empty() {
                return bad("extended", format!("{} sources", self.extended.len()), why);
            }
            if self.effects.instpol.is_some() && self.sky.is_some() {
                return bad(
                    "effects.instpol",
                    "set".into(),
                    "a maskless scene applies an instrumental field to its stars only: remove [sky] or the field",
                );
            }
            if inst.polarimetry.oe_offset_px.is_none() {
                return bad(
                    "instrument",
                    self.instrument.clone(),
                    "simulating a maskless layout needs the true o/e offset: set [polarimetry] oe_offset_px in the instrument file",
                );
            }
        }
        Ok(())
    }

    /// The output frames' format: BITPIX, the raw bias level, the pre/overscan sizes and the
    /// number of bias frames.
    fn validate_output(&self, path: &Path) -> Result<(), Error> {
        let bad = |key: &str, value: String, why: &str| Err(invalid(path, key, value, why));
        if ![16, -32, -64].contains(&self.output.bitpix) {
            return bad("output.bitpix", self.output.bitpix.to_string(), "must be 16, -32 or -64");
        }
        if let Some(b) = self.output.raw_bias_adu {
            if !(b.is_finite() && (0.0..60000.0).contains(&b)) {
                return bad("output.raw_bias_adu", b.to_string(), "must be a level in [0, 60000) ADU");
            }
        }
        if let Some(s) = self.output.raw_scan_px {
            if s.iter().any(|&n| n > 1000) {
                return bad("output.raw_scan_px", format!("{s:?}"), "pre/overscan sizes must be at most 1000 px");
            }
        }
        if let Some(n) = self.output.bias_frames {
            if !(3..=100).contains(&n) {
                return bad("output.bias_frames", n.to_string(), "must be 3 to 100 (a per-pixel sigma clip needs 3)");
            }
        }
        Ok(())
    }

    /// The light's sources: the transparency's scatter, the sky, each star and each extended
    /// source (fluxes >= 0, polarization degrees fractions, `p^2 + v^2 <= 1`, no circular
    /// polarization through a telescope, positive sizes).
    fn validate_sources(&self, path: &Path) -> Result<(), Error> {
        let bad = |key: &str, value: String, why: &str| Err(invalid(path, key, value, why));
        let frac = |key: &str, v: f64| non_negative_fraction(path, key, v);
        let nonneg = |key: &str, v: f64| non_negative(path, key, v);
        if let Some(t) = self.effects.transparency_rms {
            if !(t.is_finite() && (0.0..0.5).contains(&t)) {
                return bad("effects.transparency_rms", t.to_string(), "a relative rms in [0, 0.5) (0.05 for 5 %)");
            }
        }
        if let Some(s) = &self.sky {
            nonneg("sky.brightness_e", s.brightness_e)?;
            frac("sky.p", s.p)?;
            if !(s.v.abs() <= 1.0 && s.p * s.p + s.v * s.v <= 1.0 + 1e-12) {
                return bad(
                    "sky.v",
                    s.v.to_string(),
                    "V/I is a fraction with p^2 + v^2 <= 1 (no light is more than fully polarized)",
                );
            }
            if s.v != 0.0 && self.telescope.is_some() {
                return bad(
                    "sky.v",
                    s.v.to_string(),
                    "the sky's circular polarization is not carried through [telescope]: the simulator takes (I, Q, U) \
                     through the telescope's matrices",
                );
            }
        }
        for (k, s) in self.stars.iter().enumerate() {
            nonneg(&format!("stars[{k}].flux_e"), s.flux_e)?;
            frac(&format!("stars[{k}].p"), s.p)?;
            if !(s.v.abs() <= 1.0 && s.p * s.p + s.v * s.v <= 1.0 + 1e-12) {
                return bad(
                    &format!("stars[{k}].v"),
                    s.v.to_string(),
                    "V/I is a fraction with p^2 + v^2 <= 1 (no light is more than fully polarized)",
                );
            }
            if s.v != 0.0 && self.telescope.is_some() {
                return bad(
                    &format!("stars[{k}].v"),
                    s.v.to_string(),
                    "a star's circular polarization is not carried through [telescope]: the simulator takes (I, Q, U) \
                     through the telescope's matrices",
                );
            }
            if !(s.fwhm_arcsec.is_finite() && s.fwhm_arcsec > 0.0) {
                return bad(&format!("stars[{k}].fwhm_arcsec"), s.fwhm_arcsec.to_string(), "must be positive");
            }
            if s.psf == Psf::Moffat && !(s.moffat_beta > 1.0) {
                return bad(&format!("stars[{k}].moffat_beta"), s.moffat_beta.to_string(), "must be > 1");
            }
        }
        for (k, e) in self.extended.iter().enumerate() {
            frac(&format!("extended[{k}].p"), e.p)?;
            match e.profile {
                Profile::Image => {
                    if e.image.is_none() {
                        return bad(
                            &format!("extended[{k}].image"),
                            "(absent)".into(),
                            "profile = \"image\" needs a file",
                        );
                    }
                }
                _ => {
                    if !(e.r_e_arcsec > 0.0) {
                        return bad(&format!("extended[{k}].r_e_arcsec"), e.r_e_arcsec.to_string(), "must be positive");
                    }
                    if !(e.sersic_n > 0.0) {
                        return bad(&format!("extended[{k}].sersic_n"), e.sersic_n.to_string(), "must be positive");
                    }
                    if !(e.axis_ratio > 0.0 && e.axis_ratio <= 1.0) {
                        return bad(
                            &format!("extended[{k}].axis_ratio"),
                            e.axis_ratio.to_string(),
                            "must be in (0, 1]",
                        );
                    }
                    nonneg(&format!("extended[{k}].i_e"), e.i_e)?;
                }
            }
        }
        Ok(())
    }

    /// The instrument's and detector's effects: the analyser's transmissions, the
    /// post-analyser term, the plate's harmonics, the flat-field errors, read noise, gain and
    /// cosmic rays (whose hits must fit the detector and its memory).
    fn validate_effects(&self, inst: &instrument::Instrument, path: &Path) -> Result<(), Error> {
        let bad = |key: &str, value: String, why: &str| Err(invalid(path, key, value, why));
        let nonneg = |key: &str, v: f64| non_negative(path, key, v);
        let fx = &self.effects;
        if let Some(w) = &fx.wollaston {
            for (k, v) in [("effects.wollaston.t", Some(w.t)), ("effects.wollaston.s", w.s)] {
                if let Some(v) = v {
                    if !(v > 0.0 && v <= 1.0) {
                        return bad(k, v.to_string(), "a beam transmission is in (0, 1]");
                    }
                }
            }
        }
        if let Some(p) = &fx.post_analyzer {
            if !(p.b.abs() < 1.0) {
                return bad("effects.post_analyzer.b", p.b.to_string(), "|B| must be < 1");
            }
        }
        for (k, h) in [("effects.dust", &fx.dust), ("effects.pleochroism", &fx.pleochroism)] {
            if let Some(h) = h {
                if !(h.amplitude.abs() < 1.0) {
                    return bad(&format!("{k}.amplitude"), h.amplitude.to_string(), "must be < 1 in size");
                }
            }
        }
        if let Some(f) = &fx.flat {
            for (k, v) in [
                ("effects.flat.pixel_rms_o", f.pixel_rms_o),
                ("effects.flat.pixel_rms_e", f.pixel_rms_e),
                ("effects.flat.large_scale_o", f.large_scale_o),
                ("effects.flat.large_scale_e", f.large_scale_e),
            ] {
                if !(v.is_finite() && (0.0..0.5).contains(&v)) {
                    return bad(k, v.to_string(), "flat-field error amplitudes are fractions in [0, 0.5)");
                }
            }
        }
        if let Some(r) = fx.read_noise_e {
            nonneg("effects.read_noise_e", r)?;
        }
        if let Some(g) = fx.gain_e_per_adu {
            if !(g.is_finite() && g > 0.0) {
                return bad("effects.gain_e_per_adu", g.to_string(), "must be positive");
            }
        }
        if let Some(c) = &fx.cosmic_rays {
            nonneg("effects.cosmic_rays.rate_per_frame", c.rate_per_frame)?;
            nonneg("effects.cosmic_rays.energy_e", c.energy_e)?;
            if c.size_px == 0 {
                return bad("effects.cosmic_rays.size_px", "0".into(), "must be >= 1");
            }
            let (nx, ny) = (inst.detector.nx, inst.detector.ny);
            if c.size_px > nx.max(ny) {
                return bad(
                    "effects.cosmic_rays.size_px",
                    c.size_px.to_string(),
                    &format!("a hit larger than the detector ({nx} x {ny} px)"),
                );
            }
            // Each hit is drawn and stored (16 bytes per pixel it touches) before the frame is
            // made: refuse a rate that would cover the detector more than 10 times over, before
            // allocating, and say what it would need.
            let side = |n: usize| c.size_px.min(n) as f64;
            let touched = c.rate_per_frame * side(nx) * side(ny);
            let limit = 10.0 * nx as f64 * ny as f64;
            if touched > limit {
                return bad(
                    "effects.cosmic_rays.rate_per_frame",
                    c.rate_per_frame.to_string(),
                    &format!(
                        "{:.3e} hit pixels per frame (~{:.3e} bytes to hold them) would cover the {nx} x {ny} px \
                         detector more than 10 times: at most {:.3e} hits of {} px per frame",
                        touched,
                        16.0 * touched,
                        limit / (side(nx) * side(ny)),
                        c.size_px
                    ),
                );
            }
        }
        Ok(())
    }
}

/// A scene's value refused: the file, the key, the value given and why.
fn invalid(path: &Path, key: &str, value: String, why: &str) -> Error {
    Error::Invalid { path: path.into(), key: key.into(), value, why: why.into() }
}

/// A polarization degree: a fraction in [0, 1).
fn non_negative_fraction(path: &Path, key: &str, v: f64) -> Result<(), Error> {
    if !(v.is_finite() && (0.0..1.0).contains(&v)) {
        return Err(invalid(
            path,
            key,
            v.to_string(),
            "a polarization degree is a fraction in [0, 1) (0.0174 for 1.74%)",
        ));
    }
    Ok(())
}

/// A flux, a brightness, a noise or a rate: finite and >= 0.
fn non_negative(path: &Path, key: &str, v: f64) -> Result<(), Error> {
    if !(v.is_finite() && v >= 0.0) {
        return Err(invalid(path, key, v.to_string(), "must be a finite number >= 0"));
    }
    Ok(())
}

impl Scene {
    /// The plate causes this scene calls for (`effects.tilted_hwp`, `effects.wedged_hwp`) with
    /// the solver of its plate angles; None when it calls for neither.
    pub fn hwp_causes(&self) -> Result<Option<crate::hwp_causes::HwpCauses>, Error> {
        let fx = &self.effects;
        crate::hwp_causes::HwpCauses::new(fx.tilted_hwp.as_ref(), fx.wedged_hwp.as_ref(), &self.hwp_angles_deg)
    }

    /// The site latitude of the scene's telescope (deg): its own, else the instrument's.
    pub fn site_latitude_deg(&self, inst: &instrument::Instrument) -> Option<f64> {
        self.telescope
            .as_ref()
            .and_then(|t| t.site_latitude_deg)
            .or(inst.telescope.as_ref().and_then(|t| t.site_latitude_deg))
    }

    fn validate_telescope(&self, t: &TelescopeSpec, inst: &instrument::Instrument, path: &Path) -> Result<(), Error> {
        let bad = |key: &str, value: String, why: &str| {
            Err(Error::Invalid { path: path.into(), key: format!("telescope.{key}"), value, why: why.into() })
        };
        if mueller::mirror::MetalTable::builtin(&t.metal).is_err() && !Path::new(&t.metal).is_file() {
            return bad("metal", t.metal.clone(), "is neither a built-in table (aluminium, silver) nor a table file");
        }
        if !(t.factor.is_finite() && t.factor > 0.0 && t.factor < 10.0) {
            return bad("factor", t.factor.to_string(), "a factor on n and k in (0, 10)");
        }
        if !(t.overlayer_thickness_nm.is_finite() && (0.0..=10_000.0).contains(&t.overlayer_thickness_nm)) {
            return bad("overlayer_thickness_nm", t.overlayer_thickness_nm.to_string(), "must be 0 to 10000 nm");
        }
        for (k, v) in [("offset_deg", t.offset_deg), ("rotator_deg", t.rotator_deg)] {
            if !(v.is_finite() && v.abs() <= 360.0) {
                return bad(k, v.to_string(), "an angle in degrees (-360 to 360)");
            }
        }
        if !(t.dec_deg.is_finite() && t.dec_deg.abs() <= 90.0) {
            return bad("dec_deg", t.dec_deg.to_string(), "a declination in degrees (-90 to 90)");
        }
        if !(t.overhead_s.is_finite() && t.overhead_s >= 0.0) {
            return bad("overhead_s", t.overhead_s.to_string(), "must be a finite number >= 0");
        }
        let n = self.hwp_angles_deg.len();
        match (t.ha_start_deg, t.hour_angles_deg.is_empty()) {
            (Some(_), false) | (None, true) => {
                return bad(
                    "hour_angles_deg",
                    format!("{} given, ha_start_deg {:?}", t.hour_angles_deg.len(), t.ha_start_deg),
                    "give either ha_start_deg or hour_angles_deg (one per HWP angle)",
                )
            }
            (None, false) if t.hour_angles_deg.len() != n => {
                return bad(
                    "hour_angles_deg",
                    format!("{} values", t.hour_angles_deg.len()),
                    &format!("give one hour angle per HWP angle ({n})"),
                )
            }
            _ => {}
        }
        if let Some(h) = t.ha_start_deg.iter().chain(&t.hour_angles_deg).find(|h| !(h.is_finite() && h.abs() <= 180.0))
        {
            return bad("ha_start_deg", h.to_string(), "an hour angle in degrees (-180 to 180, positive west)");
        }
        let Some(lat) = self.site_latitude_deg(inst) else {
            return bad(
                "site_latitude_deg",
                "(absent)".into(),
                &format!("give the site latitude here or in the instrument's [telescope] section ({})", inst.name),
            );
        };
        if !(lat.is_finite() && lat.abs() <= 90.0) {
            return bad("site_latitude_deg", lat.to_string(), "a latitude in degrees (-90 to 90)");
        }
        // The target must be up during every exposure (and the parallactic angle defined: not
        // through the zenith).
        let (phi, dec) = (lat.to_radians(), t.dec_deg.to_radians());
        for k in 0..n {
            let (a, b) = t.hour_angles(k, self.exposure_s);
            for h in [a, b] {
                let h = h.to_radians();
                let sin_alt = phi.sin() * dec.sin() + phi.cos() * dec.cos() * h.cos();
                if !(0.0..=1.0 - 1e-9).contains(&sin_alt) {
                    return bad(
                        "dec_deg",
                        t.dec_deg.to_string(),
                        &format!(
                            "exposure {k} at hour angle {:.3} deg: the target is {} from latitude {lat} deg",
                            h.to_degrees(),
                            if sin_alt < 0.0 { "below the horizon" } else { "at the zenith (no parallactic angle)" }
                        ),
                    );
                }
            }
        }
        Ok(())
    }
}

/// The rotor position (as the headers number it) of an exposure sweeping `sweep_deg` about
/// `angle_deg`, for an instrument that reads its plate's range from a rotor position: `Err`
/// unless the range is exactly one of the rotor's positions (`instrument::HwpRotation`).
pub(crate) fn rotor_position(r: &instrument::HwpRotation, angle_deg: f64, sweep_deg: f64) -> Result<i64, String> {
    let n = r.positions_per_turn as f64;
    let step = 360.0 / n;
    let k = ((angle_deg - r.zero_deg) / step - 0.5).round();
    let pos = r.first_position + k.rem_euclid(n) as i64;
    match r.position_range(pos) {
        Ok((mid, d))
            if (d - sweep_deg).abs() < 1e-9
                && ((angle_deg - mid) / 360.0 - ((angle_deg - mid) / 360.0).round()).abs() < 1e-9 =>
        {
            Ok(pos)
        }
        _ => Err(format!(
            "the instrument reads the plate's range from a rotor position of {} per turn ({step} deg each, the first \
             from {} deg): an exposure at {angle_deg} deg sweeping {sweep_deg} deg is not one of them",
            r.positions_per_turn, r.zero_deg
        )),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const MIN: &str = "instrument = \"fors1\"\nfilter = \"V\"\n[sky]\nbrightness_e = 1000\np = 0.01\n";

    #[test]
    fn minimal_scene_gets_defaults() {
        let s = Scene::from_toml_str(MIN, Path::new("s.toml")).unwrap();
        assert_eq!(s.hwp_angles_deg, vec![0.0, 22.5, 45.0, 67.5]);
        assert_eq!(s.output.bitpix, 16);
        assert!(!s.effects.photon_noise && s.effects.instpol.is_none());
    }

    #[test]
    fn unknown_keys_are_named() {
        for (text, key) in [
            (format!("{MIN}brightnes = 3\n"), "brightnes"),
            (format!("{MIN}[effects]\nphoton_nois = true\n"), "photon_nois"),
            (
                format!("{MIN}[effects.instpol]\nkind = \"radial\"\ncoeffs_percent = [0]\ncenter_arcmin = [0, 0]\n"),
                "center_arcmin",
            ),
            (format!("seeed = 3\n{MIN}"), "seeed"),
        ] {
            let e = Scene::from_toml_str(&text, Path::new("scene.toml")).unwrap_err().to_string();
            assert!(e.contains(key) && e.contains("scene.toml"), "{e}");
        }
    }

    #[test]
    fn percent_given_as_fraction_is_refused() {
        let e =
            Scene::from_toml_str(&MIN.replace("p = 0.01", "p = 6.45"), Path::new("s.toml")).unwrap_err().to_string();
        assert!(e.contains("sky.p") && e.contains("fraction"), "{e}");
    }

    #[test]
    fn bad_angles_filter_and_instrument() {
        let e = Scene::from_toml_str(&format!("hwp_angles_deg = [0, 45]\n{MIN}"), Path::new("s.toml")).unwrap_err();
        assert!(e.to_string().contains("hwp_angles_deg"), "{e}");
        // The optimal set in radians by mistake.
        let e =
            Scene::from_toml_str(&format!("hwp_angles_deg = [0, 0.3927, 0.7854, 1.1781]\n{MIN}"), Path::new("s.toml"))
                .unwrap_err();
        assert!(e.to_string().contains("look like radians"), "{e}");
        let e = Scene::from_toml_str(&MIN.replace("\"V\"", "\"Z\""), Path::new("s.toml")).unwrap_err();
        assert!(e.to_string().contains("'Z'"), "{e}");
        let e = Scene::from_toml_str(&MIN.replace("fors1", "nosuch"), Path::new("s.toml")).unwrap_err();
        assert!(e.to_string().contains("nosuch"), "{e}");
    }

    #[test]
    fn prefix_escaping_the_output_folder_is_refused() {
        for pre in ["../x", "/tmp/x", "a/b", "..", ".hidden", ""] {
            let t = format!("{MIN}[output]\nprefix = \"{pre}\"\n");
            let e = Scene::from_toml_str(&t, Path::new("s.toml")).unwrap_err();
            assert!(e.to_string().contains("output.prefix"), "{pre}: {e}");
        }
        let t = format!("{MIN}[output]\nprefix = \"v_band-1\"\n");
        Scene::from_toml_str(&t, Path::new("s.toml")).unwrap();
    }

    #[test]
    fn bad_telescope_sections_are_refused_by_key() {
        // EFOSC2 carries the site latitude; FORS1 (Cassegrain, no latitude) does not.
        let efosc = "instrument = \"efosc2\"\nfilter = \"V\"\n[sky]\nbrightness_e = 1000\n";
        let ok = format!("{efosc}[telescope]\ndec_deg = -30\nha_start_deg = 20\n");
        let s = Scene::from_toml_str(&ok, Path::new("s.toml")).unwrap();
        let t = s.telescope.as_ref().unwrap();
        assert_eq!((t.metal.as_str(), t.factor), ("aluminium", 1.0));
        // Exposures follow each other at the sidereal rate: 300 s is 1.2534 deg of hour angle.
        let (a, b) = t.hour_angles(1, 300.0);
        assert!((a - 20.0 - 300.0 * HA_DEG_PER_S).abs() < 1e-12 && (b - a - 1.253_4).abs() < 1e-4, "{a} {b}");
        for (text, key) in [
            (format!("{efosc}[telescope]\ndec_deg = -30\n"), "telescope.hour_angles_deg"),
            (
                format!("{efosc}[telescope]\ndec_deg = -30\nha_start_deg = 0\nhour_angles_deg = [0, 1, 2, 3]\n"),
                "telescope.hour_angles_deg",
            ),
            (format!("{efosc}[telescope]\ndec_deg = -30\nhour_angles_deg = [0, 1]\n"), "telescope.hour_angles_deg"),
            (format!("{efosc}[telescope]\ndec_deg = 80\nha_start_deg = 10\n"), "below the horizon"),
            (format!("{efosc}[telescope]\ndec_deg = -29.26\nha_start_deg = 0\n"), "zenith"),
            (format!("{efosc}[telescope]\ndec_deg = -30\nha_start_deg = 20\nfactor = 0\n"), "telescope.factor"),
            (format!("{efosc}[telescope]\ndec_deg = -30\nha_start_deg = 20\nmetal = \"gold\"\n"), "telescope.metal"),
            (format!("{efosc}[telescope]\ndec_deg = -30\nha_start_deg = 20\nmirror = 1\n"), "mirror"),
            (format!("{MIN}[telescope]\ndec_deg = -30\nha_start_deg = 20\n"), "telescope.site_latitude_deg"),
        ] {
            let e = Scene::from_toml_str(&text, Path::new("s.toml")).unwrap_err().to_string();
            assert!(e.contains(key) && e.contains("s.toml"), "{key}: {e}");
        }
    }

    #[test]
    fn absurd_cosmic_ray_rate_is_refused_with_its_size() {
        // FORS1 is 2048 x 2048: 1e12 single-pixel hits per frame would need 1.6e13 bytes.
        let t = format!("{MIN}[effects]\ncosmic_rays = {{ rate_per_frame = 1e12, size_px = 1 }}\n");
        let e = Scene::from_toml_str(&t, Path::new("s.toml")).unwrap_err().to_string();
        assert!(e.contains("rate_per_frame") && e.contains("1.000e12") && e.contains("1.600e13"), "{e}");
        // The limit is 10 coverages of the detector: just below it is accepted.
        let ok = 10.0 * 2048.0 * 2048.0 * 0.99;
        let t = format!("{MIN}[effects]\ncosmic_rays = {{ rate_per_frame = {ok}, size_px = 1 }}\n");
        Scene::from_toml_str(&t, Path::new("s.toml")).unwrap();
        let t = format!("{MIN}[effects]\ncosmic_rays = {{ rate_per_frame = 5, size_px = 100000 }}\n");
        let e = Scene::from_toml_str(&t, Path::new("s.toml")).unwrap_err().to_string();
        assert!(e.contains("size_px"), "{e}");
    }
}
