//! Frame reduction: a set of frames at `N` HWP angles to a binned [`StokesMap`].
//!
//! Steps: open the frames and check their headers; group them by filter and HWP angle and
//! check that they form a usable set (one filter, one size, a complete set of angles — for
//! angles on the `22.5 deg` grid the smallest optimal set that contains them, or the `N = 2`
//! pair `{0, 22.5}`; several frames at one angle are summed); then for every sky pixel the
//! mask lets through ([`crate::beams`]) take `f_O,i`, `f_E,i` (bias removed, times the gain:
//! electrons), the one `F_i` (`stokes::normalized_difference`) and `Q/I`, `U/I` from the one
//! `stokes::StokesSolver`, and finally the sigma-clipped mean of each bin ([`crate::bin`]).
//!
//! Frames taken through a quarter-wave plate go through the same steps with the circular
//! demodulation's weights (`stokes::circular`) in place of `eq:Q`'s, and give a map of `V/I`
//! ([`CircularMap`], [`reduce_circular_files_with`]); [`reduce_for_plate`] takes the one the
//! instrument's plate calls for.
//!
//! [`reduce_files`] never holds a frame whole: bands of bin rows are reduced in parallel, each
//! reading the few detector rows it needs from every file just before using them (so reading
//! overlaps computing and the rows are still in cache). [`reduce_set`] does the same from
//! frames in memory; both give the same map to the bit.
//!
//! Pixels are masked (not used) when any of their `2N` values is NaN or infinite (a warning
//! names the file and the count), reaches the instrument's saturation level (warning), or
//! when `f_O + f_E` is not positive (or, absurdly, beyond about `1e+-140` e-, where the
//! variance of `F` is out of f64's range). A frame with no finite pixel is an error.
//!
//! Errors of a bin are given two ways: from the scatter of its kept pixels (`SIGMA_Q`, the
//! honest one, which includes anything the noise model does not know) and propagated from
//! photon and read noise (`SIGQ_PHOT`, `sigma_F^2` of `stokes::variance_normalized_difference`);
//! the two agree for pure photon noise (`eq:sigp` divided by `sqrt(n)`). In bins of fewer than
//! [`SCATTER_MIN_PIXELS`] kept pixels the photon error is `SIGMA_Q`'s floor.

use crate::beams::BeamGeometry;
use crate::bin::{clipped_bin_taking, BinSamples, ClipConfig, PixelSample};
use crate::calib::{avx2_dispatch, Calibrated, MasterRows, ReadOptions, SumScratch};
use crate::fits::{PixelView, RawKind};
use crate::frame::{Conversion, Frame};
use crate::io::{FrameRows, OpenFrame};
use crate::maps::{BinGeometry, CircularMap, StokesMap};
use crate::{Error, Warning};
use instrument::Instrument;
use rayon::prelude::*;
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use stokes::{fast_variance_in_range, normalized_difference, variance_normalized_difference_fast, StokesSolver};

/// Reduction settings.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct ReduceConfig {
    /// Bin side (px); the paper uses 30.
    pub bin_px: usize,
    pub clip: ClipConfig,
    /// Minimum number of kept pixels for a valid bin; `None`: a quarter of a full bin (at
    /// least 3).
    pub min_pixels: Option<usize>,
    /// Refuse an incomplete set of optimal angles (default true).
    pub require_complete_set: bool,
}

impl Default for ReduceConfig {
    fn default() -> Self {
        Self { bin_px: 30, clip: ClipConfig::default(), min_pixels: None, require_complete_set: true }
    }
}

impl ReduceConfig {
    /// Refuse settings no reduction can have, whoever asks (every reduction of frames, in
    /// memory or from files, asks here first): a clipping threshold that is not a positive
    /// number of sigma (a NaN clipped nothing and the map came out as if unclipped).
    pub fn check(&self) -> Result<(), Error> {
        let k = self.clip.nsigma;
        if !(k.is_finite() && k > 0.0) {
            return Err(Error::Invalid(format!(
                "nsigma {k}: the clipping threshold must be a positive number of sigma"
            )));
        }
        Ok(())
    }
}

/// Read frames in parallel; `on_read` is called once per file read (for a progress bar).
/// The first unreadable file (in the order given) is the error.
pub fn read_frames(paths: &[PathBuf], inst: &Instrument, on_read: &(dyn Fn() + Sync)) -> Result<Vec<Frame>, Error> {
    read_frames_with(paths, inst, &ReadOptions::default(), on_read)
}

/// [`read_frames`] with calibration frames and HWP angles ([`ReadOptions`]): one [`Frame`]
/// per exposure, calibrated to electrons when the instrument's format or the options ask
/// for it (see [`crate::calib`]).
pub fn read_frames_with(
    paths: &[PathBuf],
    inst: &Instrument,
    opts: &ReadOptions,
    on_read: &(dyn Fn() + Sync),
) -> Result<Vec<Frame>, Error> {
    if paths.is_empty() {
        return Err(Error::NoFrames);
    }
    let frames = crate::calib::read_exposures(paths, inst, opts)?;
    for _ in paths {
        on_read();
    }
    Ok(frames)
}

/// An opened frame's facts as [`group_frames`] and [`bad_pixel_notes`] take them.
fn open_meta(f: &OpenFrame) -> (&Path, &str, usize, usize, f64) {
    (f.path.as_path(), f.filter.as_str(), f.nx, f.ny, f.hwp_deg)
}

/// Non-finite and saturated pixel counts of one frame.
type BadCounts = (usize, usize);

/// Warnings for masked bad pixels of each file, and the error for a frame none of whose
/// `counted_px` pixels is finite (`bad`: non-finite and saturated counts per file). An
/// exposure assembled from chips is named by its first file here; [`chip_bad_notes`] then
/// replaces its notes by one per chip file.
fn bad_pixel_notes(
    meta: &[(&Path, &str, usize, usize, f64)],
    bad: &[BadCounts],
    counted_px: usize,
    conv: &Conversion,
) -> Result<Vec<Warning>, Error> {
    let sat = conv.saturation_label();
    let mut warnings = Vec::new();
    for (fr, &(nbad, nsat)) in meta.iter().zip(bad) {
        if counted_px > 0 && nbad == counted_px {
            return Err(Error::AllNonFinite { path: fr.0.into() });
        }
        if nbad > 0 {
            warnings.push(Warning { file: Some(fr.0.into()), message: format!("{nbad} NaN/infinite pixels masked") });
        }
        if nsat > 0 {
            warnings.push(Warning {
                file: Some(fr.0.into()),
                message: format!("{nsat} saturated pixels (>= {sat}) masked"),
            });
        }
    }
    Ok(warnings)
}

/// One exposure assembled from chip files: its (first) file, and each chip's place with its
/// non-finite and saturated pixel counts.
type ChipCounts = (PathBuf, Vec<(crate::frame::ChipPlace, BadCounts)>);

/// Each chip's non-finite and saturated pixels of an exposure of `nx` x `ny` assembled from
/// `chips`, counted on the chip's own place over the whole detector; `rows(row0, out)` fills
/// `out` with whole rows from `row0` (bands of [`LOAD_ROWS`]).
fn count_per_chip(
    chips: &[crate::frame::ChipPlace],
    (nx, ny): (usize, usize),
    sat: f64,
    mut rows: impl FnMut(usize, &mut [f64]) -> Result<(), Error>,
) -> Result<Vec<(crate::frame::ChipPlace, BadCounts)>, Error> {
    let mut counts = vec![(0, 0); chips.len()];
    let mut band = Vec::new();
    let mut row0 = 0;
    while row0 < ny {
        let n = LOAD_ROWS.min(ny - row0);
        band.resize(n * nx, 0.0);
        rows(row0, &mut band)?;
        for (c, k) in chips.iter().zip(counts.iter_mut()) {
            for y in c.y0.max(row0)..(c.y0 + c.ny).min(row0 + n).min(ny) {
                let at = (y - row0) * nx;
                let (b, s) = PixelView::F64(&band[at + c.x0.min(nx)..at + (c.x0 + c.nx).min(nx)]).count_bad(sat);
                *k = (k.0 + b, k.1 + s);
            }
        }
        row0 += n;
    }
    Ok(chips.iter().cloned().zip(counts).collect())
}

/// The bad-pixel notes `whole` ([`bad_pixel_notes`] per exposure), with those of each
/// exposure assembled from chips (`chips`) made per chip file: each chip's NaN and saturated
/// pixels counted on its own place and named by its own file, so that a saturated pixel of
/// CHIP2 is reported in the CHIP2 file ([`crate::frame::file_of`]'s decision, by rectangle).
/// Frames in memory and frames read from disk both come here.
fn chip_bad_notes(whole: Vec<Warning>, chips: &[ChipCounts], conv: &Conversion) -> Vec<Warning> {
    let sat = conv.saturation_label();
    let mut out: Vec<Warning> = whole
        .into_iter()
        .filter(|w| !chips.iter().any(|(path, _)| w.file.as_deref() == Some(path.as_path())))
        .collect();
    for (c, (nbad, nsat)) in chips.iter().flat_map(|(_, per)| per) {
        if *nbad > 0 {
            out.push(Warning { file: Some(c.path.clone()), message: format!("{nbad} NaN/infinite pixels masked") });
        }
        if *nsat > 0 {
            out.push(Warning {
                file: Some(c.path.clone()),
                message: format!("{nsat} saturated pixels (>= {sat}) masked"),
            });
        }
    }
    out
}

/// Which pixels of an exposure its bad values are counted over: all of them (a catalog), or
/// those the reduction's pass reads, the o and e pixels of every binned sky pixel (`reduce`:
/// a saturated pixel in a masked strip changes nothing and is not reported).
#[derive(Clone, Copy)]
enum Counted<'a> {
    Whole,
    Used(&'a Instrument, &'a BinGeometry),
}

/// [`chip_bad_notes`]'s counts for the exposures of `frames` read from disk that were
/// assembled from chips and have a bad pixel among those `bad` counted (per exposure): each
/// such exposure is read once more and counted per chip, over the pixels `counted`. Only
/// exposures with a bad pixel are read again (a saturated star in a chip exposure costs one
/// more read of it).
fn disk_chip_counts<'a>(
    frames: impl Iterator<Item = (&'a OpenFrame, BadCounts)>,
    sat: f64,
    counted: Counted<'_>,
) -> Result<Vec<ChipCounts>, Error> {
    let mut out = Vec::new();
    let mut bytes = Vec::new();
    for (f, (nbad, nsat)) in frames {
        let places = f.chip_places();
        if places.is_empty() || nbad + nsat == 0 {
            continue;
        }
        let per = match counted {
            Counted::Whole => {
                count_per_chip(&places, (f.nx, f.ny), sat, |row0, out| f.load_rows(row0, out, &mut bytes))?
            }
            Counted::Used(inst, geom) => {
                let mut data = vec![0.0; f.nx * f.ny];
                f.load_rows(0, &mut data, &mut bytes)?;
                count_used_per_chip(&places, &data, f.nx, inst, geom, sat)
            }
        };
        out.push((f.path.clone(), per));
    }
    Ok(out)
}

/// The non-finite and saturated values of an exposure (`data`, `nx` wide) among the o and e
/// pixels of every sky pixel inside the map's bins `geom`, each given to the chip whose place
/// holds it ([`crate::frame::file_of`]'s rectangles): what the reduction's pass counted, per chip.
fn count_used_per_chip(
    chips: &[crate::frame::ChipPlace],
    data: &[f64],
    nx: usize,
    inst: &Instrument,
    geom: &BinGeometry,
    sat: f64,
) -> Vec<(crate::frame::ChipPlace, BadCounts)> {
    let g = BeamGeometry::new(inst);
    let xs = geom.origin_x..geom.origin_x + geom.nx * geom.bin_px;
    let ys = geom.origin_y..geom.origin_y + geom.ny * geom.bin_px;
    let mut counts = vec![(0, 0); chips.len()];
    let beams =
        g.sky_pixels().filter(|(x, y)| xs.contains(x) && ys.contains(y)).filter_map(|(x, y)| g.beams_of_sky(x, y));
    for k in beams.flat_map(|(o, e)| [o, e]) {
        let v = data[k];
        if let Some(c) = chips.iter().position(|c| c.holds(k % nx, k / nx)) {
            counts[c].0 += usize::from(!v.is_finite());
            counts[c].1 += usize::from(v >= sat);
        }
    }
    chips.iter().cloned().zip(counts).collect()
}

/// What grouping decided: the filter, sorted angles, which frames (indices) at each angle in
/// summing order, and the notes.
struct Grouping {
    filter: String,
    angles: Vec<f64>,
    members: Vec<Vec<usize>>,
    nx: usize,
    ny: usize,
    warnings: Vec<Warning>,
}

/// The checks of [`FrameSet::from_frames`] on frame facts alone (`meta`: path, filter, nx,
/// ny, HWP angle; `sweep_deg`: the set's common sweep, 0 for a fixed plate).
fn group_frames(
    meta: &[(&Path, &str, usize, usize, f64)],
    inst: &Instrument,
    require_complete: bool,
    sweep_deg: f64,
) -> Result<Grouping, Error> {
    if meta.is_empty() {
        return Err(Error::NoFrames);
    }
    check_not_radians(meta)?;
    let mut by_filter: BTreeMap<String, Vec<&Path>> = BTreeMap::new();
    for fr in meta {
        // A filter the instrument does not know has no wavelength or HWP zero angle: an error.
        let canon = inst.filter(fr.1).map(|x| x.name.clone()).map_err(|_| Error::UnknownFilter {
            path: fr.0.into(),
            filter: fr.1.into(),
            instrument: inst.name.clone(),
            known: inst.filters.iter().map(|f| f.name.as_str()).collect::<Vec<_>>().join(", "),
        })?;
        by_filter.entry(canon).or_default().push(fr.0);
    }
    if by_filter.len() > 1 {
        let details: Vec<String> = by_filter
            .iter()
            .map(|(f, ps)| {
                let names: Vec<String> = ps.iter().take(3).map(|p| p.display().to_string()).collect();
                let more = if ps.len() > 3 { format!(" and {} more", ps.len() - 3) } else { String::new() };
                format!("{f}: {}{more}", names.join(", "))
            })
            .collect();
        return Err(Error::MixedFilters { details: details.join("; ") });
    }
    let filter = by_filter.into_keys().next().unwrap_or_default();
    let (nx, ny) = (meta[0].2, meta[0].3);
    for fr in meta {
        if fr.2 != nx || fr.3 != ny {
            return Err(Error::SizeMismatch {
                path: fr.0.into(),
                got_nx: fr.2,
                got_ny: fr.3,
                expected: format!("{} is {nx} x {ny}", meta[0].0.display()),
            });
        }
    }
    let mut warnings = Vec::new();
    // Group by angle (stable sort: repeated exposures are summed in the order given).
    let mut angles: Vec<f64> = Vec::new();
    let mut members: Vec<Vec<usize>> = Vec::new();
    let mut order: Vec<usize> = (0..meta.len()).collect();
    order.sort_by(|&a, &b| meta[a].4.total_cmp(&meta[b].4));
    for k in order {
        let fr = &meta[k];
        match angles.iter().position(|a| (a - fr.4).abs() < ANGLE_TOL_DEG) {
            Some(i) => {
                warnings.push(Warning {
                    file: Some(fr.0.into()),
                    message: format!(
                        "second frame at HWP angle {} deg: summed with {}",
                        fr.4,
                        meta[members[i][0]].0.display()
                    ),
                });
                members[i].push(k);
            }
            None => {
                angles.push(fr.4);
                members.push(vec![k]);
            }
        }
    }
    // The optimal sets are a half-wave plate's, fixed or turning; a quarter-wave plate's
    // angles are judged by the circular demodulation (stokes::CircularSolver), which names a
    // set lacking V.
    if inst.polarimetry.plate == instrument::Plate::HalfWave {
        match check_complete(&filter, &angles, sweep_deg) {
            Err(e) if require_complete => return Err(e),
            // Reduced as asked, by least squares on what is there, with the gap named.
            Err(e) => warnings.push(Warning {
                file: None,
                message: format!("{e}: reduced by least squares on the angles present, as asked"),
            }),
            Ok(()) => {}
        }
    }
    Ok(Grouping { filter, angles, members, nx, ny, warnings })
}

/// HWP angles that are evidently radians (all within [0, 2 pi], every one a multiple of pi/8,
/// not all on the 22.5 deg grid): a header written in the wrong unit would otherwise be read
/// as plate positions a fraction of a degree apart (P 41 % for a 2 % source).
fn check_not_radians(meta: &[(&Path, &str, usize, usize, f64)]) -> Result<(), Error> {
    let a: Vec<f64> = meta.iter().map(|m| m.4).collect();
    let step = std::f64::consts::PI / 8.0;
    let on = |x: f64, s: f64| ((x / s) - (x / s).round()).abs() < 1e-3;
    let distinct = {
        let mut v = a.clone();
        v.sort_by(f64::total_cmp);
        v.dedup_by(|x, y| (*x - *y).abs() < 1e-6);
        v.len()
    };
    let radians = distinct >= 2
        && a.iter().all(|&x| (0.0..=2.0 * std::f64::consts::PI + 1e-6).contains(&x) && on(x, step))
        && !a.iter().all(|&x| on(x, 22.5));
    if radians {
        return Err(Error::Invalid(format!(
            "HWP angles {} (from {} ...) look like radians (multiples of pi/8 = 0.3927): the header keyword must hold degrees (0, 22.5, 45, ...)",
            fmt_angles(&a),
            meta[0].0.display()
        )));
    }
    Ok(())
}

/// A usable set: one filter, one detector size, each HWP angle once (frames at the same
/// angle summed), angles sorted.
#[derive(Debug, Clone)]
pub struct FrameSet {
    /// Canonical filter name (the instrument's, when it knows the filter).
    pub filter: String,
    pub angles_deg: Vec<f64>,
    /// The plate angle every exposure swept (deg; 0: a fixed plate), shared by the set (frames
    /// that swept different ranges are refused).
    pub hwp_sweep_deg: f64,
    /// Summed pixel values (ADU) per angle, row-major.
    pub data: Vec<Vec<f64>>,
    /// Files per angle.
    pub files: Vec<Vec<PathBuf>>,
    pub nx: usize,
    pub ny: usize,
    pub warnings: Vec<Warning>,
    /// How the values become electrons (the instrument's ADU, or electrons already).
    pub conversion: Conversion,
    /// Per angle, the chip files of its first exposure with their places (empty for plain
    /// frames): which file a pixel came from ([`crate::frame::file_of`]).
    pub chips: Vec<Vec<crate::frame::ChipPlace>>,
}

/// Angles (deg) equal within this tolerance are the same plate position.
const ANGLE_TOL_DEG: f64 = 0.05;

fn fmt_angles(a: &[f64]) -> String {
    let v: Vec<String> = a.iter().map(|x| format!("{x} deg")).collect();
    format!("[{}]", v.join(", "))
}

impl FrameSet {
    fn chip_places(&self) -> Vec<Vec<crate::frame::ChipPlace>> {
        self.chips.clone()
    }

    /// Each exposure's file and the HWP angle (deg) it is grouped at, angle by angle.
    pub fn exposures(&self) -> Vec<(PathBuf, f64)> {
        exposures_of(&self.files, &self.angles_deg)
    }

    /// Group and check frames (see the module docs).
    pub fn from_frames(mut frames: Vec<Frame>, inst: &Instrument, require_complete: bool) -> Result<Self, Error> {
        let conversion = common_conversion(frames.iter().map(|f| &f.conversion), inst)?;
        let sat = conversion.saturation;
        let bad: Vec<BadCounts> = frames.par_iter().map(|fr| PixelView::F64(&fr.data).count_bad(sat)).collect();
        let meta: Vec<_> =
            frames.iter().map(|f| (f.path.as_path(), f.filter.as_str(), f.nx, f.ny, f.hwp_deg)).collect();
        let hwp_sweep_deg = common_sweep(frames.iter().map(|f| (f.path.as_path(), f.hwp_sweep_deg)))?;
        let g = group_frames(&meta, inst, require_complete, hwp_sweep_deg)?;
        let chips: Vec<ChipCounts> = frames
            .iter()
            .filter(|f| !f.chips.is_empty())
            .map(|f| {
                let per = count_per_chip(&f.chips, (f.nx, f.ny), sat, |row0, out| {
                    out.copy_from_slice(&f.data[row0 * f.nx..row0 * f.nx + out.len()]);
                    Ok(())
                })?;
                Ok((f.path.clone(), per))
            })
            .collect::<Result<_, Error>>()?;
        let mut warnings = chip_bad_notes(bad_pixel_notes(&meta, &bad, g.nx * g.ny, &conversion)?, &chips, &conversion);
        warnings.extend(g.warnings);
        // Move (not copy) each angle's first frame; add the repeats to it.
        let data: Vec<Vec<f64>> = g
            .members
            .iter()
            .map(|m| {
                let mut d = std::mem::take(&mut frames[m[0]].data);
                for &k in &m[1..] {
                    for (a, s) in d.iter_mut().zip(&frames[k].data) {
                        *a += s;
                    }
                }
                d
            })
            .collect();
        let files = g.members.iter().map(|m| m.iter().map(|&k| frames[k].path.clone()).collect()).collect();
        let chips = g.members.iter().map(|m| frames[m[0]].chips.clone()).collect();
        Ok(Self {
            chips,
            filter: g.filter,
            angles_deg: g.angles,
            hwp_sweep_deg,
            data,
            files,
            nx: g.nx,
            ny: g.ny,
            warnings,
            conversion,
        })
    }
}

/// The plate angle (deg) every one of `frames` swept: the exposures of one reduction share
/// the plate's motion (a turning plate's exposures each sweep one rotor position), so the
/// modulation efficiency `sin(2d)/(2d)` is one number for the set. Sweeps more than 0.05 deg
/// apart are refused naming two files.
pub(crate) fn common_sweep<'a>(mut frames: impl Iterator<Item = (&'a Path, f64)>) -> Result<f64, Error> {
    let Some((p0, d0)) = frames.next() else { return Ok(0.0) };
    for (p, d) in frames {
        if (d - d0).abs() > ANGLE_TOL_DEG {
            return Err(Error::Invalid(format!(
                "{}: the plate swept {d} deg during this exposure but {d0} deg during {}: the frames of one reduction \
                 must share the plate's motion (fixed, or the same range per exposure)",
                p.display(),
                p0.display()
            )));
        }
    }
    Ok(d0)
}

/// The one Stokes solver of a frame set: its HWP angles (deg, the middle of each exposure's
/// range for a turning plate), each with the set's sweep `sweep_deg` (0: the fixed plate's
/// `eq:Q`, `eq:U`; else the averaged modulation, `stokes::StokesSolver::with_sweeps`).
pub fn solver_of(angles_deg: &[f64], sweep_deg: f64) -> Result<StokesSolver, Error> {
    let theta: Vec<f64> = angles_deg.iter().map(|a| a.to_radians()).collect();
    if sweep_deg == 0.0 {
        return Ok(StokesSolver::new(&theta)?);
    }
    Ok(StokesSolver::with_sweeps(&theta, &vec![sweep_deg.to_radians(); theta.len()])?)
}

/// The circular demodulation of plate angles `angles_deg` (deg) with the plate's zero angle
/// (deg): refused, naming the angles, when they do not determine `V`.
pub fn circular_solver(angles_deg: &[f64], zero_angle_deg: f64) -> Result<stokes::CircularSolver, Error> {
    let theta: Vec<f64> = angles_deg.iter().map(|a| a.to_radians()).collect();
    Ok(stokes::CircularSolver::with_zero_angle(&theta, zero_angle_deg.to_radians())?)
}

/// Frames by HWP angle as the catalog measures them, one angle at a time: held in memory
/// ([`FrameSet`]) or read from disk when asked for ([`DiskFrames`]). Either way, angle `i`'s
/// pixels are its exposures summed, in the instrument's ADU or in electrons
/// ([`FrameSource::conversion`]).
pub trait FrameSource: Sync {
    fn nx(&self) -> usize;
    fn ny(&self) -> usize;
    fn filter(&self) -> &str;
    /// HWP angles (deg), sorted.
    fn angles_deg(&self) -> &[f64];
    /// The plate angle every exposure swept (deg; 0: fixed).
    fn hwp_sweep_deg(&self) -> f64;
    /// The exposures of each angle.
    fn files(&self) -> &[Vec<PathBuf>];
    /// Per angle, the chip files of its first exposure with their places (empty for plain
    /// frames), for naming a pixel's file ([`crate::frame::file_of`]).
    fn chips(&self) -> Vec<Vec<crate::frame::ChipPlace>>;
    fn conversion(&self) -> Conversion;
    /// `f` applied to angle `i`'s pixels (row-major).
    fn with_frame<R>(&self, i: usize, f: impl FnOnce(&[f64]) -> R) -> Result<R, Error>;
    /// `f` called as angle `i`'s rows arrive, with the rows read so far from the top
    /// (`rows.len() / nx` whole rows), band after band, the last call with the whole frame; a
    /// frame in memory comes in one call. Work on rows just read finds them in cache.
    fn with_frame_rows(&self, i: usize, f: &mut dyn FnMut(&[f64])) -> Result<(), Error>;
    /// Frame-sized buffers the caller is done with, for the next frames read (frames held in
    /// memory need none).
    fn recycle(&self, _buffers: Vec<Vec<f64>>) {}
}

impl FrameSource for FrameSet {
    fn nx(&self) -> usize {
        self.nx
    }
    fn ny(&self) -> usize {
        self.ny
    }
    fn filter(&self) -> &str {
        &self.filter
    }
    fn angles_deg(&self) -> &[f64] {
        &self.angles_deg
    }
    fn hwp_sweep_deg(&self) -> f64 {
        self.hwp_sweep_deg
    }
    fn files(&self) -> &[Vec<PathBuf>] {
        &self.files
    }
    fn chips(&self) -> Vec<Vec<crate::frame::ChipPlace>> {
        self.chip_places()
    }
    fn conversion(&self) -> Conversion {
        self.conversion
    }
    fn with_frame<R>(&self, i: usize, f: impl FnOnce(&[f64]) -> R) -> Result<R, Error> {
        Ok(f(&self.data[i]))
    }
    fn with_frame_rows(&self, i: usize, f: &mut dyn FnMut(&[f64])) -> Result<(), Error> {
        f(&self.data[i]);
        Ok(())
    }
}

/// Rows read per call when a frame is loaded: small enough that the raw bytes stay in cache
/// between the read and the decoding.
const LOAD_ROWS: usize = 64;

/// A set of frames opened, grouped and checked like a [`FrameSet`], whose pixels stay on disk
/// until an angle is asked for ([`FrameSource::with_frame`]); each request reads its
/// exposures into a buffer taken from a pool and given back after, so that a catalog of 16
/// frames of 2048 x 2048 holds about one frame per thread instead of all of them (fresh
/// memory for every frame, zeroed by the kernel page by page, was a third of a catalog's time).
/// Bad pixels are counted as the frames are read ([`DiskFrames::bad_pixel_warnings`]).
pub struct DiskFrames {
    frames: Vec<OpenFrame>,
    members: Vec<Vec<usize>>,
    filter: String,
    angles: Vec<f64>,
    hwp_sweep_deg: f64,
    files: Vec<Vec<PathBuf>>,
    nx: usize,
    ny: usize,
    conversion: Conversion,
    /// The grouping's notes (frames summed, angles completed, ...).
    pub warnings: Vec<Warning>,
    pool: std::sync::Mutex<Vec<(Vec<f64>, Vec<f64>, Vec<u8>)>>,
    bad: std::sync::Mutex<Vec<Option<BadCounts>>>,
    on_read: Option<Box<dyn Fn() + Send + Sync>>,
}

impl DiskFrames {
    /// Open `paths` (headers checked, calibration frames of `opts` prepared) and group them by
    /// HWP angle as [`FrameSet::from_frames`] does.
    pub fn open(
        paths: &[PathBuf],
        inst: &Instrument,
        opts: &ReadOptions,
        require_complete: bool,
    ) -> Result<Self, Error> {
        if paths.is_empty() {
            return Err(Error::NoFrames);
        }
        let frames: Vec<OpenFrame> = crate::io::open_exposures(paths, inst, opts)?;
        let conversion = common_conversion(frames.iter().map(|f| &f.conversion), inst)?;
        let meta: Vec<_> = frames.iter().map(open_meta).collect();
        let hwp_sweep_deg = common_sweep(frames.iter().map(|f| (f.path.as_path(), f.hwp_sweep_deg)))?;
        let g = group_frames(&meta, inst, require_complete, hwp_sweep_deg)?;
        let files = g.members.iter().map(|m| m.iter().map(|&k| frames[k].path.clone()).collect()).collect();
        let n = frames.len();
        Ok(Self {
            members: g.members,
            filter: g.filter,
            angles: g.angles,
            hwp_sweep_deg,
            files,
            nx: g.nx,
            ny: g.ny,
            conversion,
            warnings: g.warnings,
            pool: std::sync::Mutex::new(Vec::new()),
            bad: std::sync::Mutex::new(vec![None; n]),
            frames,
            on_read: None,
        })
    }

    fn chip_places(&self) -> Vec<Vec<crate::frame::ChipPlace>> {
        self.members.iter().map(|m| self.frames[m[0]].chip_places()).collect()
    }

    /// Call `f` once for every exposure the first time it is read (a progress bar).
    pub fn set_on_read(&mut self, f: Box<dyn Fn() + Send + Sync>) {
        self.on_read = Some(f);
    }

    /// Each exposure's HWP angle (deg), in the order given.
    pub fn exposure_angles_deg(&self) -> Vec<f64> {
        self.frames.iter().map(|f| f.hwp_deg).collect()
    }

    /// Each exposure's file (a chip instrument's: its first chip file) and HWP angle (deg), in
    /// the order given.
    pub fn exposures(&self) -> Vec<(PathBuf, f64)> {
        self.frames.iter().map(|f| (f.path.clone(), f.hwp_deg)).collect()
    }

    /// The warnings of [`FrameSet::from_frames`] for the frames read so far: masked NaN and
    /// saturated pixels per file, then the grouping's notes; an error for a frame none of
    /// whose pixels is finite.
    pub fn bad_pixel_warnings(&self) -> Result<Vec<Warning>, Error> {
        let bad = self.bad.lock().unwrap_or_else(|e| e.into_inner());
        let read: Vec<usize> = (0..self.frames.len()).filter(|&k| bad[k].is_some()).collect();
        let meta: Vec<_> = read.iter().map(|&k| open_meta(&self.frames[k])).collect();
        let counts: Vec<BadCounts> = read.iter().map(|&k| bad[k].unwrap_or_default()).collect();
        let read_counts = read.iter().map(|&k| &self.frames[k]).zip(counts.iter().copied());
        let chips = disk_chip_counts(read_counts, self.conversion.saturation, Counted::Whole)?;
        let whole = bad_pixel_notes(&meta, &counts, self.nx * self.ny, &self.conversion)?;
        let mut w = chip_bad_notes(whole, &chips, &self.conversion);
        w.extend(self.warnings.iter().cloned());
        Ok(w)
    }

    /// Rows `row0 ..` of exposure `k` into `out` (whole rows; `bytes`: scratch), and their
    /// NaN and saturated pixels (counted while the rows are in cache).
    fn load_band(&self, k: usize, row0: usize, out: &mut [f64], bytes: &mut Vec<u8>) -> Result<BadCounts, Error> {
        self.frames[k].load_rows_counting(row0, out, bytes, self.conversion.saturation)
    }

    /// A hash of exposure `k`'s file to feed as its rows are read, with the bytes after its
    /// data (to add last), when the run's provenance waits for it and the rows come straight
    /// from the file as stored; `None` otherwise (the provenance then hashes the file itself).
    fn start_hash(&self, k: usize) -> Result<Option<(crate::provenance::StreamHash, Vec<u8>)>, Error> {
        let fr = &self.frames[k];
        let crate::io::FrameRows::File(r) = &fr.rows else { return Ok(None) };
        if !(fr.path.is_file() && crate::provenance::wants_hash(&fr.path)) {
            return Ok(None);
        }
        let (head, tail) = r.bytes_around_data(&fr.path, self.ny)?;
        let mut h = crate::provenance::StreamHash::default();
        h.update(&head);
        Ok(Some((h, tail)))
    }

    /// Feed the `rows` rows of exposure `k` just read (their stored bytes, in `bytes`) to its hash.
    fn feed(&self, k: usize, h: &mut Option<(crate::provenance::StreamHash, Vec<u8>)>, rows: usize, bytes: &[u8]) {
        if let (Some((h, _)), crate::io::FrameRows::File(r)) = (h.as_mut(), &self.frames[k].rows) {
            h.update(&bytes[..rows * self.nx * r.kind().bytes()]);
        }
    }

    /// Record exposure `k`'s bad-pixel counts (and tell the progress bar the first time).
    fn record(&self, k: usize, counts: BadCounts) {
        let first = self.bad.lock().unwrap_or_else(|e| e.into_inner())[k].replace(counts).is_none();
        if let (true, Some(f)) = (first, &self.on_read) {
            f();
        }
    }
}

impl FrameSource for DiskFrames {
    fn nx(&self) -> usize {
        self.nx
    }
    fn ny(&self) -> usize {
        self.ny
    }
    fn filter(&self) -> &str {
        &self.filter
    }
    fn angles_deg(&self) -> &[f64] {
        &self.angles
    }
    fn hwp_sweep_deg(&self) -> f64 {
        self.hwp_sweep_deg
    }
    fn files(&self) -> &[Vec<PathBuf>] {
        &self.files
    }
    fn chips(&self) -> Vec<Vec<crate::frame::ChipPlace>> {
        self.chip_places()
    }
    fn conversion(&self) -> Conversion {
        self.conversion
    }
    fn with_frame<R>(&self, i: usize, f: impl FnOnce(&[f64]) -> R) -> Result<R, Error> {
        let (n, mut f, mut out) = (self.nx * self.ny, Some(f), None);
        self.with_frame_rows(i, &mut |rows| {
            if rows.len() == n {
                out = f.take().map(|f| f(rows));
            }
        })?;
        out.ok_or(Error::NoFrames)
    }

    fn with_frame_rows(&self, i: usize, f: &mut dyn FnMut(&[f64])) -> Result<(), Error> {
        let taken = self.pool.lock().unwrap_or_else(|e| e.into_inner()).pop();
        let (mut sum, mut one, mut bytes) = taken.unwrap_or_default();
        let (nx, ny) = (self.nx, self.ny);
        crate::par_resize(&mut sum, nx * ny, 0.0);
        let m = &self.members[i];
        let res = (|| {
            let mut counts: Vec<BadCounts> = vec![(0, 0); m.len()];
            // The provenance's hash of each file read straight from disk, fed the rows' bytes
            // as they pass (the file is then read once, not once more by the hashing).
            let mut hashes: Vec<Option<(crate::provenance::StreamHash, Vec<u8>)>> =
                m.iter().map(|&k| self.start_hash(k)).collect::<Result<_, _>>()?;
            let mut row0 = 0;
            while row0 < ny {
                let rows = LOAD_ROWS.min(ny - row0);
                let band = &mut sum[row0 * nx..(row0 + rows) * nx];
                let c = self.load_band(m[0], row0, band, &mut bytes)?;
                counts[0] = (counts[0].0 + c.0, counts[0].1 + c.1);
                self.feed(m[0], &mut hashes[0], rows, &bytes);
                // Repeats are added in the order FrameSet::from_frames adds them (same sums).
                for (j, &k) in m.iter().enumerate().skip(1) {
                    one.resize(rows * nx, 0.0);
                    let c = self.load_band(k, row0, &mut one[..rows * nx], &mut bytes)?;
                    counts[j] = (counts[j].0 + c.0, counts[j].1 + c.1);
                    self.feed(k, &mut hashes[j], rows, &bytes);
                    band.iter_mut().zip(&one).for_each(|(a, s)| *a += s);
                }
                row0 += rows;
                f(&sum[..row0 * nx]);
            }
            for ((&k, &c), h) in m.iter().zip(&counts).zip(hashes) {
                self.record(k, c);
                if let Some((mut h, tail)) = h {
                    h.update(&tail);
                    crate::provenance::record_hash(&self.frames[k].path, h.finish());
                }
            }
            Ok(())
        })();
        self.pool.lock().unwrap_or_else(|e| e.into_inner()).push((sum, one, bytes));
        res
    }
    fn recycle(&self, buffers: Vec<Vec<f64>>) {
        let mut pool = self.pool.lock().unwrap_or_else(|e| e.into_inner());
        pool.extend(buffers.into_iter().map(|b| (b, Vec::new(), Vec::new())));
    }
}

/// The one conversion of a set of frames: all in the instrument's ADU, or all in electrons
/// (then with the largest read noise of them, a conservative noise model).
fn common_conversion<'a>(convs: impl Iterator<Item = &'a Conversion>, inst: &Instrument) -> Result<Conversion, Error> {
    let mut out: Option<Conversion> = None;
    for c in convs {
        out = Some(match out {
            None => *c,
            Some(o) if o.is_electrons() && c.is_electrons() => {
                Conversion::electrons(o.read_noise_e2.max(c.read_noise_e2))
            }
            Some(o) if o == *c => o,
            Some(_) => return Err(Error::Invalid("frames mix calibrated (electrons) and raw (ADU) images".into())),
        });
    }
    Ok(out.unwrap_or_else(|| Conversion::of_instrument(inst)))
}

/// The set's plate angles must be complete ([`plate_set_gap`]): refused naming the missing ones.
fn check_complete(filter: &str, angles: &[f64], sweep_deg: f64) -> Result<(), Error> {
    match plate_set_gap(angles, sweep_deg) {
        None => Ok(()),
        Some(g) => Err(Error::MissingAngle {
            filter: filter.into(),
            have: fmt_angles(angles),
            missing: fmt_angles(&g.missing_deg),
            n: g.n,
            expected: fmt_angles(&g.expected_deg),
        }),
    }
}

/// What an incomplete set of HWP angles lacks ([`optimal_set_gap`]).
#[derive(Debug, Clone, PartialEq)]
pub struct AngleGap {
    /// The size of the smallest optimal set that holds the angles.
    pub n: usize,
    /// That set's angles (deg) and those of them not among the angles.
    pub expected_deg: Vec<f64>,
    pub missing_deg: Vec<f64>,
}

/// The one completeness rule of a set of HWP angles (deg), which the reduction enforces and a
/// scan of raw files uses to name an aborted sequence's missing angles: for angles on the
/// optimal grid (`i * 22.5 deg`), the smallest optimal set containing them must be complete
/// (`{0, 22.5}` is the complete `N = 2` set). `None` when it is, or when the angles are off the
/// grid (least squares on what is there).
pub fn optimal_set_gap(angles: &[f64]) -> Option<AngleGap> {
    grid_set_gap(angles, 0.0, 22.5, true)
}

/// The completeness rule of every half-wave plate, fixed or turning: a fixed plate's angles
/// by [`optimal_set_gap`]; a turning plate's exposures (`sweep_deg > 0`, `angles` the middles
/// of their ranges) are positions of a rotor whose ranges tile the turn, each `sweep_deg`
/// wide, and the set must hold every position of the whole modulation periods (90 deg) it
/// touches, as the fixed plate's optimal set must (a rotor of 16 positions: 4 per period; a
/// turn that does not divide into periods: the whole turn). `None` when complete, or when the
/// angles are not on one grid (least squares on what is there).
pub fn plate_set_gap(angles: &[f64], sweep_deg: f64) -> Option<AngleGap> {
    if sweep_deg == 0.0 {
        return optimal_set_gap(angles);
    }
    let step = sweep_deg.abs();
    if !(step.is_finite() && step > 0.0) {
        return None;
    }
    // The ranges' starts, on a grid offset from 0 by the first one's remainder.
    let starts: Vec<f64> = angles.iter().map(|a| (a - 0.5 * step).rem_euclid(360.0)).collect();
    let offset = starts.first()?.rem_euclid(step);
    let gap = grid_set_gap(&starts, offset, step, false)?;
    let mid = |v: Vec<f64>| v.into_iter().map(|a| a + 0.5 * step).collect();
    Some(AngleGap { n: gap.n, expected_deg: mid(gap.expected_deg), missing_deg: mid(gap.missing_deg) })
}

/// The set gap of `angles` on the grid `offset + i step` (deg): the smallest set of whole
/// modulation periods (90 deg; the whole turn when `step` does not divide 90 deg) containing
/// them, less the angles. `two`: a pair of neighbours is the complete `N = 2` set.
fn grid_set_gap(angles: &[f64], offset: f64, step: f64, two: bool) -> Option<AngleGap> {
    let whole = |x: f64| ((x - x.round()).abs() < 1e-9).then_some(x.round() as usize);
    let per_turn = whole(360.0 / step)?;
    let per = whole(90.0 / step).unwrap_or(per_turn).max(1);
    let idx: Option<Vec<usize>> = angles
        .iter()
        .map(|a| {
            let r = (a - offset) / step;
            ((r - r.round()).abs() * step < ANGLE_TOL_DEG && r.round() >= 0.0).then_some(r.round() as usize)
        })
        .collect();
    let idx = idx?;
    // A half-wave plate at theta + 360 deg is the same plate position, and the modulation
    // (eq:F) repeats every 90 deg: a set such as 90 ... 157.5 or 360 ... 427.5 is the optimal
    // set shifted, not an incomplete one. Indices are taken modulo the turn (360 deg) and
    // shifted by whole periods (90 deg) to start at the first one.
    let idx: Vec<usize> = idx.iter().map(|i| i % per_turn).collect();
    let base = idx.iter().min().map_or(0, |&i| i / per * per);
    let idx: Vec<usize> = idx.iter().map(|i| i - base).collect();
    let m = idx.iter().max().map_or(0, |&i| i + 1);
    if two && m <= 2 && idx.len() == 2 {
        return None;
    }
    let n = m.div_ceil(per).max(1) * per;
    let at = |i: usize| offset + (i + base) as f64 * step;
    let expected: Vec<f64> = (0..n).map(at).collect();
    let missing: Vec<f64> = (0..n).filter(|i| !idx.contains(i)).map(at).collect();
    (!missing.is_empty()).then_some(AngleGap { n, expected_deg: expected, missing_deg: missing })
}

/// The reduced map with the notes gathered on the way.
#[derive(Debug, Clone)]
pub struct Reduced {
    pub map: StokesMap,
    pub warnings: Vec<Warning>,
    /// Each exposure's file and the HWP angle (deg) it was reduced at, angle by angle: what a
    /// caller needs to record the exposures' telescope angles in the map
    /// ([`StokesMap::exposure_tracks`]).
    pub exposures: Vec<(PathBuf, f64)>,
}

/// Each exposure's file and HWP angle, from the files grouped by angle.
fn exposures_of(files: &[Vec<PathBuf>], angles_deg: &[f64]) -> Vec<(PathBuf, f64)> {
    files.iter().zip(angles_deg).flat_map(|(f, &a)| f.iter().map(move |p| (p.clone(), a))).collect()
}

/// A bin side must be a number of pixels that fits the detector (1 ..= its longer side): a bin
/// of 1e11 px overflowed the bin-count arithmetic before it was checked. Every caller of
/// [`reduce_files_with`] with a user's bin (the CLI, the Python package) checks it here.
pub fn check_bin(bin_px: usize, inst: &Instrument) -> Result<(), Error> {
    let side = inst.detector.nx.max(inst.detector.ny);
    if bin_px == 0 || bin_px > side {
        return Err(Error::Invalid(format!(
            "a bin side in pixels must be between 1 and the detector's {side} px ({} is {} x {} px)",
            inst.name, inst.detector.nx, inst.detector.ny
        )));
    }
    Ok(())
}

/// The bin grid used for an instrument: `bin_px` bins starting at the first sky band.
pub fn bin_geometry(inst: &Instrument, bin_px: usize) -> BinGeometry {
    let g = BeamGeometry::new(inst);
    let first = g.sky_bands().iter().map(|r| r.start).min().unwrap_or(0);
    let (ox, oy) = if g.along_y { (0, first) } else { (first, 0) };
    BinGeometry::covering(bin_px, ox, oy, g.nx, g.ny, inst.detector.pixel_scale_arcsec)
}

/// A Stokes map holds `Q/I`, `U/I`: refused, with the reason and what works instead, for an
/// instrument whose plate is a quarter-wave plate.
fn require_half_wave(inst: &Instrument) -> Result<(), Error> {
    if inst.polarimetry.plate == instrument::Plate::QuarterWave {
        return Err(Error::Invalid(format!(
            "instrument {} has a quarter-wave plate (plate = \"quarter_wave\"): its 2- and 4-position sets do not \
             determine Q/I and U/I, which a Stokes map and a sky-field calibration need; its frames give a V/I map \
             (instpol reduce) and the V/I of stars (photometry, catalog)",
            inst.name
        )));
    }
    Ok(())
}

/// A circular map holds `V/I`, which a half-wave plate does not modulate: refused, naming the
/// instrument's plate.
fn require_quarter_wave(inst: &Instrument) -> Result<(), Error> {
    if inst.polarimetry.plate != instrument::Plate::QuarterWave {
        return Err(Error::Invalid(format!(
            "instrument {} has a half-wave plate, which does not modulate V/I: its frames reduce to a Q/I, U/I map \
             (reduce_files_with)",
            inst.name
        )));
    }
    Ok(())
}

/// The weights each angle's `F_i` is folded with, per pixel, by the reduction's kernel.
struct PlateWeights {
    cq: Vec<f64>,
    cu: Vec<f64>,
    /// A quarter-wave plate's zero angle (deg) the demodulation used; `None` for a half-wave
    /// plate.
    qwp_zero_deg: Option<f64>,
}

/// The kernel's weights for the instrument's plate. A half-wave plate: `eq:Q`'s and `eq:U`'s
/// (`StokesSolver`, with the modulation a turning plate averages). A quarter-wave plate: the
/// circular demodulation's `w_i` of `v = sum w_i F_i` (`stokes::circular`, at the plate's
/// axis angles: the angles plus the filter's `qwp_zero_angle_deg`) in the first slot and zeros
/// in the second, so the kernel's `Q` sums carry `V/I` and its photon variance, and its `U`
/// sums stay 0 (the bins' clipping of that column then rejects nothing). A turning
/// quarter-wave plate is refused, as photometry and catalog refuse it.
fn plate_weights(inst: &Instrument, filter: &str, angles_deg: &[f64], sweep_deg: f64) -> Result<PlateWeights, Error> {
    match inst.polarimetry.plate {
        instrument::Plate::HalfWave => {
            let solver = solver_of(angles_deg, sweep_deg)?;
            let (cq, cu) = solver.weights();
            Ok(PlateWeights { cq: cq.to_vec(), cu: cu.to_vec(), qwp_zero_deg: None })
        }
        instrument::Plate::QuarterWave => {
            if sweep_deg != 0.0 {
                return Err(Error::Invalid(format!(
                    "the frames' plate swept {sweep_deg} deg during each exposure: a turning quarter-wave plate is not \
                     modelled"
                )));
            }
            // As photometry and catalog take it: 0 for a filter the instrument does not know.
            let zero = inst.filter(filter).map_or(0.0, |f| f.qwp_zero_angle_deg());
            let solver = circular_solver(angles_deg, zero)?;
            let w = solver.weights().to_vec();
            Ok(PlateWeights { cu: vec![0.0; w.len()], cq: w, qwp_zero_deg: Some(zero) })
        }
    }
}

/// Per-pixel `Q/I`, `U/I` of every sky pixel (NaN where masked or outside the sky bands),
/// row-major over the detector in o coordinates: for inspection and tests. Computed by the
/// reduction's own kernel, row by row.
pub fn pixel_qu(set: &FrameSet, inst: &Instrument) -> Result<(Vec<f64>, Vec<f64>), Error> {
    let inst = &*inst.for_filter(&set.filter);
    require_half_wave(inst)?;
    let solver = solver_of(&set.angles_deg, set.hwp_sweep_deg)?;
    let (cq, cu) = solver.weights();
    let g = BeamGeometry::new(inst);
    g.require_separable_sky().map_err(Error::Invalid)?;
    let det = set.conversion.det();
    let rows: Vec<Rows> = set.data.iter().map(|v| Rows::View(PixelView::F64(v))).collect();
    let mut q = vec![f64::NAN; g.nx * g.ny];
    let mut u = vec![f64::NAN; g.nx * g.ny];
    let (mut k, mut segs) = (Kernel::new(), Vec::new());
    for y in 0..g.ny {
        segments_of_row(&g, y, 0, g.nx, &mut segs);
        for &(x0, x1, o0, e0) in &segs {
            for c0 in (0..x1 - x0).step_by(CHUNK) {
                let len = CHUNK.min(x1 - x0 - c0);
                k.reset(len);
                for (i, r) in rows.iter().enumerate() {
                    let (o, e) = ((o0 + c0, 0), (e0 + c0, 0));
                    k.fold_angle(Fold { rows: r, o, e, len, nexp: set.files[i].len(), w: (cq[i], cu[i]), det });
                }
                for j in (0..len).filter(|&j| k.ok[j] != 0) {
                    q[o0 + c0 + j] = k.q[j];
                    u[o0 + c0 + j] = k.u[j];
                }
            }
        }
    }
    Ok((q, u))
}

/// Reduce a checked frame set to a binned Stokes map (a half-wave plate's frames; a
/// quarter-wave plate's are refused: [`reduce_circular_set`]).
pub fn reduce_set(set: &FrameSet, inst: &Instrument, cfg: &ReduceConfig) -> Result<Reduced, Error> {
    require_half_wave(inst)?;
    Ok(reduce_set_plate(set, inst, cfg)?.0)
}

/// Reduce a checked frame set taken through a quarter-wave plate to a binned `V/I` map (a
/// half-wave plate's frames are refused: [`reduce_set`]).
pub fn reduce_circular_set(set: &FrameSet, inst: &Instrument, cfg: &ReduceConfig) -> Result<CircularReduced, Error> {
    require_quarter_wave(inst)?;
    let (r, zero) = reduce_set_plate(set, inst, cfg)?;
    Ok(CircularReduced::of(r, zero))
}

/// The reduction of a frame set with the weights of the instrument's plate
/// ([`plate_weights`]): the map of a half-wave plate, or the carrier of a quarter-wave plate's
/// `V/I` ([`CircularReduced::of`]) with the zero angle used.
fn reduce_set_plate(set: &FrameSet, inst: &Instrument, cfg: &ReduceConfig) -> Result<(Reduced, Option<f64>), Error> {
    cfg.check()?;
    if inst.polarimetry.layout == instrument::Layout::TwoCameras {
        return reduce_two_cameras(set, inst, cfg);
    }
    // The beam layout of the frames' filter (its own throw, when the instrument gives one).
    let inst = &*inst.for_filter(&set.filter);
    let inputs: Vec<AngleInput> = set
        .data
        .iter()
        .zip(&set.files)
        .map(|(d, f)| AngleInput {
            members: vec![Member::View(PixelView::F64(d))],
            nexp: f.len(),
            det: set.conversion.det(),
        })
        .collect();
    // The masked strips of each angle's sum, its bias that of the exposures summed.
    let g = BeamGeometry::new(inst);
    let rows = crate::pedestal::sample_rows(&g);
    let mut warnings = set.warnings.clone();
    for (d, f) in set.data.iter().zip(&set.files) {
        let n = f.len() as f64;
        let r: Vec<(usize, &[f64])> = rows.iter().map(|&y| (y, &d[y * set.nx..(y + 1) * set.nx])).collect();
        let c = &set.conversion;
        if let Some(l) = crate::pedestal::levels(&g, &r, n * c.bias, n * c.saturation) {
            warnings.extend(crate::pedestal::judge(&f[0], &l, n * c.bias)?);
        }
    }
    let pass =
        reduce_bands(&inputs, 0, set.nx, set.ny, (&set.filter, &set.angles_deg, set.hwp_sweep_deg), inst, cfg, &|| {})?;
    let map = assemble_map(pass.stats, inst, cfg, &set.filter, &set.angles_deg, &inputs)?;
    Ok((Reduced { map, warnings, exposures: exposures_of(&set.files, &set.angles_deg) }, pass.qwp_zero_deg))
}

/// Two cameras (`layout = "two_cameras"`): the e camera of every angle resampled onto the o
/// camera's pixels through the camera transform (the instrument file's, or measured from the
/// stars of the first angle's frame, [`crate::layout`]), by bilinear interpolation
/// ([`crate::beams::CameraMap::e_value`]), and the pair laid out as the one strip of a strip
/// layout (o camera in rows `0..h`, its resampled e image in rows `h..2h`), which the
/// reduction proper then takes as it takes a mask strip. The map is put on the o camera's own
/// pixels ([`on_o_camera`]).
///
/// Errors: a resampled pixel is a weighted mean of four e pixels, so neighbouring pixels share
/// noise and each one's scatter is below an e pixel's (the weights' squares sum to 1/4 ... 1);
/// the scatter of a bin's pixels then understates the error of its mean. The photon and read
/// noise propagated pixel by pixel (`SIGQ_PHOT`) counts each pixel's full variance as if
/// independent, which for a transform that keeps pixel areas (each e pixel's weights over the o
/// grid sum to about 1) is the variance of the bin's mean. So a two-camera map's `SIGMA_Q`,
/// `SIGMA_U` are the larger of the scatter error and the photon error in every bin (not only in
/// bins of fewer than [`SCATTER_MIN_PIXELS`]).
fn reduce_two_cameras(set: &FrameSet, inst: &Instrument, cfg: &ReduceConfig) -> Result<(Reduced, Option<f64>), Error> {
    let img = set.data.first().ok_or(Error::NoFrames)?;
    let g = crate::layout::layout_of_image(img, set.nx, set.ny, &set.files[0][0], &inst.for_filter(&set.filter))?;
    let no_map = || Error::Invalid(format!("instrument {}: two cameras without their camera map", inst.name));
    let c = g.cameras.as_ref().ok_or_else(no_map)?;
    let t = c.transform.ok_or_else(no_map)?;
    let (w, h) = c.o_size;
    let nx = set.nx;
    let data: Vec<Vec<f64>> = set
        .data
        .par_iter()
        .zip(&set.files)
        .map(|(d, files)| {
            // The angle's sum of `files.len()` exposures saturates at that many times the level.
            let sat = set.conversion.saturation * files.len() as f64;
            let mut out = vec![f64::NAN; 2 * w * h];
            for v in 0..h {
                let row = (c.o_origin.1 + v) * nx + c.o_origin.0;
                out[v * w..(v + 1) * w].copy_from_slice(&d[row..row + w]);
                for u in 0..w {
                    out[(h + v) * w + u] = c.e_value(d, nx, &t, u, v, sat);
                }
            }
            out
        })
        .collect();
    // The strip layout of the pair: one strip of h rows from row 0, its e image h rows on. The
    // throw is a millionth of a pixel over h so that the strip keeps h whole rows however
    // h * scale / scale rounds.
    let mut strip = inst.clone();
    strip.detector.nx = w;
    strip.detector.ny = 2 * h;
    let p = &mut strip.polarimetry;
    p.layout = instrument::Layout::Strips;
    p.strip_axis = "y".into();
    p.strip_starts_px = Some(vec![0.0]);
    p.strip_margin_px = 0.0;
    p.extraordinary_offset_sign = 1;
    p.throw_terms.clear();
    p.throw_arcsec = (h as f64 + 1e-6) * strip.detector.pixel_scale_arcsec;
    p.cameras = None;
    for f in &mut strip.filters {
        f.throw_terms = None;
    }
    let pair = FrameSet {
        filter: set.filter.clone(),
        angles_deg: set.angles_deg.clone(),
        hwp_sweep_deg: set.hwp_sweep_deg,
        data,
        files: set.files.clone(),
        nx: w,
        ny: 2 * h,
        warnings: set.warnings.clone(),
        conversion: set.conversion,
        chips: vec![],
    };
    let (mut r, zero) = reduce_set_plate(&pair, &strip, cfg)?;
    if let Some((rms, n)) = c.measured {
        r.warnings.push(Warning {
            file: set.files.first().and_then(|f| f.first()).cloned(),
            message: format!("camera transform measured from {n} star pairs of this frame, residual {rms:.3} px"),
        });
    }
    on_o_camera(&mut r.map, inst, c);
    Ok((r, zero))
}

/// The map of a two-camera pair ([`reduce_two_cameras`]) put on the o camera: only the bin rows
/// of the o camera kept, its pixels the o camera's own (from its first pixel: the detector
/// frame's when the o camera sits at the frame's origin, as MOPTOP's camera 1 does), and every
/// bin's error the larger of its scatter and photon errors (the resampled e pixels' noise is
/// correlated: see [`reduce_two_cameras`]).
fn on_o_camera(m: &mut StokesMap, inst: &Instrument, c: &crate::beams::CameraMap) {
    let b = m.geometry.bin_px;
    let nbx = m.geometry.nx;
    let nby = c.o_size.1.div_ceil(b).min(m.geometry.ny);
    let keep = nbx * nby;
    for v in [
        &mut m.q,
        &mut m.u,
        &mut m.sigma_q,
        &mut m.sigma_u,
        &mut m.cov_qu,
        &mut m.sigma_q_phot,
        &mut m.sigma_u_phot,
        &mut m.p,
        &mut m.chi,
        &mut m.intensity,
        &mut m.intensity_snr,
    ] {
        v.truncate(keep);
    }
    m.n_pixels.truncate(keep);
    m.valid.truncate(keep);
    for k in (0..keep).filter(|&k| m.valid[k]) {
        m.sigma_q[k] = m.sigma_q[k].max(m.sigma_q_phot[k]);
        m.sigma_u[k] = m.sigma_u[k].max(m.sigma_u_phot[k]);
    }
    // The map's detector is the o camera: its field coordinates are then centred on the o
    // camera, as the instrument's are for two cameras (`instrument::Instrument::field_coords`).
    m.geometry = BinGeometry {
        bin_px: b,
        origin_x: 0,
        origin_y: 0,
        nx: nbx,
        ny: nby,
        pixel_scale_arcsec: inst.detector.pixel_scale_arcsec,
        detector_nx: c.o_size.0,
        detector_ny: c.o_size.1,
    };
}

/// One HWP angle's input: the exposures taken at it (summed) and how many exposures the
/// values hold.
struct AngleInput<'a> {
    members: Vec<Member<'a>>,
    nexp: usize,
    /// The members' conversion to electrons (bias, gain, saturation, read-noise variance).
    det: (f64, f64, f64, f64),
}

/// Where one exposure's (or one sum's) rows come from.
enum Member<'a> {
    /// Pixels in memory (a [`FrameSet`]'s per-angle sums); not counted for bad pixels (the
    /// set counted its frames when it was made).
    View(PixelView<'a>),
    /// An open file, its index among the files (for the bad-pixel counts).
    File(&'a OpenFrame, usize),
}

/// One row group of a band of bin rows: the detector rows holding its o and e pixels, read as
/// runs of consecutive rows into a group buffer (row `rows[k]` at slot `k`, `k * nx` pixels
/// in), and its sky-pixel runs.
struct Group {
    /// `(first detector row, count, first slot)`.
    runs: Vec<(usize, usize, usize)>,
    n_rows: usize,
    /// `(x0, x1, o index of x0, e index of x0, o slot index, e slot index)`: detector indices
    /// and indices into the group buffer, o and e both contiguous.
    segs: Vec<Seg>,
}

type Seg = (usize, usize, usize, usize, usize, usize);

/// A band of bin rows, read and folded in [`Group`]s of a few detector rows each (so that a
/// group's rows of every angle stay in cache between reading and use).
struct Band {
    groups: Vec<Group>,
}

/// Bytes of raw rows a group should hold (all angles): well inside a core's L2 + its L3 share.
const GROUP_BYTES: usize = 3 << 19;

/// The bands of bin rows `0..geom.ny` (see [`Band`]) for `n` angles, and how many detector
/// pixels of each frame the reduction uses (o and e pixels of the binned sky pixels).
fn plan_bands(g: &BeamGeometry, geom: &BinGeometry, row_bytes: usize) -> (Vec<Band>, usize) {
    let bp = geom.bin_px;
    let xa = geom.origin_x.min(g.nx);
    let xb = (geom.origin_x + geom.nx * bp).min(g.nx);
    // o rows per group: o and e rows of every angle (`row_bytes` per detector row, all angles).
    let per_row = 2 * row_bytes.max(1);
    let group_rows = (GROUP_BYTES / per_row.max(1)).clamp(1, bp);
    let mut used_px = 0;
    let mut row_segs = Vec::new();
    let bands = (0..geom.ny)
        .map(|j| {
            let y0 = geom.origin_y + j * bp;
            let y1 = (y0 + bp).min(g.ny);
            let groups = (y0..y1)
                .step_by(group_rows)
                .map(|ya| {
                    let mut segs = Vec::new();
                    for y in ya..(ya + group_rows).min(y1) {
                        segments_of_row(g, y, xa, xb, &mut row_segs);
                        segs.extend_from_slice(&row_segs);
                    }
                    let mut rows: Vec<usize> = Vec::new();
                    for &(x0, x1, o0, e0) in &segs {
                        used_px += 2 * (x1 - x0);
                        for start in [o0, e0] {
                            rows.extend(start / g.nx..=(start + x1 - x0 - 1) / g.nx);
                        }
                    }
                    rows.sort_unstable();
                    rows.dedup();
                    let slot = |p: usize| {
                        let k = rows.binary_search(&(p / g.nx)).expect("row of the group");
                        k * g.nx + p % g.nx
                    };
                    let segs = segs.iter().map(|&(x0, x1, o0, e0)| (x0, x1, o0, e0, slot(o0), slot(e0))).collect();
                    let mut runs: Vec<(usize, usize, usize)> = Vec::new();
                    for (k, &r) in rows.iter().enumerate() {
                        match runs.last_mut() {
                            Some(run) if run.0 + run.1 == r => run.1 += 1,
                            _ => runs.push((r, 1, k)),
                        }
                    }
                    Group { runs, n_rows: rows.len(), segs }
                })
                .collect();
            Band { groups }
        })
        .collect();
    (bands, used_px)
}

/// The reduction's one pass, over bands of bin rows in parallel.
struct Pass {
    /// Clipped statistics of every bin, row-major.
    stats: Vec<Option<crate::bin::BinStats>>,
    /// Non-finite and saturated values of each file among the pixels the pass used.
    bad: Vec<BadCounts>,
    /// Sky pixels of each single-exposure file whose `f_O + f_E` was not positive.
    dark: Vec<usize>,
    /// Pixels of each frame the pass used (o and e pixels of the binned sky pixels).
    used_px: usize,
    /// A quarter-wave plate's zero angle (deg) the demodulation used ([`PlateWeights`]).
    qwp_zero_deg: Option<f64>,
}

/// The reduction proper: for each band of bin rows, group by group, read the detector rows
/// holding the group's o and e pixels from every angle's exposures (files are read by rows
/// here, so reading overlaps computing and a group is still in cache when it is used), then
/// fold each pixel's `F_i` into its running `Q`, `U`, their photon variances and the
/// intensity, in angle order (the same operations in the same order as a per-pixel
/// `solver.solve`), and finally clip the band's bins. `on_file` ticks `nfiles` times in all,
/// as the bands complete.
#[allow(clippy::too_many_arguments)]
fn reduce_bands(
    inputs: &[AngleInput],
    nfiles: usize,
    nx: usize,
    ny: usize,
    (filter, angles_deg, sweep_deg): (&str, &[f64], f64),
    inst: &Instrument,
    cfg: &ReduceConfig,
    on_file: &(dyn Fn() + Sync),
) -> Result<Pass, Error> {
    if cfg.bin_px == 0 {
        return Err(Error::Invalid("bin size must be at least 1 px".into()));
    }
    let weights = plate_weights(inst, filter, angles_deg, sweep_deg)?;
    let (cq, cu) = (&weights.cq[..], &weights.cu[..]);
    let g = BeamGeometry::new(inst);
    g.require_separable_sky().map_err(Error::Invalid)?;
    if (nx, ny) != (g.nx, g.ny) {
        return Err(Error::Invalid(format!(
            "frames are {} x {} px, instrument {} has {} x {}",
            nx, ny, inst.name, g.nx, g.ny
        )));
    }
    let geom = bin_geometry(inst, cfg.bin_px);
    let n = cq.len();
    // Bytes a group holds per detector row, so that its rows stay in cache between reading and
    // folding: 4 a pixel for a frame read by rows (f32 frames), 8 for rows summed over repeated
    // exposures or calibrated from raw chips (f64 buffers), plus for raw chips the scratch
    // row and the masters' rows (f32 bias and inverse flat).
    let calibrated = |m: &Member| matches!(m, Member::File(f, _) if matches!(f.rows, FrameRows::Calibrated(_)));
    let row_bytes: usize = inputs
        .iter()
        .map(|inp| if inp.members.len() > 1 || inp.members.iter().any(calibrated) { 8 * nx } else { 4 * nx })
        .sum::<usize>()
        .max(4 * nx * n)
        + if inputs.iter().any(|inp| inp.members.iter().any(calibrated)) { 16 * nx } else { 0 };
    let (bands, used_px) = plan_bands(&g, &geom, row_bytes);
    let min_pixels = cfg.min_pixels.unwrap_or((cfg.bin_px * cfg.bin_px / 4).max(3));
    let bp = geom.bin_px;
    let done = std::sync::atomic::AtomicUsize::new(0);
    let nb = bands.len().max(1);
    type BandOut = (Vec<Option<crate::bin::BinStats>>, Vec<BadCounts>, Vec<usize>);
    // Rayon calls `map_init`'s init once per piece of work it splits off, not once per thread:
    // scratch goes back to a pool when a piece is done, so the group buffers are allocated
    // (and page-faulted) about once per thread.
    let pool: std::sync::Mutex<Vec<Scratch>> = std::sync::Mutex::new(Vec::new());
    let per_band: Vec<Result<BandOut, Error>> = bands
        .par_iter()
        .map_init(
            || Pooled::take(&pool, || Scratch::new(geom.nx, n)),
            |sc, band| -> Result<BandOut, Error> {
                let sc = sc.get();
                let mut bad = vec![(0, 0); nfiles];
                let mut dark = vec![0; nfiles];
                for b in sc.bins.iter_mut() {
                    b.clear();
                }
                for group in &band.groups {
                    sc.read_group(inputs, group, g.nx, &mut bad)?;
                    let Scratch { k, raw, sum, bins, .. } = &mut *sc;
                    let rows: Vec<Rows> =
                        inputs.iter().enumerate().map(|(i, inp)| Rows::of(inp, &raw[i], &sum[i])).collect();
                    for &(x0, x1, o0, e0, os, es) in &group.segs {
                        let mut c0 = 0;
                        while c0 < x1 - x0 {
                            let len = CHUNK.min(x1 - x0 - c0);
                            k.reset(len);
                            for (i, inp) in inputs.iter().enumerate() {
                                let counted = k.fold_angle(Fold {
                                    rows: &rows[i],
                                    o: (o0 + c0, os + c0),
                                    e: (e0 + c0, es + c0),
                                    len,
                                    nexp: inp.nexp,
                                    w: (cq[i], cu[i]),
                                    det: inp.det,
                                });
                                if let (Some(c), [Member::File(_, fi)]) = (counted, &inp.members[..]) {
                                    bad[*fi].0 += c.nonfinite;
                                    bad[*fi].1 += c.saturated;
                                    dark[*fi] += c.dark;
                                }
                            }
                            let Kernel { q, u, vq, vu, isum, ok, .. } = &*k;
                            // Hand the chunk to its bins a bin's run at a time: whole slices
                            // when no pixel of the run is masked (the usual case).
                            let nf = n as f64;
                            let mut j = 0;
                            while j < len {
                                let bi = (x0 + c0 + j - geom.origin_x) / bp;
                                let end = (geom.origin_x + (bi + 1) * bp - (x0 + c0)).min(len);
                                let b = &mut bins[bi];
                                if ok[j..end].iter().all(|&o| o != 0) {
                                    b.q.extend_from_slice(&q[j..end]);
                                    b.u.extend_from_slice(&u[j..end]);
                                    b.i.extend(isum[j..end].iter().map(|s| s / nf));
                                    b.var_q.extend_from_slice(&vq[j..end]);
                                    b.var_u.extend_from_slice(&vu[j..end]);
                                } else {
                                    for t in (j..end).filter(|&t| ok[t] != 0) {
                                        b.push(PixelSample {
                                            qu: mueller::Qu::new(q[t], u[t], vq[t], vu[t], 0.0),
                                            i: isum[t] / nf,
                                        });
                                    }
                                }
                                j = end;
                            }
                            c0 += len;
                        }
                    }
                }
                // Along a row of bins the sky changes little: each bin's clipping starts its
                // median searches where the previous bin's ended.
                let mut hints = [None; 3];
                let stats =
                    sc.bins.iter_mut().map(|b| clipped_bin_taking(b, cfg.clip, min_pixels, &mut hints)).collect();
                let d = done.fetch_add(1, std::sync::atomic::Ordering::Relaxed) + 1;
                for _ in (d - 1) * nfiles / nb..d * nfiles / nb {
                    on_file();
                }
                Ok((stats, bad, dark))
            },
        )
        .collect();
    let mut stats = Vec::with_capacity(geom.nx * geom.ny);
    let mut bad = vec![(0, 0); nfiles];
    let mut dark = vec![0; nfiles];
    for r in per_band {
        let (s, b, k) = r?;
        stats.extend(s);
        for (t, x) in bad.iter_mut().zip(b) {
            t.0 += x.0;
            t.1 += x.1;
        }
        for (t, x) in dark.iter_mut().zip(k) {
            *t += x;
        }
    }
    Ok(Pass { stats, bad, dark, used_px, qwp_zero_deg: weights.qwp_zero_deg })
}

/// The fewest kept pixels whose scatter is taken as a bin's error as it is. The scatter of
/// `n` pixels is itself uncertain by `1 / sqrt(2 (n - 1))` of its value (10 % at 50), and
/// sigma clipping trims the tails of a small sample further: with a handful of pixels it fell
/// far below the noise (against a known sky, RMS pulls of 2.5 at 2 x 2 px bins and 2.8 at
/// 4 x 4 px, 1.0 from 8 x 8 px). Below it, a bin's error is the larger of its scatter and its
/// photon and read noise (`SIGQ_PHOT`); from it up the scatter is kept, as it also holds what
/// the noise model does not know (flat-field errors, structure in the sky).
pub const SCATTER_MIN_PIXELS: usize = 50;

/// The map from the bins' clipped statistics.
fn assemble_map(
    stats: Vec<Option<crate::bin::BinStats>>,
    inst: &Instrument,
    cfg: &ReduceConfig,
    filter: &str,
    angles_deg: &[f64],
    inputs: &[AngleInput],
) -> Result<StokesMap, Error> {
    let geom = bin_geometry(inst, cfg.bin_px);
    let rn2 = inputs.first().map_or(inst.detector.read_noise_e.powi(2), |a| a.det.3);
    let nexp_total: f64 = inputs.iter().map(|a| a.nexp as f64).sum();
    let mut map = StokesMap::empty(geom, &inst.name, filter, angles_deg.to_vec());
    // The map stays at the plate; what turns it into the sky frame is recorded with it.
    map.hwp_zero_angle_deg = inst.filter(filter).ok().map(|f| f.chi_offset_deg());
    map.product = Some(crate::provenance::Product::of_instrument(inst, filter, Some(mueller::Frame::Plate)));
    for (k, s) in stats.into_iter().enumerate() {
        let Some(s) = s else { continue };
        let (p, chi) = s.qu.p_chi();
        map.q[k] = s.qu.q;
        map.u[k] = s.qu.u;
        // Below SCATTER_MIN_PIXELS the scatter is no error estimate of its own: the photon
        // and read noise are its floor.
        let small = s.n_kept < SCATTER_MIN_PIXELS;
        map.sigma_q[k] = if small { s.qu.sigma_q().max(s.sigma_q_phot) } else { s.qu.sigma_q() };
        map.sigma_u[k] = if small { s.qu.sigma_u().max(s.sigma_u_phot) } else { s.qu.sigma_u() };
        map.cov_qu[k] = s.qu.cov_qu;
        map.sigma_q_phot[k] = s.sigma_q_phot;
        map.sigma_u_phot[k] = s.sigma_u_phot;
        map.p[k] = p;
        map.chi[k] = chi;
        map.n_pixels[k] = s.n_kept as u32;
        map.intensity[k] = s.intensity;
        // Combined image: every exposure summed (photon + read noise per exposure).
        let tot = s.intensity * nexp_total;
        map.intensity_snr[k] = tot / (tot + 2.0 * nexp_total * rn2).sqrt();
        map.valid[k] = true;
    }
    if map.n_valid() == 0 {
        // Bins smaller than the minimum count can never be valid: say so, not "masked".
        let min = cfg.min_pixels.unwrap_or((cfg.bin_px * cfg.bin_px / 4).max(3));
        if cfg.bin_px * cfg.bin_px < min {
            return Err(Error::Invalid(format!(
                "bins of {b} x {b} px hold {} pixels, fewer than the {min} a bin needs to be valid (with sigma clipping): use --bin 2 or more",
                cfg.bin_px * cfg.bin_px,
                b = cfg.bin_px
            )));
        }
        return Err(Error::NoValidBins);
    }
    Ok(map)
}

/// Pixels of a row processed together (a FORS row): the per-pixel buffers stay in L1/L2.
const CHUNK: usize = 2048;

/// A value borrowed from a pool and given back when dropped.
struct Pooled<'a, T> {
    value: Option<T>,
    pool: &'a std::sync::Mutex<Vec<T>>,
}

impl<'a, T> Pooled<'a, T> {
    fn take(pool: &'a std::sync::Mutex<Vec<T>>, make: impl FnOnce() -> T) -> Self {
        let value = pool.lock().ok().and_then(|mut p| p.pop()).unwrap_or_else(make);
        Self { value: Some(value), pool }
    }

    fn get(&mut self) -> &mut T {
        self.value.as_mut().expect("present until dropped")
    }
}

impl<T> Drop for Pooled<'_, T> {
    fn drop(&mut self) {
        if let (Some(v), Ok(mut p)) = (self.value.take(), self.pool.lock()) {
            p.push(v);
        }
    }
}

/// One angle's pixels for the current group, as the kernel reads them.
enum Rows<'a> {
    /// The whole image in memory, by detector index.
    View(PixelView<'a>),
    /// The group's rows as stored in the file (big-endian), by group-buffer index.
    Raw(&'a [u8], RawKind),
    /// The group's rows summed over repeated exposures (or one exposure's calibrated rows), by
    /// group-buffer index.
    Sum(&'a [f64]),
}

impl<'a> Rows<'a> {
    fn of(inp: &'a AngleInput<'a>, raw: &'a [u8], sum: &'a [f64]) -> Self {
        match &inp.members[..] {
            [Member::View(v)] => Rows::View(*v),
            [Member::File(f, _)] => match &f.rows {
                FrameRows::File(r) => Rows::Raw(raw, r.kind()),
                FrameRows::Memory(p) => Rows::View(p.view()),
                // Calibrated into the group buffer by `read_group`.
                FrameRows::Calibrated(_) => Rows::Sum(sum),
            },
            _ => Rows::Sum(sum),
        }
    }

    /// `out.len()` values from detector index `det` (group-buffer index `slot`) as f64 ADU;
    /// inlined into the kernel, so decoding gets its vectors.
    #[inline(always)]
    fn load(&self, det: usize, slot: usize, out: &mut [f64]) {
        match self {
            Rows::View(v) => v.load(det, out),
            Rows::Raw(b, kind) => kind.decode_at(b, slot, out),
            Rows::Sum(s) => out.copy_from_slice(&s[slot..slot + out.len()]),
        }
    }
}

/// The masters' rows of a group (read by [`Scratch::group_masters`], which sizes both buffers
/// for the whole group) from detector row `r0`, which sits at `at` in the group buffer's layout.
fn master_rows<'a>(bias: &'a [f32], flat: &'a [f32], r0: usize, at: usize) -> MasterRows<'a> {
    MasterRows { row0: r0, bias: &bias[at..], flat: &flat[at..] }
}

/// Per-thread buffers of [`reduce_bands`], reused across bands: each angle's group of rows
/// (as stored, or summed over repeated exposures), the kernel, and the samples of each bin of
/// the band.
struct Scratch {
    raw: Vec<Vec<u8>>,
    sum: Vec<Vec<f64>>,
    tmp: Vec<f64>,
    bytes: Vec<u8>,
    /// The group's rows of the masters of its raw exposures (bias, inverse flat), in the
    /// group buffer's layout, and which masters they are (their address; 0 for none yet).
    mbias: Vec<f32>,
    mflat: Vec<f32>,
    mkey: usize,
    /// Scratch of [`Calibrated::load_rows_summed`], the o and e ranges of a run and each
    /// exposure's bad-value counts.
    summing: SumScratch,
    ranges: Vec<(usize, usize)>,
    counts: Vec<BadCounts>,
    k: Kernel,
    bins: Vec<BinSamples>,
}

impl Scratch {
    fn new(nbins: usize, n_angles: usize) -> Self {
        Self {
            raw: vec![Vec::new(); n_angles],
            sum: vec![Vec::new(); n_angles],
            tmp: Vec::new(),
            bytes: Vec::new(),
            mbias: Vec::new(),
            mflat: Vec::new(),
            mkey: 0,
            summing: SumScratch::default(),
            ranges: Vec::new(),
            counts: Vec::new(),
            k: Kernel::new(),
            bins: vec![BinSamples::default(); nbins],
        }
    }

    /// The masters' rows of `group` for the raw exposure `c`, read once per group: the
    /// exposures of a run share their masters, so the first raw exposure of the group reads
    /// them and the others find them (see [`Calibrated::load_rows_with`]).
    fn group_masters(&mut self, c: &Calibrated, group: &Group, nx: usize) -> Result<(), Error> {
        let m = c.masters();
        let key = std::sync::Arc::as_ptr(m) as usize;
        if self.mkey == key {
            return Ok(());
        }
        let n = group.n_rows * nx;
        self.mbias.resize(n, 0.0);
        self.mflat.resize(n, 0.0);
        for &(r0, nr, slot0) in &group.runs {
            let span = slot0 * nx..(slot0 + nr) * nx;
            m.rows(r0, &mut self.mbias[span.clone()], &mut self.mflat[span], &mut self.bytes)?;
        }
        self.mkey = key;
        Ok(())
    }

    /// Angle `i`'s repeated raw exposures `exps` (its `members`, all summable) calibrated and
    /// summed into its group buffer ([`Calibrated::load_rows_summed`]), each exposure's bad
    /// values counted over the group's o and e pixels into `bad`.
    #[allow(clippy::too_many_arguments)]
    fn read_summed(
        &mut self,
        i: usize,
        members: &[Member],
        exps: &[&Calibrated],
        group: &Group,
        nx: usize,
        sat: f64,
        bad: &mut [BadCounts],
    ) -> Result<(), Error> {
        self.group_masters(exps[0], group, nx)?;
        self.sum[i].resize(group.n_rows * nx, 0.0);
        self.counts.clear();
        self.counts.resize(exps.len(), (0, 0));
        for &(r0, nr, slot0) in &group.runs {
            let (a, b) = (slot0 * nx, (slot0 + nr) * nx);
            // The group's o and e ranges within this run, as indices into it.
            self.ranges.clear();
            for &(x0, x1, _, _, os, es) in &group.segs {
                for start in [os, es] {
                    let (lo, hi) = (start.max(a), (start + x1 - x0).min(b));
                    if lo < hi {
                        self.ranges.push((lo - a, hi - a));
                    }
                }
            }
            let m = master_rows(&self.mbias, &self.mflat, r0, a);
            let out = &mut self.sum[i][a..b];
            Calibrated::load_rows_summed(exps, r0, out, &mut self.summing, m, &self.ranges, sat, &mut self.counts)?;
        }
        for (m, c) in members.iter().zip(&self.counts) {
            if let Member::File(_, fi) = m {
                bad[*fi].0 += c.0;
                bad[*fi].1 += c.1;
            }
        }
        Ok(())
    }

    avx2_dispatch! {
        /// Read a group's rows of every angle that comes from files: a single exposure's rows as
        /// stored (decoded and counted by the kernel); repeated exposures decoded and summed in
        /// order, each exposure's bad values counted on the group's o and e pixels. The counting
        /// and summing loops in 4-wide AVX2 where the CPU has it (the same IEEE additions in the
        /// same order, so the same bits): they were 9 % of a raw FORS2 reduction's profile.
        fn read_group / read_group_avx2 / read_group_avx512 => read_group_impl(
            &mut self,
            inputs: &[AngleInput],
            group: &Group,
            nx: usize,
            bad: &mut [BadCounts],
        ) -> Result<(), Error> {
            self.mkey = 0;
            for (i, inp) in inputs.iter().enumerate() {
                let sat = inp.det.2;
                match &inp.members[..] {
                    [Member::View(_)] => {}
                    [Member::File(f, _)] => match &f.rows {
                        FrameRows::File(r) => {
                            let b = r.kind().bytes();
                            let raw = &mut self.raw[i];
                            raw.resize(group.n_rows * nx * b, 0);
                            for &(r0, nr, slot0) in &group.runs {
                                f.read_raw(r, r0, &mut raw[slot0 * nx * b..(slot0 + nr) * nx * b])?;
                            }
                        }
                        // Raw chips: read and calibrated here, into the group buffer (the kernel
                        // counts the bad values of a single exposure).
                        FrameRows::Calibrated(c) => {
                            self.group_masters(c, group, nx)?;
                            let out = &mut self.sum[i];
                            out.resize(group.n_rows * nx, 0.0);
                            for &(r0, nr, slot0) in &group.runs {
                                let m = master_rows(&self.mbias, &self.mflat, r0, slot0 * nx);
                                c.load_rows_with(r0, &mut out[slot0 * nx..(slot0 + nr) * nx], &mut self.bytes, m)?;
                            }
                        }
                        FrameRows::Memory(_) => {}
                    },
                    // Repeated raw exposures: calibrated and summed row by row in one pass.
                    members if let Some(exps) = summed_raw(members) => {
                        self.read_summed(i, members, &exps, group, nx, sat, bad)?;
                    }
                    members => {
                        let npx = group.n_rows * nx;
                        self.sum[i].resize(npx, 0.0);
                        self.tmp.resize(npx, 0.0);
                        for (m_i, m) in members.iter().enumerate() {
                            if let Member::File(OpenFrame { rows: FrameRows::Calibrated(c), .. }, _) = m {
                                self.group_masters(c, group, nx)?;
                            }
                            let dst = if m_i == 0 { &mut self.sum[i][..] } else { &mut self.tmp[..] };
                            for &(r0, nr, slot0) in &group.runs {
                                let out = &mut dst[slot0 * nx..(slot0 + nr) * nx];
                                match m {
                                    Member::View(v) => v.load(r0 * nx, out),
                                    Member::File(OpenFrame { rows: FrameRows::Calibrated(c), .. }, _) => {
                                        let mr = master_rows(&self.mbias, &self.mflat, r0, slot0 * nx);
                                        c.load_rows_with(r0, out, &mut self.bytes, mr)?
                                    }
                                    Member::File(f, _) => f.load_rows(r0, out, &mut self.bytes)?,
                                }
                            }
                            if let Member::File(_, fi) = m {
                                for &(x0, x1, _, _, os, es) in &group.segs {
                                    for start in [os, es] {
                                        let (a, s) = PixelView::F64(&dst[start..start + x1 - x0]).count_bad(sat);
                                        bad[*fi].0 += a;
                                        bad[*fi].1 += s;
                                    }
                                }
                            }
                            if m_i > 0 {
                                for (a, s) in self.sum[i].iter_mut().zip(self.tmp.iter()) {
                                    *a += s;
                                }
                            }
                        }
                    }
                }
            }
            Ok(())
        }
    }
}

/// The exposures of `members` when all are raw exposures that can be calibrated and summed in
/// one pass ([`Calibrated::load_rows_summed`]); `None` otherwise.
fn summed_raw<'a>(members: &[Member<'a>]) -> Option<Vec<&'a Calibrated>> {
    let exps: Vec<&Calibrated> = members
        .iter()
        .map(|m| match m {
            Member::File(OpenFrame { rows: FrameRows::Calibrated(c), .. }, _) => Some(c),
            _ => None,
        })
        .collect::<Option<_>>()?;
    let first = exps.first()?;
    exps.iter().all(|e| first.summable_with(e)).then_some(exps)
}

/// One HWP angle's part of a chunk, as [`Kernel::fold_angle`] takes it: `len` pixels whose o
/// and e values start at detector / group-buffer indices `o` and `e` of `rows`, from `nexp`
/// exposures, with the solver's weights `w` for this angle and the detector's `det` (bias ADU,
/// gain e-/ADU, saturation ADU, read-noise variance e-^2).
#[derive(Clone, Copy)]
struct Fold<'a> {
    rows: &'a Rows<'a>,
    o: (usize, usize),
    e: (usize, usize),
    len: usize,
    nexp: usize,
    w: (f64, f64),
    det: (f64, f64, f64, f64),
}

/// Bad values of a single exposure's chunk: non-finite and saturated values among its `2 len`
/// o and e values, and pixels with finite values but `f_O + f_E <= 0` (no flux).
struct FoldCounts {
    nonfinite: usize,
    saturated: usize,
    dark: usize,
}

/// Running per-pixel sums over the HWP angles of one chunk of a row (structure of arrays, so
/// the loops vectorize).
struct Kernel {
    ro: Vec<f64>,
    re: Vec<f64>,
    q: Vec<f64>,
    u: Vec<f64>,
    vq: Vec<f64>,
    vu: Vec<f64>,
    isum: Vec<f64>,
    /// 1 while the pixel is usable, 0 once masked (u64 lanes, as wide as the f64 ones, so the
    /// mask needs no packing in the vector loop).
    ok: Vec<u64>,
}

impl Kernel {
    fn new() -> Self {
        let z = || vec![0.0; CHUNK];
        Self { ro: z(), re: z(), q: z(), u: z(), vq: z(), vu: z(), isum: z(), ok: vec![1; CHUNK] }
    }

    fn reset(&mut self, len: usize) {
        for v in [&mut self.q, &mut self.u, &mut self.vq, &mut self.vu, &mut self.isum] {
            v[..len].fill(0.0);
        }
        self.ok[..len].fill(1);
    }

    avx2_dispatch! {
        /// Fold one HWP angle into the running sums of the chunk's pixels (see [`Fold`]): the
        /// per-pixel steps of the module docs (mask, electrons, the one `F_i`, its photon + read
        /// noise variance, `Q`, `U` by the solver's weights), in the order a per-pixel
        /// `StokesSolver::solve` uses, so sums are the same to the bit. For a single exposure, also
        /// returns the chunk's counts of bad values ([`FoldCounts`]).
        ///
        /// Decoding and one pass bound by its two divisions: 4-wide AVX2 vectors where the CPU
        /// has them (same IEEE operations, so the same bits; no FMA is enabled).
        fn fold_angle / fold_avx2 / fold_avx512 => fold_impl(&mut self, a: Fold) -> Option<FoldCounts> {
            let len = a.len;
            // Rows already in f64 (summed or calibrated) are read where they are; others are
            // decoded into the kernel's buffers first.
            let (ro, re): (&[f64], &[f64]) = match a.rows {
                Rows::Sum(s) => (&s[a.o.1..a.o.1 + len], &s[a.e.1..a.e.1 + len]),
                rows => {
                    rows.load(a.o.0, a.o.1, &mut self.ro[..len]);
                    rows.load(a.e.0, a.e.1, &mut self.re[..len]);
                    (&self.ro[..len], &self.re[..len])
                }
            };
            let Self { q, u, vq, vu, isum, ok, .. } = self;
            let acc = Acc {
                q: &mut q[..len],
                u: &mut u[..len],
                vq: &mut vq[..len],
                vu: &mut vu[..len],
                isum: &mut isum[..len],
                ok: &mut ok[..len],
            };
            // Separate loops for one and several exposures: x / 1 is x exactly, so the single
            // exposure's loop skips a division.
            if a.nexp == 1 {
                Some(fold_loop::<true>(ro, re, acc, 1.0, a.w, a.det))
            } else {
                fold_loop::<false>(ro, re, acc, a.nexp as f64, a.w, a.det);
                None
            }
        }
    }
}

/// A chunk's running sums, as [`fold_loop`] updates them (the [`Kernel`]'s, `len` long).
struct Acc<'a> {
    q: &'a mut [f64],
    u: &'a mut [f64],
    vq: &'a mut [f64],
    vu: &'a mut [f64],
    isum: &'a mut [f64],
    ok: &'a mut [u64],
}

/// The per-pixel loop of [`Kernel::fold_angle`]: one angle's o and e values (`ro`, `re`, the
/// chunk's length) folded into the running sums `acc`.
#[inline(always)]
fn fold_loop<const ONE: bool>(
    ro: &[f64],
    re: &[f64],
    acc: Acc,
    ne: f64,
    (cqi, cui): (f64, f64),
    (bias, gain, sat, rn2): (f64, f64, f64, f64),
) -> FoldCounts {
    let len = ro.len();
    let (bias_n, sat_n, rn2_n) = (bias * ne, sat * ne, ne * rn2);
    let (cq2, cu2) = (cqi * cqi, cui * cui);
    let re = &re[..len];
    let Acc { q, u, vq, vu, isum, ok } = acc;
    let (q, u, vq, vu, isum, ok) =
        (&mut q[..len], &mut u[..len], &mut vq[..len], &mut vu[..len], &mut isum[..len], &mut ok[..len]);
    let (mut n_nonfinite, mut n_sat, mut n_dark) = (0usize, 0usize, 0usize);
    for k in 0..len {
        let (r_o, r_e) = (ro[k], re[k]);
        let (fin_o, fin_e) = (r_o.is_finite(), r_e.is_finite());
        let (sat_o, sat_e) = (r_o >= sat_n, r_e >= sat_n);
        n_nonfinite += !fin_o as usize + !fin_e as usize;
        n_sat += sat_o as usize + sat_e as usize;
        let f_o = (r_o - bias_n) * gain;
        let f_e = (r_e - bias_n) * gain;
        let tot = f_o + f_e;
        n_dark += (fin_o & fin_e & !(tot > 0.0)) as usize;
        let f = normalized_difference(f_o, f_e);
        // Photon (e-) plus read-noise variance of each beam, propagated to F.
        let vf = variance_normalized_difference_fast(f_o, f_e, f_o.max(0.0) + rn2_n, f_e.max(0.0) + rn2_n);
        ok[k] &= (fin_o & fin_e & !sat_o & !sat_e & (tot > 0.0) & fast_variance_in_range(vf)) as u64;
        q[k] += cqi * f;
        u[k] += cui * f;
        isum[k] += if ONE { tot } else { tot / ne };
        vq[k] += cq2 * vf;
        vu[k] += cu2 * vf;
    }
    FoldCounts { nonfinite: n_nonfinite, saturated: n_sat, dark: n_dark }
}

/// The runs of sky pixels of row `y` within columns `[xa, xb)` into `segs`: `(x0, x1, o index
/// of x0, e index of x0)`, o and e both contiguous.
fn segments_of_row(g: &BeamGeometry, y: usize, xa: usize, xb: usize, segs: &mut Vec<(usize, usize, usize, usize)>) {
    segs.clear();
    if xa >= xb {
        return;
    }
    if g.along_y && g.shift_constant_across() {
        // Strips stacked along y with a throw that varies along y only (or not at all): a row
        // is all sky or all masked, with one e shift.
        if let Some((o, e)) = g.beams_of_sky(xa, y) {
            segs.push((xa, xb, o, e));
        }
        return;
    }
    let mut cur: Option<(usize, usize, usize, usize)> = None;
    for x in xa..xb {
        match (g.beams_of_sky(x, y), cur.as_mut()) {
            (Some((o, e)), Some(c)) if c.2 + (x - c.0) == o && c.3 + (x - c.0) == e => c.1 = x + 1,
            (Some((o, e)), _) => {
                if let Some(c) = cur.take() {
                    segs.push(c);
                }
                cur = Some((x, x + 1, o, e));
            }
            (None, _) => {
                if let Some(c) = cur.take() {
                    segs.push(c);
                }
            }
        }
    }
    if let Some(c) = cur {
        segs.push(c);
    }
}

/// Read, check and reduce frame files in one call; `on_read` ticks once per file in all, as
/// the reading (which is spread over the reduction) goes along.
///
/// Same result as [`read_frames`] + [`FrameSet::from_frames`] + [`reduce_set`], but the frames
/// are never held whole: each is opened and its header checked first, then its pixels are read
/// by bands of rows as the reduction needs them (straight from the file for uncompressed
/// images; through CFITSIO, whole, for compressed or scaled ones). Bad pixels are counted over
/// the rows the beams use.
pub fn reduce_files(
    paths: &[PathBuf],
    inst: &Instrument,
    cfg: &ReduceConfig,
    on_read: &(dyn Fn() + Sync),
) -> Result<Reduced, Error> {
    reduce_files_with(paths, inst, cfg, &ReadOptions::default(), on_read)
}

/// The masked strips of every plain frame read for the level they should not have
/// ([`crate::pedestal`]): an error for a frame that still carries its bias, the warnings of
/// the doubtful ones. Raw chip exposures have their bias from overscan or a master.
fn pedestal_notes(frames: &[OpenFrame], inst: &Instrument, conv: &Conversion) -> Result<Vec<Warning>, Error> {
    let g = BeamGeometry::new(inst);
    let rows = crate::pedestal::sample_rows(&g);
    if rows.is_empty() {
        return Ok(Vec::new());
    }
    let judged: Vec<Result<Option<Warning>, Error>> = frames
        .par_iter()
        .filter(|f| f.is_plain() && f.nx == g.nx)
        .map(|f| {
            let (mut buf, mut bytes) = (vec![0.0; rows.len() * f.nx], Vec::new());
            for (k, &y) in rows.iter().enumerate() {
                f.load_rows(y, &mut buf[k * f.nx..(k + 1) * f.nx], &mut bytes)?;
            }
            let r: Vec<(usize, &[f64])> =
                rows.iter().enumerate().map(|(k, &y)| (y, &buf[k * f.nx..(k + 1) * f.nx])).collect();
            match crate::pedestal::levels(&g, &r, conv.bias, conv.saturation) {
                Some(l) => crate::pedestal::judge(&f.path, &l, conv.bias),
                None => Ok(None),
            }
        })
        .collect();
    judged.into_iter().filter_map(|r| r.transpose()).collect()
}

/// [`reduce_files`] with calibration frames and HWP angles ([`ReadOptions`]). Raw frames
/// (chips, overscan, bias, flat) are calibrated in the same pass, row by row as the bands read
/// them (see [`crate::calib`]): no frame is held whole, raw or calibrated. A quarter-wave
/// plate's frames are refused ([`reduce_circular_files_with`]; [`reduce_for_plate`] takes
/// either).
pub fn reduce_files_with(
    paths: &[PathBuf],
    inst: &Instrument,
    cfg: &ReduceConfig,
    opts: &ReadOptions,
    on_read: &(dyn Fn() + Sync),
) -> Result<Reduced, Error> {
    require_half_wave(inst)?;
    let mut r = reduce_files_plate(paths, inst, cfg, opts, on_read)?.0;
    // On a rotator: the set's one position angle on the sky, for the corrected map's turn.
    let files: Vec<&std::path::Path> = r.exposures.iter().map(|(p, _)| p.as_path()).collect();
    r.map.sky_pa_deg = crate::sky_angle::of_set(&files, inst)?;
    Ok(r)
}

/// [`reduce_files_with`] for frames taken through a quarter-wave plate: the binned `V/I` map
/// (the same reading, masking, bins, clipping and errors; the circular demodulation's weights,
/// `stokes::circular`, in place of `eq:Q`'s). A half-wave plate's frames are refused.
pub fn reduce_circular_files_with(
    paths: &[PathBuf],
    inst: &Instrument,
    cfg: &ReduceConfig,
    opts: &ReadOptions,
    on_read: &(dyn Fn() + Sync),
) -> Result<CircularReduced, Error> {
    require_quarter_wave(inst)?;
    let (r, zero) = reduce_files_plate(paths, inst, cfg, opts, on_read)?;
    Ok(CircularReduced::of(r, zero))
}

/// What a frame set reduces to, by the instrument's plate ([`reduce_for_plate`]).
#[derive(Debug, Clone)]
pub enum PlateReduced {
    /// A half-wave plate: the Stokes map of `Q/I`, `U/I`.
    Linear(Box<Reduced>),
    /// A quarter-wave plate: the map of `V/I`.
    Circular(Box<CircularReduced>),
}

/// The reduction `instpol reduce` and the Python package's `reduce` run: the instrument's plate
/// decides the map ([`reduce_files_with`] for a half-wave plate, [`reduce_circular_files_with`]
/// for a quarter-wave plate), so no face holds that rule.
pub fn reduce_for_plate(
    paths: &[PathBuf],
    inst: &Instrument,
    cfg: &ReduceConfig,
    opts: &ReadOptions,
    on_read: &(dyn Fn() + Sync),
) -> Result<PlateReduced, Error> {
    match inst.polarimetry.plate {
        instrument::Plate::HalfWave => {
            reduce_files_with(paths, inst, cfg, opts, on_read).map(|r| PlateReduced::Linear(Box::new(r)))
        }
        instrument::Plate::QuarterWave => {
            reduce_circular_files_with(paths, inst, cfg, opts, on_read).map(|r| PlateReduced::Circular(Box::new(r)))
        }
    }
}

/// A quarter-wave plate's reduced map with the notes gathered on the way.
#[derive(Debug, Clone)]
pub struct CircularReduced {
    pub map: CircularMap,
    pub warnings: Vec<Warning>,
    /// Each exposure's file and the plate angle (deg) it was reduced at, angle by angle.
    pub exposures: Vec<(PathBuf, f64)>,
}

impl CircularReduced {
    /// The circular map from the reduction's pass with a quarter-wave plate's weights
    /// ([`plate_weights`]): the carrier's `Q/I` sums are `V/I`, their scatter and photon errors
    /// `V/I`'s, and the bins, coverage, intensity and WCS are the map's as they are.
    fn of(r: Reduced, qwp_zero_deg: Option<f64>) -> Self {
        let m = r.map;
        let map = CircularMap {
            geometry: m.geometry,
            instrument: m.instrument,
            filter: m.filter,
            plate_angles_deg: m.hwp_angles_deg,
            qwp_zero_angle_deg: qwp_zero_deg.unwrap_or(0.0),
            v: m.q,
            sigma_v: m.sigma_q,
            sigma_v_phot: m.sigma_q_phot,
            n_pixels: m.n_pixels,
            intensity: m.intensity,
            intensity_snr: m.intensity_snr,
            valid: m.valid,
            celestial_wcs: m.celestial_wcs,
            product: m.product,
        };
        Self { map, warnings: r.warnings, exposures: r.exposures }
    }
}

/// The reduction of frame files with the weights of the instrument's plate
/// ([`plate_weights`]), and the quarter-wave plate's zero angle used (`None` for a half-wave
/// plate).
fn reduce_files_plate(
    paths: &[PathBuf],
    inst: &Instrument,
    cfg: &ReduceConfig,
    opts: &ReadOptions,
    on_read: &(dyn Fn() + Sync),
) -> Result<(Reduced, Option<f64>), Error> {
    cfg.check()?;
    // Two cameras: the frames in memory, for the e camera's resampling (reduce_two_cameras).
    if inst.polarimetry.layout == instrument::Layout::TwoCameras {
        let frames = read_frames_with(paths, inst, opts, on_read)?;
        let set = FrameSet::from_frames(frames, inst, cfg.require_complete_set)?;
        return reduce_set_plate(&set, inst, cfg);
    }
    // Opened and grouped as the catalog opens them; the bands below read the rows.
    let set = DiskFrames::open(paths, inst, opts, cfg.require_complete_set)?;
    let inst = &*inst.for_filter(&set.filter);
    let (frames, conversion) = (&set.frames, set.conversion);
    let meta: Vec<_> = frames.iter().map(open_meta).collect();
    let inputs: Vec<AngleInput> = set
        .members
        .iter()
        .map(|m| AngleInput {
            members: m.iter().map(|&k| Member::File(&frames[k], k)).collect(),
            nexp: m.len(),
            det: Conversion {
                read_noise_e2: m.iter().map(|&k| frames[k].conversion.read_noise_e2).fold(0.0, f64::max),
                ..conversion
            }
            .det(),
        })
        .collect();
    let pedestals = pedestal_notes(frames, inst, &conversion)?;
    let pass = reduce_bands(
        &inputs,
        frames.len(),
        set.nx,
        set.ny,
        (&set.filter, &set.angles, set.hwp_sweep_deg),
        inst,
        cfg,
        on_read,
    )?;
    let geom = bin_geometry(inst, cfg.bin_px);
    let counted = Counted::Used(inst, &geom);
    let chips = disk_chip_counts(frames.iter().zip(pass.bad.iter().copied()), conversion.saturation, counted)?;
    let whole = bad_pixel_notes(&meta, &pass.bad, pass.used_px, &conversion)?;
    let mut warnings = chip_bad_notes(whole, &chips, &conversion);
    warnings.extend(pedestals);
    warnings.extend(set.warnings.iter().cloned());
    let mut map = match assemble_map(pass.stats, inst, cfg, &set.filter, &set.angles, &inputs) {
        // Say why when it is that some frames hold no flux above the bias anywhere.
        Err(Error::NoValidBins) => {
            let dark: Vec<String> = meta
                .iter()
                .zip(&pass.dark)
                .filter(|(_, &d)| pass.used_px > 0 && 2 * d == pass.used_px)
                .map(|(m, _)| m.0.display().to_string())
                .collect();
            if dark.is_empty() {
                return Err(Error::NoValidBins);
            }
            let more = if dark.len() > 3 { format!(" and {} more", dark.len() - 3) } else { String::new() };
            return Err(Error::NoFlux {
                files: format!("{}{more}", dark[..dark.len().min(3)].join(", ")),
                bias: inst.detector.bias_adu,
                gain: inst.detector.gain_e_per_adu,
            });
        }
        r => r?,
    };
    // The first frame's celestial WCS, carried through the binning, when its pixels are the
    // map's detector pixels (a plain frame, same size; not chips trimmed and assembled).
    match crate::wcs::celestial_wcs_of(&frames[0].path, frames[0].nx, frames[0].ny) {
        Ok(Some(w)) => {
            let g = &map.geometry;
            map.celestial_wcs = Some(w.binned(g.bin_px, [g.origin_x, g.origin_y]))
        }
        Ok(None) => {}
        Err(why) => warnings.push(crate::Warning {
            file: Some(frames[0].path.clone()),
            message: format!("celestial WCS not carried to the map: {why}"),
        }),
    }
    Ok((Reduced { map, warnings, exposures: exposures_of(&set.files, &set.angles) }, pass.qwp_zero_deg))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A clipping threshold that is not a positive number of sigma is refused by the check
    /// every reduction asks, naming it; the default passes.
    #[test]
    fn a_clipping_threshold_is_a_positive_number() {
        assert!(ReduceConfig::default().check().is_ok());
        for k in [f64::NAN, f64::INFINITY, 0.0, -3.0] {
            let cfg =
                ReduceConfig { clip: ClipConfig { nsigma: k, ..ClipConfig::default() }, ..ReduceConfig::default() };
            let e = cfg.check().unwrap_err().to_string();
            assert!(e.contains("nsigma"), "{k}: {e}");
        }
    }

    /// The exposures of one reduction share the plate's motion: equal sweeps (to 0.05 deg)
    /// are the set's, two different ones are refused naming both files; the set's solver with a
    /// sweep of 22.5 deg weighs the F_i by 1/sinc (its weights 1/0.9003 of the fixed plate's).
    #[test]
    fn one_sweep_per_set_and_its_solver() {
        let (a, b) = (Path::new("a.fits"), Path::new("b.fits"));
        assert_eq!(common_sweep([(a, 22.5), (b, 22.52)].into_iter()).unwrap(), 22.5);
        assert_eq!(common_sweep(std::iter::empty()).unwrap(), 0.0);
        let e = common_sweep([(a, 22.5), (b, 0.0)].into_iter()).unwrap_err().to_string();
        assert!(e.contains("a.fits") && e.contains("b.fits") && e.contains("swept"), "{e}");
        let angles = [0.0, 22.5, 45.0, 67.5];
        let (fixed, swept) = (solver_of(&angles, 0.0).unwrap(), solver_of(&angles, 22.5).unwrap());
        let sinc = (2.0 * 22.5f64.to_radians()).sin() / (2.0 * 22.5f64.to_radians());
        for (w0, w1) in fixed.weights().0.iter().zip(swept.weights().0) {
            assert!((w1 * sinc - w0).abs() < 1e-15, "{w0} {w1}");
        }
        assert!(solver_of(&angles, 90.0).unwrap_err().to_string().contains("nothing modulated"));
    }

    fn tiny(axis: &str) -> Instrument {
        let text = include_str!("../../../instruments/fors1.toml")
            .replace("nx = 2048", "nx = 96")
            .replace("ny = 2048", "ny = 64")
            .replace("throw_arcsec = 22.0", "throw_arcsec = 2.0")
            .replace("strip_count = 9", "strip_count = 3")
            .replace("first_strip_y_px = 34", "first_strip_y_px = 2")
            .replace("bias_adu = 0.0", "bias_adu = 200.0")
            .replace("strip_axis = \"y\"", &format!("strip_axis = \"{axis}\""));
        Instrument::from_toml_str(&text, Path::new("tiny.toml")).unwrap()
    }

    /// Noiseless uniform sky (`eq:F`: `F_i = Q cos 4theta_i + U sin 4theta_i`, o and e fluxes
    /// `I/2 (1 +- F_i)`) for strips along y and along x: every valid bin returns the sky's Q, U
    /// and I, so the o/e pixel runs the row kernel uses are the beams' (a wrong e pixel would
    /// see the dark bias and give F = 1).
    #[test]
    fn uniform_sky_is_recovered_for_both_strip_axes() {
        let (q0, u0, i0) = (0.013, -0.021, 4000.0);
        for axis in ["y", "x"] {
            let inst = tiny(axis);
            let g = BeamGeometry::new(&inst);
            let det = &inst.detector;
            let angles: Vec<f64> = (0..4).map(|i| i as f64 * 22.5).collect();
            let data: Vec<Vec<f64>> = angles
                .iter()
                .map(|a| {
                    let t = 4.0 * a.to_radians();
                    let f = q0 * t.cos() + u0 * t.sin();
                    let mut d = vec![det.bias_adu; g.nx * g.ny];
                    for (x, y) in g.sky_pixels() {
                        let (o, e) = g.beams_of_sky(x, y).unwrap();
                        d[o] = det.bias_adu + 0.5 * i0 * (1.0 + f) / det.gain_e_per_adu;
                        d[e] = det.bias_adu + 0.5 * i0 * (1.0 - f) / det.gain_e_per_adu;
                    }
                    d
                })
                .collect();
            let files = (0..4).map(|i| vec![PathBuf::from(format!("f{i}.fits"))]).collect();
            let set = FrameSet {
                filter: "V".into(),
                angles_deg: angles,
                hwp_sweep_deg: 0.0,
                data,
                files,
                nx: g.nx,
                ny: g.ny,
                warnings: vec![],
                conversion: Conversion::of_instrument(&inst),
                chips: vec![],
            };
            let cfg = ReduceConfig { bin_px: 4, ..Default::default() };
            let m = reduce_set(&set, &inst, &cfg).unwrap().map;
            assert!(m.n_valid() >= 10, "axis {axis}: {} valid bins", m.n_valid());
            for k in (0..m.q.len()).filter(|&k| m.valid[k]) {
                assert!((m.q[k] - q0).abs() < 1e-12 && (m.u[k] - u0).abs() < 1e-12, "axis {axis} bin {k}");
                assert!((m.intensity[k] - i0).abs() < 1e-8, "axis {axis} bin {k}: {}", m.intensity[k]);
            }
        }
    }

    /// The kernel's per-pixel Q, U are `StokesSolver::solve` of the `F_i` (`eq:F`, `eq:Q`,
    /// `eq:U`) to the bit, computed here pixel by pixel, for both strip axes and an angle with
    /// two exposures; masked pixels (a NaN, a saturated value) are NaN.
    #[test]
    fn pixel_qu_is_the_solver_pixel_by_pixel() {
        for axis in ["y", "x"] {
            let inst = tiny(axis);
            let g = BeamGeometry::new(&inst);
            let det = &inst.detector;
            let angles: Vec<f64> = (0..8).map(|i| i as f64 * 22.5).collect();
            let nexp = |i: usize| if i == 3 { 2 } else { 1 };
            let data: Vec<Vec<f64>> = (0..8)
                .map(|i| {
                    (0..g.nx * g.ny)
                        .map(|p| nexp(i) as f64 * (det.bias_adu + 1000.0 + ((p * 7919 + i * 104729) % 997) as f64))
                        .collect()
                })
                .collect();
            let mut data = data;
            let (xs, ys) = g.sky_pixels().nth(5).unwrap();
            let (o_nan, _) = g.beams_of_sky(xs, ys).unwrap();
            data[2][o_nan] = f64::NAN;
            let (xs, ys) = g.sky_pixels().nth(17).unwrap();
            let (_, e_sat) = g.beams_of_sky(xs, ys).unwrap();
            data[6][e_sat] = det.saturation_adu + 1.0;
            let files = (0..8).map(|i| (0..nexp(i)).map(|k| PathBuf::from(format!("f{i}_{k}"))).collect()).collect();
            let set = FrameSet {
                filter: "V".into(),
                angles_deg: angles.clone(),
                hwp_sweep_deg: 0.0,
                data,
                files,
                nx: g.nx,
                ny: g.ny,
                warnings: vec![],
                conversion: Conversion::of_instrument(&inst),
                chips: vec![],
            };
            let (q, u) = pixel_qu(&set, &inst).unwrap();
            let theta: Vec<f64> = angles.iter().map(|a| a.to_radians()).collect();
            let solver = StokesSolver::new(&theta).unwrap();
            let mut checked = 0;
            for (x, y) in g.sky_pixels() {
                let (o, e) = g.beams_of_sky(x, y).unwrap();
                if o == o_nan || e == e_sat {
                    assert!(q[o].is_nan() && u[o].is_nan(), "axis {axis}: masked pixel ({x}, {y})");
                    continue;
                }
                let f: Vec<f64> = (0..8)
                    .map(|i| {
                        let ne = nexp(i) as f64;
                        let fo = (set.data[i][o] - det.bias_adu * ne) * det.gain_e_per_adu;
                        let fe = (set.data[i][e] - det.bias_adu * ne) * det.gain_e_per_adu;
                        normalized_difference(fo, fe)
                    })
                    .collect();
                let (qs, us) = solver.solve(&f);
                assert_eq!((q[o].to_bits(), u[o].to_bits()), (qs.to_bits(), us.to_bits()), "axis {axis}: ({x}, {y})");
                checked += 1;
            }
            assert!(checked > 100, "axis {axis}: {checked} pixels");
        }
    }

    #[test]
    fn missing_angle_is_named() {
        let e = check_complete("V", &[0.0, 22.5, 67.5], 0.0).unwrap_err().to_string();
        assert!(e.contains("missing [45 deg]") && e.contains("N = 4"), "{e}");
        let e = check_complete("V", &[0.0, 22.5, 45.0, 67.5, 90.0], 0.0).unwrap_err().to_string();
        assert!(e.contains("N = 8") && e.contains("112.5 deg"), "{e}");
        check_complete("V", &[0.0, 22.5], 0.0).unwrap();
        check_complete("V", &[0.0, 22.5, 45.0, 67.5], 0.0).unwrap();
        // Off-grid sets are left to the solver.
        check_complete("V", &[0.0, 10.0, 50.0], 0.0).unwrap();
    }

    /// HWP sets complete modulo 90 or 360 deg are accepted (the plate at theta + 360 is the
    /// same position; eq:F repeats every 90 deg); a set missing a position is refused naming
    /// it in the angles given.
    #[test]
    fn angle_sets_complete_modulo_90_or_360() {
        for set in [
            vec![90.0, 112.5, 135.0, 157.5],
            vec![360.0, 382.5, 405.0, 427.5],
            vec![180.0, 202.5, 225.0, 247.5, 270.0, 292.5, 315.0, 337.5],
            vec![0.0, 22.5, 45.0, 67.5],
        ] {
            check_complete("V", &set, 0.0).unwrap_or_else(|e| panic!("{set:?}: {e}"));
        }
        let e = check_complete("V", &[90.0, 112.5, 135.0], 0.0).unwrap_err().to_string();
        assert!(e.contains("missing [157.5 deg]"), "{e}");
        let e = check_complete("V", &[0.0, 22.5, 67.5], 0.0).unwrap_err().to_string();
        assert!(e.contains("missing [45 deg]"), "{e}");
    }

    /// A turning plate's set is judged by the same rule on its rotor's positions: 16 ranges
    /// of 22.5 deg (middles at 11.25 + 22.5 k) with one missing is refused naming that range's
    /// middle; the whole turn, or one whole period (4 positions), is complete; a rotor of 8
    /// ranges of 45 deg needs both of a period's positions; a rotor offset from 0 (zero_deg
    /// 5 deg) the same.
    #[test]
    fn a_turning_plate_set_is_complete_by_the_same_rule() {
        let mids = |n: usize, zero: f64| -> Vec<f64> {
            let step = 360.0 / n as f64;
            (0..n).map(|k| zero + (k as f64 + 0.5) * step).collect()
        };
        let all = mids(16, 0.0);
        check_complete("R", &all, 22.5).unwrap();
        check_complete("R", &all[..4], 22.5).unwrap();
        check_complete("R", &all[8..12], 22.5).unwrap();
        let mut gap = all.clone();
        gap.remove(2);
        let e = check_complete("R", &gap, 22.5).unwrap_err().to_string();
        assert!(e.contains("missing [56.25 deg]") && e.contains("N = 16"), "{e}");
        let g = plate_set_gap(&all[..3], 22.5).unwrap();
        assert_eq!((g.n, g.missing_deg), (4, vec![78.75]));
        let eight = mids(8, 0.0);
        check_complete("R", &eight, 45.0).unwrap();
        check_complete("R", &eight[..2], 45.0).unwrap();
        let g = plate_set_gap(&eight[..3], 45.0).unwrap();
        assert_eq!((g.n, g.missing_deg), (4, vec![157.5]));
        let shifted = mids(16, 5.0);
        check_complete("R", &shifted, 22.5).unwrap();
        let e = check_complete("R", &shifted[1..], 22.5).unwrap_err().to_string();
        assert!(e.contains("missing [16.25 deg]"), "{e}");
        // Ranges not on one grid are left to the solver, as a fixed plate's off-grid angles.
        assert!(plate_set_gap(&[11.25, 40.0, 56.25], 22.5).is_none());
    }

    /// Angle sets in radians are refused naming the unit; degrees pass.
    #[test]
    fn radian_hwp_angles_are_refused() {
        let p = Path::new("f.fits");
        let m = |a: &[f64]| a.iter().map(|&x| (p, "V", 8usize, 8usize, x)).collect::<Vec<_>>();
        let pi8 = std::f64::consts::PI / 8.0;
        let e = check_not_radians(&m(&[0.0, pi8, 2.0 * pi8, 3.0 * pi8])).unwrap_err().to_string();
        assert!(e.contains("radians") && e.contains("f.fits"), "{e}");
        check_not_radians(&m(&[0.0, 22.5, 45.0, 67.5])).unwrap();
        check_not_radians(&m(&[0.0, 0.0])).unwrap();
    }
}
