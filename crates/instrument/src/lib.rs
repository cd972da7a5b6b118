//! Instrument definitions: what a dual-beam imaging polarimeter looks like to the software.
//!
//! An instrument file (TOML, in `instruments/`) gives the detector, the field, the focal-plane
//! mask strips and the Wollaston throw (which fix where the ordinary and extraordinary images
//! of each strip fall on the detector), the FITS header keywords that carry the HWP angle and
//! the filter, and the filters with their effective wavelengths and HWP chromatic zero angles.
//! Files are validated on load: unknown keys and impossible values are errors that name the
//! file and the key. This crate holds data and geometry only; no optics, no reduction.

use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};

mod format;
pub mod headers;
mod sky_angle;
pub mod telescope;
pub mod toml_numbers;
pub use format::{Chip, Correction, FrameFormat, NumberOrKeyword};
pub use headers::{Headers, Role};
pub use sky_angle::SkyAngle;
pub use telescope::{Focus, Telescope};

/// Errors while loading an instrument definition.
#[derive(Debug, thiserror::Error)]
pub enum Error {
    #[error("cannot read instrument file {path}: {source}")]
    Io { path: PathBuf, source: std::io::Error },
    #[error("instrument file {path}: {message}")]
    Parse { path: PathBuf, message: String },
    #[error("instrument file {path}: {key} = {value}: {why}")]
    Invalid { path: PathBuf, key: String, value: String, why: String },
    #[error("unknown instrument '{name}': not a file, and not one of the built-in instruments ({known})")]
    Unknown { name: String, known: String },
    #[error("instrument {instrument} has no filter '{filter}' (known: {known})")]
    UnknownFilter { instrument: String, filter: String, known: String },
}

/// Detector geometry and electronics.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Detector {
    pub nx: usize,
    pub ny: usize,
    pub pixel_scale_arcsec: f64,
    pub gain_e_per_adu: f64,
    pub read_noise_e: f64,
    pub saturation_adu: f64,
    #[serde(default)]
    pub bias_adu: f64,
}

/// The field of view.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Field {
    pub width_arcmin: f64,
    pub height_arcmin: f64,
}

/// How the two beams of a sky point reach the detector.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Layout {
    /// A focal-plane strip mask (FORS, EFOSC2, ALFOSC): each open strip of the sky is imaged
    /// twice, side by side along the strip axis; the sky between strips is masked. Sky-field
    /// (extended-source) calibration works.
    #[default]
    Strips,
    /// No mask (a calcite or Savart plate): every point of the sky is imaged twice, the
    /// extraordinary image offset from the ordinary one by a fixed 2-D vector, and the sky of
    /// the two beams overlaps. Point sources work; sky-field calibration is impossible.
    Maskless,
    /// Two detectors behind a polarizing beam splitter (MOPTOP): the o beam falls on one
    /// camera, the e beam on the other. Each exposure is two files, one per camera, placed
    /// side by side in one detector frame by `[format]`'s chips (found by the camera keyword,
    /// paired by the exposure keywords); `[polarimetry.cameras]` says which chip is which, how
    /// the e camera's image is turned, and where a point of the o camera falls on the e
    /// camera. Point sources work; a per-pixel map is refused (the cameras do not share sky
    /// pixels).
    TwoCameras,
}

/// The wave plate before the analyser (`[polarimetry] plate`): a half-wave plate measures
/// linear polarization (`q`, `u`: `eq:F`), a quarter-wave plate circular polarization (`V/I`,
/// `stokes::circular`). Both are `mueller::Hwp` of their nominal retardance.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Plate {
    /// Retardance pi: linear polarization.
    #[default]
    HalfWave,
    /// Retardance pi/2: circular polarization.
    QuarterWave,
}

impl Plate {
    /// The plate's name as the instrument file writes it (`half_wave`, `quarter_wave`).
    pub fn name(self) -> &'static str {
        match self {
            Plate::HalfWave => "half_wave",
            Plate::QuarterWave => "quarter_wave",
        }
    }

    /// The plate's nominal retardance (rad).
    pub fn retardance(self) -> f64 {
        match self {
            Plate::HalfWave => std::f64::consts::PI,
            Plate::QuarterWave => std::f64::consts::FRAC_PI_2,
        }
    }
}

/// How an image is turned relative to another: one of the 8 flips and rotations by multiples
/// of 90 deg that map pixel rows and columns onto rows and columns.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Orientation {
    #[default]
    Identity,
    /// Columns reversed (x -> -x).
    FlipX,
    /// Rows reversed (y -> -y).
    FlipY,
    /// Turned by 180 deg (x -> -x, y -> -y).
    Rot180,
    /// Turned by 90 deg counter-clockwise ((x, y) -> (-y, x)).
    Rot90,
    /// Turned by 270 deg counter-clockwise ((x, y) -> (y, -x)).
    Rot270,
    /// Rows and columns exchanged ((x, y) -> (y, x)).
    Transpose,
    /// The other diagonal ((x, y) -> (-y, -x)).
    AntiTranspose,
}

impl Orientation {
    /// The linear part `[[a, b], [c, d]]`: `(x', y') = (a x + b y, c x + d y)` about the
    /// image's centre.
    pub fn matrix(self) -> [[f64; 2]; 2] {
        match self {
            Orientation::Identity => [[1.0, 0.0], [0.0, 1.0]],
            Orientation::FlipX => [[-1.0, 0.0], [0.0, 1.0]],
            Orientation::FlipY => [[1.0, 0.0], [0.0, -1.0]],
            Orientation::Rot180 => [[-1.0, 0.0], [0.0, -1.0]],
            Orientation::Rot90 => [[0.0, -1.0], [1.0, 0.0]],
            Orientation::Rot270 => [[0.0, 1.0], [-1.0, 0.0]],
            Orientation::Transpose => [[0.0, 1.0], [1.0, 0.0]],
            Orientation::AntiTranspose => [[0.0, -1.0], [-1.0, 0.0]],
        }
    }

    /// Whether the image's width and height trade places.
    pub fn swaps_axes(self) -> bool {
        self.matrix()[0][0] == 0.0
    }

    /// Pixel `(x, y)` of an `nx` x `ny` image (0-based) as it appears in the image turned by
    /// this orientation (of size `ny` x `nx` when [`Self::swaps_axes`]).
    ///
    /// ```
    /// use instrument::Orientation;
    /// // A 10 x 4 image: its pixel (0, 0) is at (9, 0) once flipped in x, (0, 9) once turned
    /// // by 90 deg (a 4 x 10 image), and the turn's inverse brings it back.
    /// assert_eq!(Orientation::FlipX.apply(0.0, 0.0, 10, 4), (9.0, 0.0));
    /// assert_eq!(Orientation::Rot90.apply(0.0, 0.0, 10, 4), (3.0, 0.0));
    /// let (x, y) = Orientation::Rot90.apply(2.5, 1.0, 10, 4);
    /// assert_eq!(Orientation::Rot90.inverse().apply(x, y, 4, 10), (2.5, 1.0));
    /// ```
    pub fn apply(self, x: f64, y: f64, nx: usize, ny: usize) -> (f64, f64) {
        let m = self.matrix();
        let (cx, cy) = (0.5 * (nx as f64 - 1.0), 0.5 * (ny as f64 - 1.0));
        let (ox, oy) = if self.swaps_axes() { (cy, cx) } else { (cx, cy) };
        let (u, v) = (x - cx, y - cy);
        (m[0][0] * u + m[0][1] * v + ox, m[1][0] * u + m[1][1] * v + oy)
    }

    /// The orientation that undoes this one.
    pub fn inverse(self) -> Self {
        match self {
            Orientation::Rot90 => Orientation::Rot270,
            Orientation::Rot270 => Orientation::Rot90,
            o => o,
        }
    }
}

/// The two cameras of a [`Layout::TwoCameras`] instrument (`[polarimetry.cameras]`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Cameras {
    /// The `[format]` chip (by name) that is the camera of the ordinary beam. The sky's pixel
    /// coordinates are this camera's, as read.
    pub o_chip: String,
    /// The `[format]` chip of the extraordinary beam.
    pub e_chip: String,
    /// How the e camera's image, as read, is turned relative to the o camera's (a beam
    /// splitter's reflection flips one of them): the image the e chip holds, turned by this,
    /// shows the sky as the o camera does.
    #[serde(default)]
    pub e_orientation: Orientation,
    /// Where a point of the o camera falls on the e camera once turned by `e_orientation`:
    /// `[a, b, c, d, e, f]` with `x' = a x + b y + c`, `y' = d x + e y + f` (each camera's own
    /// 0-based pixels); absent: measured from the stars of the frames, and refused when fewer
    /// than 3 star pairs match or their residual exceeds `max_residual_px`.
    #[serde(default)]
    pub transform: Option<[f64; 6]>,
    /// The largest RMS residual (px) of a transform measured from star pairs (default 0.5).
    #[serde(default = "default_max_residual")]
    pub max_residual_px: f64,
}

fn default_max_residual() -> f64 {
    0.5
}

/// One term `c * u^i * v^j` of the variation of the o/e offset across the field (px), with
/// `u = (x - cx) / cx`, `v = (y - cy) / cy` the o-image pixel position scaled to [-1, 1] over
/// the detector (`cx = (nx - 1) / 2`, `cy = (ny - 1) / 2`).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct OffsetTerm {
    pub i: u32,
    pub j: u32,
    pub c: f64,
}

impl OffsetTerm {
    /// The sum of `terms` at o pixel `(x, y)` of an `nx` x `ny` detector (px): the one
    /// evaluation of a varying o/e offset, for the instrument's checks and the beam layout.
    ///
    /// ```
    /// use instrument::OffsetTerm;
    /// // 2 + 3 v^2 at the top row of a 101-row detector (v = 1) and at its middle (v = 0).
    /// let t = [OffsetTerm { i: 0, j: 0, c: 2.0 }, OffsetTerm { i: 0, j: 2, c: 3.0 }];
    /// assert_eq!(OffsetTerm::sum(&t, 101, 101, 50.0, 100.0), 5.0);
    /// assert_eq!(OffsetTerm::sum(&t, 101, 101, 50.0, 50.0), 2.0);
    /// ```
    pub fn sum(terms: &[OffsetTerm], nx: usize, ny: usize, x: f64, y: f64) -> f64 {
        if terms.is_empty() {
            return 0.0;
        }
        let cx = 0.5 * (nx as f64 - 1.0);
        let cy = 0.5 * (ny as f64 - 1.0);
        let (u, v) = ((x - cx) / cx.max(0.5), (y - cy) / cy.max(0.5));
        terms.iter().map(|k| k.c * u.powi(k.i as i32) * v.powi(k.j as i32)).sum()
    }
}

/// Polarimetric optics as the detector sees them: beam layout, mask strips, throw, header
/// keywords.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Polarimetry {
    /// `"strips"` (default) or `"maskless"`.
    #[serde(default)]
    pub layout: Layout,
    /// The wave plate: `"half_wave"` (default: linear polarization) or `"quarter_wave"`
    /// (circular polarization; its zero angle is each filter's `qwp_zero_angle_deg`).
    #[serde(default)]
    pub plate: Plate,
    /// Strips: the Wollaston throw (arcsec), also the height of each mask strip.
    #[serde(default)]
    pub throw_arcsec: f64,
    /// Strips: detector axis along which the Wollaston separates the beams: "x" or "y".
    #[serde(default = "default_strip_axis")]
    pub strip_axis: String,
    /// Strips: number of open strips (ignored when `strip_starts_px` lists them).
    #[serde(default)]
    pub strip_count: usize,
    /// Strips: lower edge (0-based pixel, along the strip axis, a real number) of the first
    /// strip's ordinary image; the others follow every two throws.
    #[serde(default)]
    pub first_strip_y_px: f64,
    /// Strips: the lower edges of every strip's ordinary image (px along the strip axis, real
    /// numbers), when the strips are not evenly spaced; replaces `first_strip_y_px` and
    /// `strip_count`.
    #[serde(default)]
    pub strip_starts_px: Option<Vec<f64>>,
    /// Strips: +1: the extraordinary image lies at +throw from the ordinary one; -1: at -throw.
    #[serde(default = "default_sign")]
    pub extraordinary_offset_sign: i32,
    /// Strips: pixels (along the strip axis) not used at each edge of every strip image
    /// (vignetting by the mask edge; room for a throw that varies across the field).
    #[serde(default)]
    pub strip_margin_px: f64,
    /// Strips: how the o/e offset along the strip axis varies across the field, added to the
    /// throw (px): a low-order polynomial of position (FORS2-like distortion).
    #[serde(default)]
    pub throw_terms: Vec<OffsetTerm>,
    /// Maskless: the extraordinary image's offset from the ordinary one `[dx, dy]` (px);
    /// measured from the frames' stars when absent.
    #[serde(default)]
    pub oe_offset_px: Option<[f64; 2]>,
    /// The header keyword of the HWP angle (deg); empty: the headers carry none and the angles
    /// are given with the frames (`--hwp-angles`).
    #[serde(default)]
    pub hwp_angle_keyword: String,
    /// Keywords read in order when a frame lacks `hwp_angle_keyword` (archives of one
    /// instrument write the plate angle under more than one name); the first present is used.
    #[serde(default)]
    pub hwp_angle_fallback_keywords: Vec<String>,
    pub filter_keyword: String,
    #[serde(default = "default_exptime_keyword")]
    pub exptime_keyword: String,
    /// A plate that turns during each exposure (`[polarimetry.rotation]`); absent: the plate
    /// stands still at the angle of `hwp_angle_keyword`.
    #[serde(default)]
    pub rotation: Option<HwpRotation>,
    /// Two cameras (`layout = "two_cameras"`): which chip is which and how they map.
    #[serde(default)]
    pub cameras: Option<Cameras>,
    /// Where the instrument's position angle on the sky is read (`[polarimetry.sky_angle]`):
    /// catalogs and corrected maps then give `chi` north through east. Absent: angles stay in
    /// the instrument's frame.
    #[serde(default)]
    pub sky_angle: Option<SkyAngle>,
}

/// A half-wave plate that turns continuously: each exposure integrates the modulation over the
/// range of plate angles it swept (MOPTOP: the rotor turns without stopping, each exposure
/// covering one of 16 positions per turn). The range is read from the frame's header either as
/// begin and end angles (`begin_keyword`, `end_keyword`), or as a rotor position
/// (`position_keyword`) of `positions_per_turn` equal positions per turn, position
/// `first_position` starting at `zero_deg`. The reduction demodulates with the range's middle
/// angle and its modulation efficiency `sin(2d)/(2d)` (`mueller::hwp_sweep_efficiency`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct HwpRotation {
    /// Keyword of the plate angle (deg) at the start of the exposure.
    #[serde(default)]
    pub begin_keyword: String,
    /// Keyword of the plate angle (deg) at the end of the exposure.
    #[serde(default)]
    pub end_keyword: String,
    /// Keyword of the rotor position (an integer) of the exposure.
    #[serde(default)]
    pub position_keyword: String,
    /// Equal positions per turn of the rotor (each exposure sweeps 360 / this deg).
    #[serde(default)]
    pub positions_per_turn: u32,
    /// The number the headers give the first position (1 for MOPTOP's 1..16).
    #[serde(default = "default_first_position")]
    pub first_position: i64,
    /// The plate angle (deg) at the start of the first position.
    #[serde(default)]
    pub zero_deg: f64,
}

fn default_first_position() -> i64 {
    1
}

impl HwpRotation {
    /// Whether the exposure's range comes from a rotor position (else begin and end angles).
    pub fn by_position(&self) -> bool {
        !self.position_keyword.is_empty()
    }

    /// The middle angle and the sweep (deg) of an exposure from its begin and end angles
    /// (deg). The sweep is `end - begin` taken modulo 360 into (-180, 180] (a turn through
    /// 360 deg during the exposure is not a range the header can express), so a range across
    /// 0 deg (350 to 12.5) sweeps 22.5 deg about 1.25 deg.
    ///
    /// ```
    /// let (mid, d) = instrument::HwpRotation::range(350.0, 12.5);
    /// assert!((mid - 361.25).abs() < 1e-12 && (d - 22.5).abs() < 1e-12);
    /// ```
    pub fn range(begin_deg: f64, end_deg: f64) -> (f64, f64) {
        let mut d = (end_deg - begin_deg).rem_euclid(360.0);
        if d > 180.0 {
            d -= 360.0;
        }
        (begin_deg + 0.5 * d, d)
    }

    /// The middle angle and sweep (deg) of rotor position `pos`: position `first_position`
    /// spans `zero_deg .. zero_deg + 360 / positions_per_turn`, the next the following range.
    /// `Err` with the reason when `pos` is not a position of the turn.
    ///
    /// ```
    /// let r = instrument::HwpRotation { position_keyword: "MOPRPOS".into(), positions_per_turn: 16,
    ///     first_position: 1, zero_deg: 0.0, begin_keyword: String::new(), end_keyword: String::new() };
    /// assert_eq!(r.position_range(1).unwrap(), (11.25, 22.5));
    /// assert_eq!(r.position_range(16).unwrap(), (348.75, 22.5));
    /// assert!(r.position_range(17).is_err());
    /// ```
    pub fn position_range(&self, pos: i64) -> Result<(f64, f64), String> {
        let n = self.positions_per_turn as i64;
        let k = pos - self.first_position;
        if !(0..n).contains(&k) {
            return Err(format!(
                "rotor position {pos} is not one of the {n} positions per turn ({} to {})",
                self.first_position,
                self.first_position + n - 1
            ));
        }
        let step = 360.0 / n as f64;
        Ok((self.zero_deg + (k as f64 + 0.5) * step, step))
    }

    /// The file's checks: one way of giving the range, complete; `Err((key, value, why))`.
    fn check(&self) -> Result<(), (String, String, String)> {
        let key = |k: &str| format!("polarimetry.rotation.{k}");
        let by_angles = !self.begin_keyword.is_empty() || !self.end_keyword.is_empty();
        if by_angles == self.by_position() {
            return Err((
                key("begin_keyword/position_keyword"),
                format!("'{}', '{}' / '{}'", self.begin_keyword, self.end_keyword, self.position_keyword),
                "give either begin_keyword and end_keyword (the exposure's plate angles) or position_keyword with \
                 positions_per_turn (the rotor's position), not both and not neither"
                    .into(),
            ));
        }
        if by_angles && (self.begin_keyword.is_empty() || self.end_keyword.is_empty()) {
            return Err((
                key("begin_keyword/end_keyword"),
                format!("'{}' / '{}'", self.begin_keyword, self.end_keyword),
                "both the begin and the end keyword are needed".into(),
            ));
        }
        if self.by_position() && self.positions_per_turn <= 4 {
            return Err((
                key("positions_per_turn"),
                self.positions_per_turn.to_string(),
                "need more than 4 positions per turn: with 4 or fewer each exposure sweeps 90 deg or more of plate \
                 angle, a whole modulation period, and nothing is modulated (efficiency sin(2d)/(2d) = 0 at 90 deg)"
                    .into(),
            ));
        }
        if !self.by_position() && self.positions_per_turn != 0 {
            return Err((
                key("positions_per_turn"),
                self.positions_per_turn.to_string(),
                "only a rotor position (position_keyword) has positions per turn".into(),
            ));
        }
        if !self.zero_deg.is_finite() {
            return Err((key("zero_deg"), self.zero_deg.to_string(), "must be a finite angle in degrees".into()));
        }
        Ok(())
    }
}

fn default_exptime_keyword() -> String {
    "EXPTIME".into()
}

fn default_strip_axis() -> String {
    "y".into()
}

fn default_sign() -> i32 {
    1
}

/// A filter.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Filter {
    pub name: String,
    #[serde(default)]
    pub aliases: Vec<String>,
    pub lambda_eff_nm: f64,
    /// HWP chromatic zero angle: degrees to add to a measured chi (section `sec:HWP`); `None`
    /// when the instrument file gives none (not yet measured): chi is then reported in the
    /// plate's frame ([`Filter::chi_offset_deg`] is 0) with [`Filter::zero_angle_warning`].
    #[serde(default)]
    pub hwp_chi_offset_deg: Option<f64>,
    /// Quarter-wave plate (`[polarimetry] plate = "quarter_wave"`): the angle (deg) of the
    /// plate's fast axis when the header's plate angle reads 0, i.e. the axis sits at the
    /// header's angle plus this; absent: 0.
    #[serde(default)]
    pub qwp_zero_angle_deg: Option<f64>,
    /// Strips: this filter's variation of the o/e offset, in place of `polarimetry.throw_terms`
    /// (a Wollaston's throw is chromatic: FORS2's differs by 2 px between b_HIGH and v_HIGH).
    /// Frames of this filter are reduced, measured and simulated with it
    /// ([`Instrument::for_filter`]).
    #[serde(default)]
    pub throw_terms: Option<Vec<OffsetTerm>>,
}

impl Filter {
    /// The zero angle to add to a measured chi (deg): the file's, or 0 when it gives none.
    pub fn chi_offset_deg(&self) -> f64 {
        self.hwp_chi_offset_deg.unwrap_or(0.0)
    }

    /// A quarter-wave plate's zero angle (deg): its fast axis sits at the header's plate angle
    /// plus this; 0 when the file gives none.
    pub fn qwp_zero_angle_deg(&self) -> f64 {
        self.qwp_zero_angle_deg.unwrap_or(0.0)
    }

    /// What to tell whoever reads a chi measured in this filter of instrument `inst` when the
    /// instrument file gives no zero angle: the angle is the plate's, off the sky's by an
    /// unknown few degrees.
    pub fn zero_angle_warning(&self, inst: &str) -> Option<String> {
        self.hwp_chi_offset_deg.is_none().then(|| {
            format!(
                "instrument {inst} gives no HWP zero angle for filter {} (hwp_chi_offset_deg): chi is the plate's angle, \
                 off the sky's by the plate's chromatic zero angle (typically a few degrees); measure it on a polarized \
                 standard with `instpol zero-angle` and put it in the instrument file ({ZERO_ANGLE_GUIDE})",
                self.name
            )
        })
    }
}

/// The guide's page on the HWP zero angle and the plate and sky frames, named by the messages
/// that need the concept.
pub const ZERO_ANGLE_GUIDE: &str = "docs/guide/zero-angle.md";

/// Why a throw term is refused ([`bad_term`]).
const BAD_TERM: &str = "each term needs a finite c and powers i, j of at most 8";

/// The first of `terms` without a finite coefficient or with a power above 8, as the file
/// writes it.
fn bad_term(terms: &[OffsetTerm]) -> Option<String> {
    terms
        .iter()
        .find(|t| !t.c.is_finite() || t.i > 8 || t.j > 8)
        .map(|t| format!("{{ i = {}, j = {}, c = {} }}", t.i, t.j, t.c))
}

/// A whole instrument definition.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Instrument {
    pub name: String,
    #[serde(default)]
    pub description: String,
    pub detector: Detector,
    pub field: Field,
    pub polarimetry: Polarimetry,
    pub filters: Vec<Filter>,
    /// Optical prescription of the collimator for polarization ray tracing (optional).
    #[serde(default)]
    pub optics: Option<mueller::raytrace::Prescription>,
    /// How raw frames are laid out (HDUs, chips, overscan, binning); see [`FrameFormat`].
    #[serde(default)]
    pub format: FrameFormat,
    /// The telescope in front of the instrument (focus, mirrors, parallactic-angle and rotator
    /// keywords); see [`telescope`].
    #[serde(default)]
    pub telescope: Option<Telescope>,
    /// How the headers say what a file is (bias, flat, polarimetric exposure, standard), for
    /// sorting a folder of raw files; see [`headers`].
    #[serde(default)]
    pub headers: Option<Headers>,
    /// The definition's TOML text, as read ([`Instrument::from_toml_str`]): products record its
    /// hash, so that a product says which definition made it. `None` for an instrument built
    /// in code.
    #[serde(skip)]
    pub definition: Option<String>,
}

/// One mask strip on the detector: rows `[o_start, o_start + height)` hold its ordinary image
/// and rows `[e_start, e_start + height)` its extraordinary image (along the strip axis).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Strip {
    pub index: usize,
    pub o_start: usize,
    pub e_start: usize,
    pub height: usize,
}

const BUILTIN: &[(&str, &str)] = &[
    ("fors1", include_str!("../../../instruments/fors1.toml")),
    ("calcite", include_str!("../../../instruments/calcite.toml")),
    ("fors2", include_str!("../../../instruments/fors2.toml")),
    ("efosc2", include_str!("../../../instruments/efosc2.toml")),
    ("moptop", include_str!("../../../instruments/moptop.toml")),
];

/// The built-in instrument (its short name, as [`Instrument::load`] takes it) that writes `value`
/// in its files' instrument keyword (FITS `INSTRUME`): the one whose `name` is `value`, or whose
/// `[headers] instrument_values` list it (case-insensitive). `None` when no built-in does.
pub fn builtin_for_keyword(value: &str) -> Option<&'static str> {
    let v = value.trim();
    if v.is_empty() {
        return None;
    }
    BUILTIN.iter().map(|(n, _)| *n).find(|n| Instrument::load(n).is_ok_and(|i| i.writes(v)))
}

/// The names of the built-in instruments, for messages.
pub fn builtin_names() -> Vec<&'static str> {
    BUILTIN.iter().map(|(n, _)| *n).collect()
}

/// The TOML text of a built-in instrument (name case-insensitive), e.g. for provenance hashes.
pub fn builtin_source(name: &str) -> Option<&'static str> {
    let lower = name.to_ascii_lowercase();
    BUILTIN.iter().find(|(n, _)| *n == lower).map(|(_, t)| *t)
}

impl Instrument {
    /// Load a built-in instrument by name (case-insensitive) or an instrument file by path.
    ///
    /// ```
    /// // Built-in instruments by name (any case); anything else is a path.
    /// let efosc2 = instrument::Instrument::load("EFOSC2").unwrap();
    /// assert_eq!(efosc2.detector.pixel_scale_arcsec, 0.24);
    /// assert!(instrument::Instrument::load("no_such_instrument.toml").is_err());
    /// ```
    pub fn load(name_or_path: &str) -> Result<Self, Error> {
        let p = Path::new(name_or_path);
        if p.is_file() {
            return Self::from_file(p);
        }
        let lower = name_or_path.to_ascii_lowercase();
        match BUILTIN.iter().find(|(n, _)| *n == lower) {
            Some((n, text)) => Self::from_toml_str(text, Path::new(&format!("<built-in {n}>"))),
            None => Err(Error::Unknown {
                name: name_or_path.into(),
                known: BUILTIN.iter().map(|(n, _)| *n).collect::<Vec<_>>().join(", "),
            }),
        }
    }

    /// Whether a file whose instrument keyword (FITS `INSTRUME`) holds `value` is this
    /// instrument's: `value` is its name, one of its `[headers] instrument_values`, or the value
    /// by which a chip of its `[format]` is matched on that keyword (a camera named there)
    /// (case-insensitive, blanks trimmed). The one rule of which instrument a file is of.
    pub fn writes(&self, value: &str) -> bool {
        let v = value.trim();
        let key = self.headers.as_ref().map_or("INSTRUME", |h| h.instrument_keyword.as_str());
        let same = |x: &str| x.trim().eq_ignore_ascii_case(v);
        same(&self.name)
            || self.headers.as_ref().is_some_and(|h| h.instrument_values.iter().any(|x| same(x)))
            || self.format.chips.iter().any(|c| {
                c.match_keyword.as_deref().is_some_and(|k| k.trim().eq_ignore_ascii_case(key))
                    && c.match_value.as_deref().is_some_and(same)
            })
    }

    /// Read and validate an instrument file.
    pub fn from_file(path: &Path) -> Result<Self, Error> {
        let text = std::fs::read_to_string(path).map_err(|source| Error::Io { path: path.into(), source })?;
        Self::from_toml_str(&text, path)
    }

    /// Parse and validate instrument TOML; `path` only labels errors.
    pub fn from_toml_str(text: &str, path: &Path) -> Result<Self, Error> {
        if let Some((key, value)) = toml_numbers::first_non_finite(text) {
            return Err(Error::Invalid {
                path: path.into(),
                key,
                value: value.to_string(),
                why: "not a finite number".into(),
            });
        }
        let mut inst: Instrument =
            toml::from_str(text).map_err(|e| Error::Parse { path: path.into(), message: e.to_string() })?;
        inst.validate(path)?;
        inst.definition = Some(text.to_string());
        if let Some(t) = &inst.telescope {
            t.check(path.parent()).map_err(|(key, value, why)| Error::Invalid {
                path: path.into(),
                key,
                value,
                why,
            })?;
        }
        Ok(inst)
    }

    fn validate(&self, path: &Path) -> Result<(), Error> {
        let bad = |key: &str, value: String, why: &str| {
            Err(Error::Invalid { path: path.into(), key: key.into(), value, why: why.into() })
        };
        let d = &self.detector;
        if d.nx == 0 || d.ny == 0 {
            return bad("detector.nx/ny", format!("{} x {}", d.nx, d.ny), "the detector must have pixels");
        }
        // Every reader and the simulator hold whole frames of f64: a bound that a real detector
        // mosaic stays far below (a 4e9 x 4e9 "detector" exhausted memory before this).
        if d.nx > 65_536 || d.ny > 65_536 || d.nx * d.ny > 400_000_000 {
            return bad(
                "detector.nx/ny",
                format!("{} x {}", d.nx, d.ny),
                &format!(
                    "{} Mpx would need {} GB per frame in memory: at most 65536 px a side and 400 Mpx in all",
                    (d.nx as f64 * d.ny as f64 / 1e6).round(),
                    (d.nx as f64 * d.ny as f64 * 8.0 / 1e9).round()
                ),
            );
        }
        for (k, v) in
            [("detector.pixel_scale_arcsec", d.pixel_scale_arcsec), ("detector.gain_e_per_adu", d.gain_e_per_adu)]
        {
            if !(v.is_finite() && v > 0.0) {
                return bad(k, v.to_string(), "must be a positive number");
            }
        }
        if !(d.read_noise_e.is_finite() && d.read_noise_e >= 0.0) {
            return bad("detector.read_noise_e", d.read_noise_e.to_string(), "must be >= 0");
        }
        if !(d.saturation_adu.is_finite() && d.saturation_adu > 0.0) {
            return bad("detector.saturation_adu", d.saturation_adu.to_string(), "must be a positive number");
        }
        match self.polarimetry.layout {
            Layout::Strips => self.validate_strips(path)?,
            Layout::Maskless => self.validate_maskless(path)?,
            Layout::TwoCameras => self.validate_two_cameras(path)?,
        }
        if self.polarimetry.layout != Layout::TwoCameras && self.polarimetry.cameras.is_some() {
            return bad(
                "polarimetry.cameras",
                format!("{:?}", self.polarimetry.layout),
                "only layout = \"two_cameras\" has cameras",
            );
        }
        if let Some(Err((key, value, why))) = self.polarimetry.rotation.as_ref().map(HwpRotation::check) {
            return bad(&key, value, &why);
        }
        if let Some(Err((key, value, why))) = self.polarimetry.sky_angle.as_ref().map(SkyAngle::check) {
            return bad(&key, value, &why);
        }
        let qwp = self.polarimetry.plate == Plate::QuarterWave;
        if qwp && self.polarimetry.rotation.is_some() {
            return bad(
                "polarimetry.rotation",
                "set".into(),
                "a quarter-wave plate that turns during its exposures is not modelled: plate = \"quarter_wave\" takes a \
                 plate standing still at each angle",
            );
        }
        for f in &self.filters {
            if let (true, Some(c)) = (qwp, f.hwp_chi_offset_deg) {
                return bad(
                    &format!("filters.{}.hwp_chi_offset_deg", f.name),
                    c.to_string(),
                    "the plate is a quarter-wave plate (plate = \"quarter_wave\"): its zero angle is qwp_zero_angle_deg, \
                     the angle of its fast axis when the header reads 0",
                );
            }
            if let Some(z) = f.qwp_zero_angle_deg {
                let key = format!("filters.{}.qwp_zero_angle_deg", f.name);
                if !qwp {
                    return bad(
                        &key,
                        z.to_string(),
                        "only a quarter-wave plate (polarimetry.plate = \"quarter_wave\") has this zero angle; a \
                         half-wave plate's is hwp_chi_offset_deg",
                    );
                }
                if !(z.is_finite() && z.abs() <= 90.0) {
                    return bad(&key, z.to_string(), "must be an angle in degrees within +-90");
                }
            }
        }
        if let Err((key, value, why)) = self.format.check(d.nx, d.ny) {
            return bad(&key, value, &why);
        }
        if let Some(Err((key, value, why))) = self.headers.as_ref().map(Headers::check) {
            return bad(&key, value, &why);
        }
        if self.filters.is_empty() {
            return bad("filters", "[]".into(), "need at least one filter");
        }
        // A name (or alias) given to two filters would make the filter a frame is in depend on
        // the order of the file.
        let mut names: Vec<(String, usize)> = vec![];
        for (i, f) in self.filters.iter().enumerate() {
            for n in std::iter::once(&f.name).chain(&f.aliases) {
                let lower = n.to_ascii_lowercase();
                if let Some(&(_, j)) = names.iter().find(|(m, j)| *m == lower && *j != i) {
                    let other = &self.filters[j].name;
                    return bad(
                        &format!("filters.{}", f.name),
                        n.clone(),
                        &format!("the name is also filter {other}'s (names and aliases must be unique, case aside)"),
                    );
                }
                names.push((lower, i));
            }
        }
        for f in &self.filters {
            if !(f.lambda_eff_nm.is_finite() && f.lambda_eff_nm > 100.0 && f.lambda_eff_nm < 30000.0) {
                return bad(
                    &format!("filters.{}.lambda_eff_nm", f.name),
                    f.lambda_eff_nm.to_string(),
                    "must be a wavelength in nm",
                );
            }
            if let Some(t) = &f.throw_terms {
                let key = format!("filters.{}.throw_terms", f.name);
                let value = format!("{} term(s)", t.len());
                if self.polarimetry.layout != Layout::Strips {
                    return bad(&key, value, "only a strip layout has a throw");
                }
                if let Some(k) = bad_term(t) {
                    return bad(&key, k, BAD_TERM);
                }
                if let Err(why) = self.for_filter(&f.name).e_lines_clear() {
                    return bad(&key, value, &why);
                }
            }
        }
        Ok(())
    }

    /// This instrument as frames in filter `filter` see it: the filter's `throw_terms` in place
    /// of the instrument's; the instrument itself when the filter has none (or is unknown).
    pub fn for_filter(&self, filter: &str) -> std::borrow::Cow<'_, Instrument> {
        match self.filter(filter).ok().and_then(|f| f.throw_terms.as_ref()) {
            Some(t) => {
                let mut i = self.clone();
                i.polarimetry.throw_terms = t.clone();
                std::borrow::Cow::Owned(i)
            }
            None => std::borrow::Cow::Borrowed(self),
        }
    }

    /// Strips: `Err` with the reason when the e image of some strip ([`Instrument::e_line_ranges`])
    /// leaves the detector or reaches the o lines of a strip.
    fn e_lines_clear(&self) -> Result<(), String> {
        let p = &self.polarimetry;
        let n = if p.strip_axis == "y" { self.detector.ny } else { self.detector.nx } as i64;
        let strips = self.strips();
        for (s, (lo, hi)) in strips.iter().zip(self.e_line_ranges()) {
            if lo > hi {
                continue;
            }
            if lo < 0 || hi >= n {
                return Err(format!(
                    "the e image of strip {} covers lines {lo}..={hi}, off the detector's {n}",
                    s.index
                ));
            }
            let hit = |o: &&Strip| (o.o_start as i64) <= hi && lo < (o.o_start + o.height) as i64;
            if let Some(o) = strips.iter().find(hit) {
                return Err(format!(
                    "the e image of strip {} covers lines {lo}..={hi}, on the o image of strip {}",
                    s.index, o.index
                ));
            }
        }
        Ok(())
    }

    /// Strips: the first and last line along the strip axis that each strip's e image covers,
    /// one pair per strip of [`Instrument::strips`] (first > last for an empty strip; the
    /// lines may lie off the detector). Without `throw_terms`, the strip's lines from
    /// `e_start`; with them, its o lines moved by the throw and its variation, rounded to whole
    /// lines as the reduction pairs pixels, sampled across the axis every 8 px and at the last
    /// line (once when no term depends on the position across). The one place this is worked
    /// out: the loader checks these lines and the beam layout marks them as e lines.
    pub fn e_line_ranges(&self) -> Vec<(i64, i64)> {
        let p = &self.polarimetry;
        let strips = self.strips();
        if p.throw_terms.is_empty() {
            return strips.iter().map(|s| (s.e_start as i64, (s.e_start + s.height) as i64 - 1)).collect();
        }
        let along_y = p.strip_axis == "y";
        let across = if along_y { self.detector.nx } else { self.detector.ny };
        let across_free = p.throw_terms.iter().all(|t| if along_y { t.i == 0 } else { t.j == 0 });
        let samples: Vec<usize> =
            if across_free { vec![0] } else { (0..across).step_by(8).chain([across.saturating_sub(1)]).collect() };
        let throw = p.extraordinary_offset_sign as f64 * self.throw_px_exact();
        strips
            .iter()
            .map(|s| {
                let (mut lo, mut hi) = (0, -1);
                for a in s.o_start..s.o_start + s.height {
                    for &c in &samples {
                        let (x, y) = if along_y { (c, a) } else { (a, c) };
                        let e = a as i64 + (throw + self.throw_variation_px(x as f64, y as f64)).round() as i64;
                        (lo, hi) = if lo > hi { (e, e) } else { (lo.min(e), hi.max(e)) };
                    }
                }
                (lo, hi)
            })
            .collect()
    }

    fn validate_strips(&self, path: &Path) -> Result<(), Error> {
        let bad = |key: &str, value: String, why: &str| {
            Err(Error::Invalid { path: path.into(), key: key.into(), value, why: why.into() })
        };
        let (d, p) = (&self.detector, &self.polarimetry);
        if p.strip_axis != "x" && p.strip_axis != "y" {
            return bad("polarimetry.strip_axis", p.strip_axis.clone(), "must be \"x\" or \"y\"");
        }
        if p.extraordinary_offset_sign != 1 && p.extraordinary_offset_sign != -1 {
            return bad(
                "polarimetry.extraordinary_offset_sign",
                p.extraordinary_offset_sign.to_string(),
                "must be 1 or -1",
            );
        }
        if !(p.throw_arcsec.is_finite() && p.throw_arcsec > 0.0) {
            return bad(
                "polarimetry.throw_arcsec",
                p.throw_arcsec.to_string(),
                "must be positive (a strip layout needs the Wollaston throw; for a maskless calcite set layout = \"maskless\")",
            );
        }
        if p.oe_offset_px.is_some() {
            return bad(
                "polarimetry.oe_offset_px",
                format!("{:?}", p.oe_offset_px.unwrap_or_default()),
                "is for layout = \"maskless\"; a strip layout's offset is the throw (throw_arcsec, throw_terms)",
            );
        }
        // The strip layout, in floating point first so that absurd values (a throw of 1e308",
        // 2^62 strips) are refused by name instead of overflowing the pixel arithmetic.
        let extent = if p.strip_axis == "y" { d.ny } else { d.nx } as f64;
        let h = p.throw_arcsec / d.pixel_scale_arcsec;
        if !(h >= 1.0 && h <= extent) {
            return bad(
                "polarimetry.throw_arcsec",
                p.throw_arcsec.to_string(),
                &format!(
                    "the throw is {h} px at {} arcsec/px (detector.pixel_scale_arcsec): it must be 1 to {extent} px",
                    d.pixel_scale_arcsec
                ),
            );
        }
        let m = p.strip_margin_px;
        if !(m.is_finite() && m >= 0.0 && 2.0 * m < h - 0.999) {
            return bad(
                "polarimetry.strip_margin_px",
                m.to_string(),
                &format!("must be >= 0 and leave at least one pixel row of the {h} px strips"),
            );
        }
        // The largest change of the throw over the field (|u|, |v| <= 1): it must fit inside
        // the margins, or e pixels near a strip edge would fall behind the mask.
        if let Some(t) = bad_term(&p.throw_terms) {
            return bad("polarimetry.throw_terms", t, BAD_TERM);
        }
        let swing: f64 = p.throw_terms.iter().map(|t| t.c.abs()).sum();
        if swing > m + 1e-9 {
            return bad(
                "polarimetry.throw_terms",
                format!("{} term(s), up to {swing} px", p.throw_terms.len()),
                &format!(
                    "the throw may change by up to {swing} px over the field, more than strip_margin_px = {m}: widen the margin so that no e pixel falls behind the mask"
                ),
            );
        }
        let starts = match &p.strip_starts_px {
            Some(v) => {
                if v.is_empty() {
                    return bad("polarimetry.strip_starts_px", "[]".into(), "need at least one strip");
                }
                if v.len() > 100_000 {
                    return bad("polarimetry.strip_starts_px", format!("{} values", v.len()), "too many strips");
                }
                v.clone()
            }
            None => {
                if p.strip_count == 0 {
                    return bad("polarimetry.strip_count", "0".into(), "need at least one strip");
                }
                let first = p.first_strip_y_px;
                let span = first + 2.0 * p.strip_count as f64 * h;
                if !(first.is_finite() && first >= 0.0 && span <= extent) {
                    let key = if !(first.is_finite() && first >= 0.0 && first < extent) {
                        "polarimetry.first_strip_y_px"
                    } else {
                        "polarimetry.strip_count"
                    };
                    let value = if key.ends_with("count") { p.strip_count.to_string() } else { first.to_string() };
                    return bad(
                        key,
                        value,
                        &format!(
                            "{} strips of {h} px (the throw) from pixel {first} span pixels {first}..{span}, outside the detector (0..{extent})",
                            p.strip_count
                        ),
                    );
                }
                self.strip_o_edges()
            }
        };
        // Every strip's o and e images inside the detector, and no two images overlapping.
        let sign = p.extraordinary_offset_sign as f64;
        let mut spans: Vec<(f64, f64)> = Vec::new();
        for &o in &starts {
            let e = o + sign * h;
            if !(o.is_finite() && o.min(e) >= 0.0 && o.max(e) + h <= extent) {
                return bad(
                    "polarimetry.strip_starts_px",
                    o.to_string(),
                    &format!(
                        "the strip at {o} px has its o image at {o}..{} and its e image at {e}..{} px: outside the detector (0..{extent})",
                        o + h,
                        e + h
                    ),
                );
            }
            spans.push((o, o + h));
            spans.push((e, e + h));
        }
        spans.sort_by(|a, b| a.0.total_cmp(&b.0));
        if let Some(w) = spans.windows(2).find(|w| w[1].0 < w[0].1 - 1e-9) {
            return bad(
                "polarimetry.strip_starts_px",
                format!("{:?}", starts),
                &format!("the strip images at {}..{} px and {}..{} px overlap", w[0].0, w[0].1, w[1].0, w[1].1),
            );
        }
        Ok(())
    }

    fn validate_maskless(&self, path: &Path) -> Result<(), Error> {
        let p = &self.polarimetry;
        let d = &self.detector;
        if let Some([dx, dy]) = p.oe_offset_px {
            let r = dx.hypot(dy);
            if !(dx.is_finite() && dy.is_finite() && r >= 2.0 && dx.abs() < d.nx as f64 && dy.abs() < d.ny as f64) {
                return Err(Error::Invalid {
                    path: path.into(),
                    key: "polarimetry.oe_offset_px".into(),
                    value: format!("[{dx}, {dy}]"),
                    why: format!(
                        "the o/e offset must be at least 2 px long and fit inside the {} x {} px detector",
                        d.nx, d.ny
                    ),
                });
            }
        }
        if p.strip_starts_px.is_some() || !p.throw_terms.is_empty() || p.strip_count != 0 {
            return Err(Error::Invalid {
                path: path.into(),
                key: "polarimetry.layout".into(),
                value: "\"maskless\"".into(),
                why: "a maskless layout has no strips: remove strip_count, strip_starts_px and throw_terms (or use layout = \"strips\")".into(),
            });
        }
        Ok(())
    }

    /// Two cameras: `[polarimetry.cameras]` names two different chips of `[format]`, each in
    /// its own file (found by `match_keyword`); the e chip, turned by `e_orientation`, is the
    /// o chip's size; the transform, when given, is finite and maps the o camera's centre onto
    /// the e camera.
    fn validate_two_cameras(&self, path: &Path) -> Result<(), Error> {
        let bad = |key: &str, value: String, why: String| {
            Err(Error::Invalid { path: path.into(), key: key.into(), value, why })
        };
        let p = &self.polarimetry;
        let Some(c) = &p.cameras else {
            return bad(
                "polarimetry.cameras",
                "(none)".into(),
                "layout = \"two_cameras\" needs [polarimetry.cameras] with o_chip and e_chip (the [format] chips of the two cameras)".into(),
            );
        };
        if p.strip_starts_px.is_some() || !p.throw_terms.is_empty() || p.strip_count != 0 || p.oe_offset_px.is_some() {
            return bad(
                "polarimetry.layout",
                "\"two_cameras\"".into(),
                "two cameras have no strips and no o/e offset: remove strip_count, strip_starts_px, throw_terms and oe_offset_px".into(),
            );
        }
        let chip = |name: &str, key: &str| {
            self.format.chips.iter().find(|ch| ch.name == name).ok_or_else(|| Error::Invalid {
                path: path.into(),
                key: format!("polarimetry.cameras.{key}"),
                value: name.into(),
                why: format!(
                    "not a chip of [format] (chips: {})",
                    self.format.chips.iter().map(|ch| ch.name.as_str()).collect::<Vec<_>>().join(", ")
                ),
            })
        };
        let (o, e) = (chip(&c.o_chip, "o_chip")?, chip(&c.e_chip, "e_chip")?);
        if c.o_chip == c.e_chip {
            return bad(
                "polarimetry.cameras.e_chip",
                c.e_chip.clone(),
                "the o and e cameras must be different chips".into(),
            );
        }
        for ch in [o, e] {
            if ch.match_keyword.is_none() {
                return bad(
                    &format!("format.chips.{}", ch.name),
                    ch.name.clone(),
                    "each camera writes its own file: give the chip match_keyword (the keyword naming the camera) and match_value".into(),
                );
            }
        }
        let [ex, ey] = e.size_px;
        let turned = if c.e_orientation.swaps_axes() { [ey, ex] } else { [ex, ey] };
        if turned != o.size_px {
            return bad(
                "polarimetry.cameras.e_orientation",
                format!("{:?}", c.e_orientation),
                format!(
                    "the e chip turned so is {} x {} px, the o chip {} x {}",
                    turned[0], turned[1], o.size_px[0], o.size_px[1]
                ),
            );
        }
        if let Some(t) = c.transform {
            let [ox, oy] = o.size_px;
            let (cx, cy) = (0.5 * (ox as f64 - 1.0), 0.5 * (oy as f64 - 1.0));
            let (x, y) = (t[0] * cx + t[1] * cy + t[2], t[3] * cx + t[4] * cy + t[5]);
            let det = t[0] * t[4] - t[1] * t[3];
            if !(t.iter().all(|v| v.is_finite())
                && det.abs() > 1e-3
                && x >= -0.5
                && y >= -0.5
                && x < ox as f64
                && y < oy as f64)
            {
                return bad(
                    "polarimetry.cameras.transform",
                    format!("{t:?}"),
                    "must be 6 finite numbers of a regular map that puts the o camera's centre on the e camera".into(),
                );
            }
        }
        if !(c.max_residual_px.is_finite() && c.max_residual_px > 0.0) {
            return bad(
                "polarimetry.cameras.max_residual_px",
                c.max_residual_px.to_string(),
                "must be a positive number of px".into(),
            );
        }
        Ok(())
    }

    /// The Wollaston throw in pixels (exact): the o/e offset of a strip layout before its
    /// variation across the field (`throw_terms`).
    pub fn throw_px_exact(&self) -> f64 {
        self.polarimetry.throw_arcsec / self.detector.pixel_scale_arcsec
    }

    /// The Wollaston throw in pixels (rounded): the whole-pixel o/e shift of a strip layout.
    pub fn throw_px(&self) -> usize {
        self.throw_px_exact().round() as usize
    }

    /// Strips: the lower edges (px along the strip axis, real) of every strip's o image.
    pub fn strip_o_edges(&self) -> Vec<f64> {
        let p = &self.polarimetry;
        if p.layout != Layout::Strips {
            return Vec::new();
        }
        if let Some(v) = &p.strip_starts_px {
            return v.clone();
        }
        let h = self.throw_px_exact();
        let below = if p.extraordinary_offset_sign < 0 { h } else { 0.0 };
        (0..p.strip_count).map(|k| p.first_strip_y_px + 2.0 * k as f64 * h + below).collect()
    }

    /// Strips: the variation of the o/e offset along the strip axis at o pixel `(x, y)` (px,
    /// added to the throw; 0 without `throw_terms`).
    pub fn throw_variation_px(&self, x: f64, y: f64) -> f64 {
        OffsetTerm::sum(&self.polarimetry.throw_terms, self.detector.nx, self.detector.ny, x, y)
    }

    /// The mask strips with the whole pixel rows (along the strip axis) of their o and e
    /// images: the rows lying entirely inside a strip's o image less its margins, and the rows
    /// a whole-pixel throw away. Empty for a maskless layout.
    ///
    /// ```
    /// // FORS1: nine strips, the first o image from row 34, the e image one throw (22" = 110 px)
    /// // above it (PR06, sec:fors1).
    /// let fors1 = instrument::Instrument::load("fors1").unwrap();
    /// let s = fors1.strips();
    /// assert_eq!(s.len(), 9);
    /// assert_eq!((s[0].o_start, s[0].e_start, s[0].height), (34, 144, 110));
    /// ```
    pub fn strips(&self) -> Vec<Strip> {
        let p = &self.polarimetry;
        let h = self.throw_px_exact();
        let m = p.strip_margin_px;
        let shift = p.extraordinary_offset_sign as f64 * h.round();
        self.strip_o_edges()
            .iter()
            .enumerate()
            .map(|(k, &lo)| {
                let a = (lo + m).ceil();
                let b = (lo + h - m).floor();
                let o = a.max(0.0) as usize;
                let height = (b - a).max(0.0) as usize;
                Strip { index: k, o_start: o, e_start: (a + shift).max(0.0) as usize, height }
            })
            .collect()
    }

    /// Whether two filter names mean one filter of this instrument: equal ignoring case and
    /// surrounding blanks, or names (or aliases) of the same filter.
    pub fn same_filter(&self, a: &str, b: &str) -> bool {
        let (a, b) = (a.trim(), b.trim());
        a.eq_ignore_ascii_case(b) || matches!((self.filter(a), self.filter(b)), (Ok(x), Ok(y)) if x.name == y.name)
    }

    /// Find a filter by name or alias (case-insensitive).
    ///
    /// ```
    /// // FORS2's I_BESS zero angle (FORS2 User Manual): 2.89 deg to add to a measured chi; names
    /// // and aliases match, an unknown filter is an error naming the known ones.
    /// let fors2 = instrument::Instrument::load("fors2").unwrap();
    /// assert_eq!(fors2.filter("I").unwrap().chi_offset_deg(), 2.89);
    /// assert!(fors2.filter("Q").unwrap_err().to_string().contains("b_HIGH"));
    /// ```
    pub fn filter(&self, name: &str) -> Result<&Filter, Error> {
        self.filters
            .iter()
            .find(|f| f.name.eq_ignore_ascii_case(name) || f.aliases.iter().any(|a| a.eq_ignore_ascii_case(name)))
            .ok_or_else(|| Error::UnknownFilter {
                instrument: self.name.clone(),
                filter: name.into(),
                known: self.filters.iter().map(|f| f.name.as_str()).collect::<Vec<_>>().join(", "),
            })
    }

    /// Field coordinates (arcmin from the detector centre) of 0-based pixel `(x, y)`.
    pub fn pixel_to_arcmin(&self, x: f64, y: f64) -> (f64, f64) {
        self.field_coords().pixel_to_arcmin(x, y)
    }

    /// 0-based pixel of field position `(x, y)` in arcmin from the detector centre.
    pub fn arcmin_to_pixel(&self, x: f64, y: f64) -> (f64, f64) {
        self.field_coords().arcmin_to_pixel(x, y)
    }

    /// The detector's field coordinates: arcmin from its centre (two cameras: from the o camera's
    /// centre, whose pixels are the sky's), unbinned pixels.
    ///
    /// ```
    /// // FORS1's corner pixel (0, 0) is 1023.5 px x 0.2" = 3.4117' from the centre on both axes.
    /// let c = instrument::Instrument::load("fors1").unwrap().field_coords();
    /// let (x, y) = c.pixel_to_arcmin(0.0, 0.0);
    /// assert!((x + 3.41166666666).abs() < 1e-9 && (y - x).abs() < 1e-15);
    /// ```
    pub fn field_coords(&self) -> field::FieldCoords {
        // Two cameras: the sky's pixels are the o camera's, so its centre is the field's.
        let o_chip = self
            .polarimetry
            .cameras
            .as_ref()
            .filter(|_| self.polarimetry.layout == Layout::TwoCameras)
            .and_then(|c| self.format.chips.iter().find(|ch| ch.name == c.o_chip));
        if let Some(ch) = o_chip {
            let centre = |o: usize, n: usize| o as f64 + 0.5 * (n as f64 - 1.0);
            return field::FieldCoords::with_origin(
                [centre(ch.origin_px[0], ch.size_px[0]), centre(ch.origin_px[1], ch.size_px[1])],
                self.detector.pixel_scale_arcsec,
            );
        }
        field::FieldCoords::centred(self.detector.nx, self.detector.ny, self.detector.pixel_scale_arcsec)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn fors1_loads_with_paper_facts() {
        let f = Instrument::load("fors1").unwrap();
        assert_eq!(f.detector.pixel_scale_arcsec, 0.2);
        assert_eq!(f.polarimetry.throw_arcsec, 22.0);
        assert_eq!(f.throw_px(), 110);
        // 2048 px * 0.2" = 6.83': the paper's 6.8' field.
        assert!((f.detector.nx as f64 * 0.2 / 60.0 - f.field.width_arcmin).abs() < 0.05);
        for b in ["B", "V", "R", "I", "v_bess"] {
            f.filter(b).unwrap();
        }
        assert!(f.filter("Z").is_err());
        let strips = f.strips();
        assert_eq!(strips.len(), 9);
        for w in strips.windows(2) {
            assert_eq!(w[1].o_start - w[0].o_start, 220);
        }
        assert!(strips.last().unwrap().e_start + 110 <= f.detector.ny);
    }

    /// `[polarimetry] plate`: the example quarter-wave instrument loads with its zero angles;
    /// a half-wave instrument by default; each plate's zero-angle key refused on the other
    /// plate, a turning quarter-wave plate and an unknown plate refused, each naming the key.
    #[test]
    fn plate_kind_and_its_zero_angle() {
        let qwp = include_str!("../../../instruments/calcite_qwp.toml");
        let i = Instrument::from_toml_str(qwp, Path::new("q.toml")).unwrap();
        assert_eq!(i.polarimetry.plate, Plate::QuarterWave);
        assert_eq!(i.polarimetry.plate.retardance(), std::f64::consts::FRAC_PI_2);
        assert_eq!(i.filter("V").unwrap().qwp_zero_angle_deg(), 0.0);
        assert_eq!(Instrument::load("calcite").unwrap().polarimetry.plate, Plate::HalfWave);
        let cases = [
            (
                qwp.replace("qwp_zero_angle_deg = 0.0       # [example]\n\n", "qwp_zero_angle_deg = 95.0\n\n"),
                "filters.V.qwp_zero_angle_deg",
            ),
            (
                qwp.replace("qwp_zero_angle_deg = 0.0       # [example]\n\n", "hwp_chi_offset_deg = 1.0\n\n"),
                "filters.V.hwp_chi_offset_deg",
            ),
            (qwp.replace("plate = \"quarter_wave\"", "plate = \"half_wave\""), "filters.V.qwp_zero_angle_deg"),
            (
                qwp.replace(
                    "exptime_keyword = \"EXPTIME\"",
                    "exptime_keyword = \"EXPTIME\"\n[polarimetry.rotation]\nbegin_keyword = \"B\"\nend_keyword = \"E\"",
                ),
                "polarimetry.rotation",
            ),
            (qwp.replace("plate = \"quarter_wave\"", "plate = \"eighth_wave\""), "eighth_wave"),
        ];
        for (text, key) in cases {
            let e = Instrument::from_toml_str(&text, Path::new("q.toml")).unwrap_err().to_string();
            assert!(e.contains(key) && e.contains("q.toml"), "{key}: {e}");
        }
    }

    #[test]
    fn unknown_key_is_named() {
        let text = include_str!("../../../instruments/fors1.toml").replace("throw_arcsec", "throw_arcsek");
        let e = Instrument::from_toml_str(&text, Path::new("x.toml")).unwrap_err().to_string();
        assert!(e.contains("throw_arcsek") && e.contains("x.toml"), "{e}");
    }

    /// `[polarimetry.rotation]`: a rotor position of 16 per turn or begin/end keywords load;
    /// both, neither, half of a pair, 4 positions per turn (90 deg: nothing modulated) and an
    /// unknown key are refused naming the key.
    #[test]
    fn plate_rotation_keys_are_checked() {
        let base = include_str!("../../../instruments/fors1.toml");
        let with = |table: &str| {
            let text =
                base.replace("exptime_keyword = \"EXPTIME\"\n", &format!("exptime_keyword = \"EXPTIME\"\n{table}"));
            assert_ne!(text, base);
            Instrument::from_toml_str(&text, Path::new("x.toml")).map_err(|e| e.to_string())
        };
        let i = with("rotation = { position_keyword = \"MOPRPOS\", positions_per_turn = 16 }\n").unwrap();
        let r = i.polarimetry.rotation.unwrap();
        assert_eq!(r.position_range(2).unwrap(), (33.75, 22.5));
        with("rotation = { begin_keyword = \"ROTBEG\", end_keyword = \"ROTEND\" }\n").unwrap();
        for (table, key) in [
            (
                "rotation = { begin_keyword = \"A\", position_keyword = \"P\", positions_per_turn = 16 }",
                "begin_keyword/position_keyword",
            ),
            ("rotation = { }", "begin_keyword/position_keyword"),
            ("rotation = { begin_keyword = \"A\" }", "begin_keyword/end_keyword"),
            ("rotation = { position_keyword = \"P\", positions_per_turn = 4 }", "positions_per_turn"),
            ("rotation = { position_keyword = \"P\", positions_per_turn = 16, step = 2 }", "step"),
        ] {
            let e = with(&format!("{table}\n")).unwrap_err();
            assert!(e.contains(key) && e.contains("x.toml"), "{table}: {e}");
        }
        assert_eq!(HwpRotation::range(10.0, 32.5), (21.25, 22.5));
        assert_eq!(HwpRotation::range(32.5, 10.0), (21.25, -22.5));
    }

    /// `[polarimetry.sky_angle]`: a keyword with its sense and offset, or the WCS; one of the
    /// two, a sense of +-1 (+1 with the WCS), each mistake refused naming its key and the file.
    #[test]
    fn sky_angle_keys_are_checked() {
        let base = include_str!("../../../instruments/fors1.toml");
        let with = |table: &str| {
            let text =
                base.replace("exptime_keyword = \"EXPTIME\"\n", &format!("exptime_keyword = \"EXPTIME\"\n{table}\n"));
            Instrument::from_toml_str(&text, Path::new("x.toml")).map_err(|e| e.to_string())
        };
        let i = with("sky_angle = { keyword = \"HIERARCH ESO ADA POSANG\", sense = -1, offset_deg = 90 }").unwrap();
        assert_eq!(i.polarimetry.sky_angle.unwrap().position_angle_deg(30.0), 60.0);
        with("sky_angle = { from_wcs = true, offset_deg = 0.5 }").unwrap();
        for (table, key) in [
            ("sky_angle = { keyword = \"ROTSKYPA\", from_wcs = true }", "keyword/from_wcs"),
            ("sky_angle = { sense = 1 }", "keyword/from_wcs"),
            ("sky_angle = { keyword = \"ROTSKYPA\", sense = 2 }", "sense"),
            ("sky_angle = { from_wcs = true, sense = -1 }", "sense"),
            ("sky_angle = { keyword = \"ROTSKYPA\", angle = 2 }", "angle"),
        ] {
            let e = with(table).unwrap_err();
            assert!(e.contains(key) && e.contains("x.toml"), "{table}: {e}");
        }
    }

    /// The built-in MOPTOP as its level-1 frames' headers describe it (instruments/moptop.toml):
    /// two cameras of 1024 px side by side, camera 2 not mirrored, the plate's range from the
    /// rotor's begin and end angles, 0.416" px (a 7.1' field about camera 1's centre), camera
    /// files matched by MOPCNUM and grouped by MOPRNUM and MOPRPOS, bias and flat already
    /// corrected; without its cameras table the layout is refused naming the key.
    #[test]
    fn moptop_loads_with_its_cameras_and_rotor() {
        let m = Instrument::load("moptop").unwrap();
        assert_eq!(m.polarimetry.layout, Layout::TwoCameras);
        let c = m.polarimetry.cameras.as_ref().unwrap();
        assert_eq!((c.o_chip.as_str(), c.e_chip.as_str(), c.e_orientation), ("CAM1", "CAM2", Orientation::Identity));
        let r = m.polarimetry.rotation.as_ref().unwrap();
        assert!(!r.by_position());
        assert_eq!((r.begin_keyword.as_str(), r.end_keyword.as_str()), ("MOPRBEG", "MOPREND"));
        assert_eq!(m.format.exposure_keywords, ["MOPRNUM", "MOPRPOS"]);
        assert!(m.format.already(Correction::Bias) && m.format.already(Correction::Flat));
        let chips: Vec<_> =
            m.format.chips.iter().map(|c| (c.match_keyword.as_deref(), c.match_value.as_deref())).collect();
        assert_eq!(chips, [(Some("MOPCNUM"), Some("1")), (Some("MOPCNUM"), Some("2"))]);
        assert!(m.writes("Moptop"), "both cameras write INSTRUME = 'Moptop'");
        // 1024 px x 0.416" = 7.10': one camera's field.
        assert!((1024.0 * m.detector.pixel_scale_arcsec / 60.0 - m.field.width_arcmin).abs() < 0.01);
        let (x, y) = m.pixel_to_arcmin(511.5, 511.5);
        assert!(x.abs() < 1e-12 && y.abs() < 1e-12, "camera 1's centre is the field's: {x} {y}");
        let text = include_str!("../../../instruments/moptop.toml");
        let cut = &text[..text.find("[polarimetry.cameras]").unwrap()];
        let rest = &text[text.find("[format]").unwrap()..];
        let e = Instrument::from_toml_str(&format!("{cut}{rest}"), Path::new("x.toml")).unwrap_err().to_string();
        assert!(e.contains("polarimetry.cameras"), "{e}");
        let e = Instrument::from_toml_str(&text.replace("o_chip = \"CAM1\"", "o_chip = \"CAM3\""), Path::new("x.toml"))
            .unwrap_err()
            .to_string();
        assert!(e.contains("o_chip") && e.contains("CAM3"), "{e}");
    }

    #[test]
    fn strips_outside_detector_rejected() {
        let text = include_str!("../../../instruments/fors1.toml").replace("strip_count = 9", "strip_count = 10");
        let e = Instrument::from_toml_str(&text, Path::new("x.toml")).unwrap_err().to_string();
        assert!(e.contains("strip_count"), "{e}");
    }

    /// FORS2's chips moved onto each other by a few rows, or side by side, or apart: refused
    /// where they share pixels (named with the first shared pixel), loaded where they do not.
    #[test]
    fn overlapping_chips_rejected() {
        let base = include_str!("../../../instruments/fors2.toml");
        let chip1 = base.find("origin_px = [0, 1040]").expect("CHIP1's origin in fors2.toml");
        let with = |origin: &str| {
            let text = format!("{}{origin}{}", &base[..chip1], &base[chip1 + "origin_px = [0, 1040]".len()..]);
            Instrument::from_toml_str(&text, Path::new("x.toml")).map(|_| ()).map_err(|e| e.to_string())
        };
        with("origin_px = [0, 1040]").unwrap();
        // CHIP2 (given after CHIP1) is rows 0..1024 (x 0..2048): CHIP1 from row 1020 shares
        // rows 1020..1023.
        let e = with("origin_px = [0, 1020]").unwrap_err();
        assert!(e.contains("overlaps chip CHIP1 at pixel (0, 1020)"), "{e}");
        let e = with("origin_px = [0, 0]").unwrap_err();
        assert!(e.contains("overlaps chip CHIP1 at pixel (0, 0)"), "{e}");
        // Touching rows 1024.. is no overlap.
        with("origin_px = [0, 1024]").unwrap();
    }

    #[test]
    fn pixel_arcmin_round_trip() {
        let f = Instrument::load("fors1").unwrap();
        let (x, y) = f.pixel_to_arcmin(1023.5, 1023.5);
        assert!(x.abs() < 1e-12 && y.abs() < 1e-12);
        let (px, py) = f.arcmin_to_pixel(-3.1, 2.2);
        let (ax, ay) = f.pixel_to_arcmin(px, py);
        assert!((ax + 3.1).abs() < 1e-12 && (ay - 2.2).abs() < 1e-12);
    }
}

/// The crate README's example, compiled and run with the documentation tests.
#[cfg(doctest)]
#[doc = include_str!("../README.md")]
pub struct ReadmeDoctests;
