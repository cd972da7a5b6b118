//! Frame reduction: a set of frames at `N` HWP angles to a binned [`StokesMap`].
//!
//! Steps: read the frames ([`read_frames`], in parallel); group them by filter and HWP angle
//! and check that they form a usable set ([`FrameSet::from_frames`]: one filter, one size,
//! a complete set of angles — for angles on the `22.5 deg` grid the smallest optimal set
//! that contains them, or the `N = 2` pair `{0, 22.5}`; several frames at one angle are summed);
//! then for every sky pixel the mask lets through ([`crate::beams`]) take `f_O,i`, `f_E,i`
//! (bias removed, times the gain: electrons), the one `F_i` (`stokes::normalized_difference`)
//! and `Q/I`, `U/I` from the one `stokes::StokesSolver`, and finally the sigma-clipped mean of
//! each bin ([`crate::bin`]).
//!
//! Pixels are masked (not used) when any of their `2N` values is NaN or infinite (a warning
//! names the file and the count), reaches the instrument's saturation level (warning), or
//! when `f_O + f_E <= 0`. A frame with no finite pixel is an error.
//!
//! Errors of a bin are given two ways: from the scatter of its kept pixels (`SIGMA_Q`, the
//! honest one, which includes anything the noise model does not know) and propagated from
//! photon and read noise (`SIGQ_PHOT`, `sigma_F` of `stokes::sigma_normalized_difference`); the
//! two agree for pure photon noise (`eq:sigp` divided by `sqrt(n)`).

use crate::beams::BeamGeometry;
use crate::bin::{clipped_bin, ClipConfig, PixelSample};
use crate::io::{read_frame, Frame};
use crate::maps::{BinGeometry, StokesMap};
use crate::{Error, Warning};
use instrument::Instrument;
use rayon::prelude::*;
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use stokes::{normalized_difference, sigma_normalized_difference, StokesSolver};

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

/// Read frames in parallel; `on_read` is called once per file read (for a progress bar).
/// The first unreadable file (in the order given) is the error.
pub fn read_frames(paths: &[PathBuf], inst: &Instrument, on_read: &(dyn Fn() + Sync)) -> Result<Vec<Frame>, Error> {
    if paths.is_empty() {
        return Err(Error::NoFrames);
    }
    let res: Vec<Result<Frame, Error>> = paths
        .par_iter()
        .map(|p| {
            let r = read_frame(p, inst);
            on_read();
            r
        })
        .collect();
    res.into_iter().collect()
}

/// A usable set: one filter, one detector size, each HWP angle once (frames at the same
/// angle summed), angles sorted.
#[derive(Debug, Clone)]
pub struct FrameSet {
    /// Canonical filter name (the instrument's, when it knows the filter).
    pub filter: String,
    pub angles_deg: Vec<f64>,
    /// Summed pixel values (ADU) per angle, row-major.
    pub data: Vec<Vec<f64>>,
    /// Files per angle.
    pub files: Vec<Vec<PathBuf>>,
    pub nx: usize,
    pub ny: usize,
    pub warnings: Vec<Warning>,
}

/// Angles (deg) equal within this tolerance are the same plate position.
const ANGLE_TOL_DEG: f64 = 0.05;

fn fmt_angles(a: &[f64]) -> String {
    let v: Vec<String> = a.iter().map(|x| format!("{x} deg")).collect();
    format!("[{}]", v.join(", "))
}

impl FrameSet {
    /// Group and check frames (see the module docs).
    pub fn from_frames(frames: Vec<Frame>, inst: &Instrument, require_complete: bool) -> Result<Self, Error> {
        if frames.is_empty() {
            return Err(Error::NoFrames);
        }
        let canon = |f: &str| inst.filter(f).map(|x| x.name.clone()).unwrap_or_else(|_| f.to_string());
        let mut by_filter: BTreeMap<String, Vec<&Path>> = BTreeMap::new();
        for fr in &frames {
            by_filter.entry(canon(&fr.filter)).or_default().push(&fr.path);
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
        let (nx, ny) = (frames[0].nx, frames[0].ny);
        for fr in &frames {
            if fr.nx != nx || fr.ny != ny {
                return Err(Error::SizeMismatch {
                    path: fr.path.clone(),
                    got_nx: fr.nx,
                    got_ny: fr.ny,
                    expected: format!("{} is {nx} x {ny}", frames[0].path.display()),
                });
            }
        }
        let mut warnings = Vec::new();
        for fr in &frames {
            let bad = fr.data.iter().filter(|v| !v.is_finite()).count();
            if bad == fr.data.len() {
                return Err(Error::AllNonFinite { path: fr.path.clone() });
            }
            if bad > 0 {
                warnings.push(Warning {
                    file: Some(fr.path.clone()),
                    message: format!("{bad} NaN/infinite pixels masked"),
                });
            }
            let sat = inst.detector.saturation_adu;
            let nsat = fr.data.iter().filter(|&&v| v >= sat).count();
            if nsat > 0 {
                warnings.push(Warning {
                    file: Some(fr.path.clone()),
                    message: format!("{nsat} saturated pixels (>= {sat} ADU) masked"),
                });
            }
        }
        // Group by angle, summing repeated exposures.
        let mut angles: Vec<f64> = Vec::new();
        let mut data: Vec<Vec<f64>> = Vec::new();
        let mut files: Vec<Vec<PathBuf>> = Vec::new();
        let mut order: Vec<usize> = (0..frames.len()).collect();
        order.sort_by(|&a, &b| frames[a].hwp_deg.total_cmp(&frames[b].hwp_deg));
        for k in order {
            let fr = &frames[k];
            match angles.iter().position(|a| (a - fr.hwp_deg).abs() < ANGLE_TOL_DEG) {
                Some(i) => {
                    for (d, s) in data[i].iter_mut().zip(&fr.data) {
                        *d += s;
                    }
                    files[i].push(fr.path.clone());
                    warnings.push(Warning {
                        file: Some(fr.path.clone()),
                        message: format!(
                            "second frame at HWP angle {} deg: summed with {}",
                            fr.hwp_deg,
                            files[i][0].display()
                        ),
                    });
                }
                None => {
                    angles.push(fr.hwp_deg);
                    data.push(fr.data.clone());
                    files.push(vec![fr.path.clone()]);
                }
            }
        }
        if require_complete {
            check_complete(&filter, &angles)?;
        }
        Ok(Self { filter, angles_deg: angles, data, files, nx, ny, warnings })
    }
}

/// For angles on the optimal grid (`i * 22.5 deg`), the smallest optimal set containing them
/// must be complete; `{0, 22.5}` is the complete `N = 2` set.
fn check_complete(filter: &str, angles: &[f64]) -> Result<(), Error> {
    let idx: Option<Vec<usize>> = angles
        .iter()
        .map(|a| {
            let r = a / 22.5;
            ((r - r.round()).abs() * 22.5 < ANGLE_TOL_DEG && r.round() >= 0.0).then_some(r.round() as usize)
        })
        .collect();
    let Some(idx) = idx else { return Ok(()) };
    let m = idx.iter().max().map_or(0, |&i| i + 1);
    if m <= 2 && idx.len() == 2 {
        return Ok(());
    }
    let n = m.div_ceil(4).max(1) * 4;
    let expected: Vec<f64> = (0..n).map(|i| i as f64 * 22.5).collect();
    let missing: Vec<f64> = (0..n).filter(|i| !idx.contains(i)).map(|i| i as f64 * 22.5).collect();
    if missing.is_empty() {
        return Ok(());
    }
    Err(Error::MissingAngle {
        filter: filter.into(),
        have: fmt_angles(angles),
        missing: fmt_angles(&missing),
        n,
        expected: fmt_angles(&expected),
    })
}

/// The reduced map with the notes gathered on the way.
#[derive(Debug, Clone)]
pub struct Reduced {
    pub map: StokesMap,
    pub warnings: Vec<Warning>,
}

/// The bin grid used for an instrument: `bin_px` bins starting at the first sky band.
pub fn bin_geometry(inst: &Instrument, bin_px: usize) -> BinGeometry {
    let g = BeamGeometry::new(inst);
    let first = g.sky_bands().iter().map(|r| r.start).min().unwrap_or(0);
    let (ox, oy) = if g.along_y { (0, first) } else { (first, 0) };
    BinGeometry::covering(bin_px, ox, oy, g.nx, g.ny, inst.detector.pixel_scale_arcsec)
}

/// Per-pixel reduction of one sky pixel: `None` when masked.
#[inline]
fn pixel_sample(
    set: &FrameSet,
    solver: &StokesSolver,
    o: usize,
    e: usize,
    bias: f64,
    gain: f64,
    sat: f64,
    rn2: f64,
    f: &mut [f64],
    vf: &mut [f64],
) -> Option<PixelSample> {
    let mut isum = 0.0;
    for (i, d) in set.data.iter().enumerate() {
        let nexp = set.files[i].len() as f64;
        let (ro, re) = (d[o], d[e]);
        if !(ro.is_finite() && re.is_finite()) || ro >= sat * nexp || re >= sat * nexp {
            return None;
        }
        let fo = (ro - bias * nexp) * gain;
        let fe = (re - bias * nexp) * gain;
        let tot = fo + fe;
        if !(tot > 0.0) {
            return None;
        }
        f[i] = normalized_difference(fo, fe);
        vf[i] =
            sigma_normalized_difference(fo, fe, (fo.max(0.0) + nexp * rn2).sqrt(), (fe.max(0.0) + nexp * rn2).sqrt())
                .powi(2);
        isum += tot / nexp;
    }
    let (q, u) = solver.solve(f);
    let (cq, cu) = solver.weights();
    let (mut var_q, mut var_u) = (0.0, 0.0);
    for i in 0..f.len() {
        var_q += cq[i] * cq[i] * vf[i];
        var_u += cu[i] * cu[i] * vf[i];
    }
    Some(PixelSample { q, u, i: isum / f.len() as f64, var_q, var_u })
}

/// Per-pixel `Q/I`, `U/I` of every sky pixel (NaN where masked or outside the sky bands),
/// row-major over the detector in o coordinates: for inspection and tests.
pub fn pixel_qu(set: &FrameSet, inst: &Instrument) -> Result<(Vec<f64>, Vec<f64>), Error> {
    let theta: Vec<f64> = set.angles_deg.iter().map(|a| a.to_radians()).collect();
    let solver = StokesSolver::new(&theta)?;
    let g = BeamGeometry::new(inst);
    let d = &inst.detector;
    let n = set.angles_deg.len();
    let mut q = vec![f64::NAN; g.nx * g.ny];
    let mut u = vec![f64::NAN; g.nx * g.ny];
    let (mut f, mut vf) = (vec![0.0; n], vec![0.0; n]);
    for (x, y) in g.sky_pixels() {
        let (o, e) = g.beams_of_sky(x, y).expect("sky pixel");
        if let Some(s) = pixel_sample(
            set,
            &solver,
            o,
            e,
            d.bias_adu,
            d.gain_e_per_adu,
            d.saturation_adu,
            d.read_noise_e.powi(2),
            &mut f,
            &mut vf,
        ) {
            q[o] = s.q;
            u[o] = s.u;
        }
    }
    Ok((q, u))
}

/// Reduce a checked frame set to a binned Stokes map.
pub fn reduce_set(set: &FrameSet, inst: &Instrument, cfg: &ReduceConfig) -> Result<Reduced, Error> {
    if cfg.bin_px == 0 {
        return Err(Error::Invalid("bin size must be at least 1 px".into()));
    }
    let theta: Vec<f64> = set.angles_deg.iter().map(|a| a.to_radians()).collect();
    let solver = StokesSolver::new(&theta)?;
    let g = BeamGeometry::new(inst);
    if (set.nx, set.ny) != (g.nx, g.ny) {
        return Err(Error::Invalid(format!(
            "frames are {} x {} px, instrument {} has {} x {}",
            set.nx, set.ny, inst.name, g.nx, g.ny
        )));
    }
    let geom = bin_geometry(inst, cfg.bin_px);
    let d = &inst.detector;
    let (bias, gain, sat, rn2) = (d.bias_adu, d.gain_e_per_adu, d.saturation_adu, d.read_noise_e.powi(2));
    let min_pixels = cfg.min_pixels.unwrap_or((cfg.bin_px * cfg.bin_px / 4).max(3));
    let n = set.angles_deg.len();
    let nexp_total: f64 = set.files.iter().map(|f| f.len() as f64).sum();
    let stats: Vec<_> = (0..geom.len())
        .into_par_iter()
        .map_init(
            || (vec![0.0; n], vec![0.0; n], Vec::new()),
            |(f, vf, samples), k| {
                let (i, j) = (k % geom.nx, k / geom.nx);
                samples.clear();
                let x0 = geom.origin_x + i * geom.bin_px;
                let y0 = geom.origin_y + j * geom.bin_px;
                for y in y0..(y0 + geom.bin_px).min(g.ny) {
                    for x in x0..(x0 + geom.bin_px).min(g.nx) {
                        if let Some((o, e)) = g.beams_of_sky(x, y) {
                            if let Some(s) = pixel_sample(set, &solver, o, e, bias, gain, sat, rn2, f, vf) {
                                samples.push(s);
                            }
                        }
                    }
                }
                clipped_bin(samples, cfg.clip, min_pixels)
            },
        )
        .collect();
    let mut map = StokesMap::empty(geom, &inst.name, &set.filter, set.angles_deg.clone());
    for (k, s) in stats.into_iter().enumerate() {
        let Some(s) = s else { continue };
        let (p, chi) = stokes::polarization(s.q, s.u);
        map.q[k] = s.q;
        map.u[k] = s.u;
        map.sigma_q[k] = s.sigma_q;
        map.sigma_u[k] = s.sigma_u;
        map.cov_qu[k] = s.cov_qu;
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
        return Err(Error::NoValidBins);
    }
    Ok(Reduced { map, warnings: set.warnings.clone() })
}

/// Read, check and reduce frame files in one call; `on_read` ticks once per file read.
pub fn reduce_files(
    paths: &[PathBuf],
    inst: &Instrument,
    cfg: &ReduceConfig,
    on_read: &(dyn Fn() + Sync),
) -> Result<Reduced, Error> {
    let frames = read_frames(paths, inst, on_read)?;
    let set = FrameSet::from_frames(frames, inst, cfg.require_complete_set)?;
    reduce_set(&set, inst, cfg)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn missing_angle_is_named() {
        let e = check_complete("V", &[0.0, 22.5, 67.5]).unwrap_err().to_string();
        assert!(e.contains("missing [45 deg]") && e.contains("N = 4"), "{e}");
        let e = check_complete("V", &[0.0, 22.5, 45.0, 67.5, 90.0]).unwrap_err().to_string();
        assert!(e.contains("N = 8") && e.contains("112.5 deg"), "{e}");
        check_complete("V", &[0.0, 22.5]).unwrap();
        check_complete("V", &[0.0, 22.5, 45.0, 67.5]).unwrap();
        // Off-grid sets are left to the solver.
        check_complete("V", &[0.0, 10.0, 50.0]).unwrap();
    }
}
