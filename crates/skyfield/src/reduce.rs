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
use crate::io::{read_frame_raw, Frame, PixelView, RawFrame};
use crate::maps::{BinGeometry, StokesMap};
use crate::{Error, Warning};
use instrument::Instrument;
use rayon::prelude::*;
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use stokes::{normalized_difference, sigma_normalized_difference, sigma_normalized_difference_into, StokesSolver};

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
            let r = read_frame_raw(p, inst).map(RawFrame::into_frame);
            on_read();
            r
        })
        .collect();
    res.into_iter().collect()
}

/// Non-finite and saturated pixel counts of one frame.
type BadCounts = (usize, usize);

/// [`read_frames`] in the stored pixel types, with each frame's bad-pixel counts taken while
/// it is still in cache.
fn read_frames_raw(
    paths: &[PathBuf],
    inst: &Instrument,
    on_read: &(dyn Fn() + Sync),
) -> Result<Vec<(RawFrame, BadCounts)>, Error> {
    if paths.is_empty() {
        return Err(Error::NoFrames);
    }
    let sat = inst.detector.saturation_adu;
    let res: Vec<Result<(RawFrame, BadCounts), Error>> = paths
        .par_iter()
        .map(|p| {
            let r = read_frame_raw(p, inst).map(|fr| {
                let c = fr.pixels.view().count_bad(sat);
                (fr, c)
            });
            on_read();
            r
        })
        .collect();
    res.into_iter().collect()
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
/// ny, HWP angle; `bad`: non-finite and saturated counts).
fn group_frames(
    meta: &[(&Path, &str, usize, usize, f64)],
    bad: &[BadCounts],
    inst: &Instrument,
    require_complete: bool,
) -> Result<Grouping, Error> {
    if meta.is_empty() {
        return Err(Error::NoFrames);
    }
    let canon = |f: &str| inst.filter(f).map(|x| x.name.clone()).unwrap_or_else(|_| f.to_string());
    let mut by_filter: BTreeMap<String, Vec<&Path>> = BTreeMap::new();
    for fr in meta {
        by_filter.entry(canon(fr.1)).or_default().push(fr.0);
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
    for (fr, &(nbad, nsat)) in meta.iter().zip(bad) {
        if nbad == fr.2 * fr.3 {
            return Err(Error::AllNonFinite { path: fr.0.into() });
        }
        if nbad > 0 {
            warnings.push(Warning { file: Some(fr.0.into()), message: format!("{nbad} NaN/infinite pixels masked") });
        }
        let sat = inst.detector.saturation_adu;
        if nsat > 0 {
            warnings.push(Warning {
                file: Some(fr.0.into()),
                message: format!("{nsat} saturated pixels (>= {sat} ADU) masked"),
            });
        }
    }
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
    if require_complete {
        check_complete(&filter, &angles)?;
    }
    Ok(Grouping { filter, angles, members, nx, ny, warnings })
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
    pub fn from_frames(mut frames: Vec<Frame>, inst: &Instrument, require_complete: bool) -> Result<Self, Error> {
        let sat = inst.detector.saturation_adu;
        let bad: Vec<BadCounts> = frames.par_iter().map(|fr| PixelView::F64(&fr.data).count_bad(sat)).collect();
        let meta: Vec<_> =
            frames.iter().map(|f| (f.path.as_path(), f.filter.as_str(), f.nx, f.ny, f.hwp_deg)).collect();
        let g = group_frames(&meta, &bad, inst, require_complete)?;
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
        Ok(Self { filter: g.filter, angles_deg: g.angles, data, files, nx: g.nx, ny: g.ny, warnings: g.warnings })
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
    let views: Vec<PixelView> = set.data.iter().map(|d| PixelView::F64(d)).collect();
    let nexp: Vec<usize> = set.files.iter().map(|f| f.len()).collect();
    let map = reduce_views(&views, &nexp, set.nx, set.ny, &set.angles_deg, &set.filter, inst, cfg)?;
    Ok(Reduced { map, warnings: set.warnings.clone() })
}

/// The reduction proper on per-angle images (`views`, ADU, `nexp[i]` exposures summed).
///
/// Parallel over rows of bins; within a detector row each angle's o and e row segments are
/// loaded once (as f64) and every pixel's `F_i` folded into its running `Q`, `U`, their photon
/// variances and the intensity, in angle order: the same operations in the same order as a
/// per-pixel `solver.solve`, so the result does not depend on this layout.
#[allow(clippy::too_many_arguments)]
fn reduce_views(
    views: &[PixelView],
    nexp: &[usize],
    nx: usize,
    ny: usize,
    angles_deg: &[f64],
    filter: &str,
    inst: &Instrument,
    cfg: &ReduceConfig,
) -> Result<StokesMap, Error> {
    if cfg.bin_px == 0 {
        return Err(Error::Invalid("bin size must be at least 1 px".into()));
    }
    let theta: Vec<f64> = angles_deg.iter().map(|a| a.to_radians()).collect();
    let solver = StokesSolver::new(&theta)?;
    let g = BeamGeometry::new(inst);
    if (nx, ny) != (g.nx, g.ny) {
        return Err(Error::Invalid(format!(
            "frames are {} x {} px, instrument {} has {} x {}",
            nx, ny, inst.name, g.nx, g.ny
        )));
    }
    let geom = bin_geometry(inst, cfg.bin_px);
    let d = &inst.detector;
    let (bias, gain, sat, rn2) = (d.bias_adu, d.gain_e_per_adu, d.saturation_adu, d.read_noise_e.powi(2));
    let min_pixels = cfg.min_pixels.unwrap_or((cfg.bin_px * cfg.bin_px / 4).max(3));
    let n = angles_deg.len();
    let nexp_total: f64 = nexp.iter().map(|&k| k as f64).sum();
    let (cq, cu) = solver.weights();
    let bp = geom.bin_px;
    // Detector columns the bins cover.
    let xa = geom.origin_x.min(g.nx);
    let xb = (geom.origin_x + geom.nx * bp).min(g.nx);
    let stats: Vec<Option<crate::bin::BinStats>> = (0..geom.ny)
        .into_par_iter()
        .map_init(
            || Scratch::new(geom.nx),
            |sc, j| {
                for b in sc.bins.iter_mut() {
                    b.clear();
                }
                let y0 = geom.origin_y + j * bp;
                for y in y0..(y0 + bp).min(g.ny) {
                    sc.segments_of_row(&g, y, xa, xb);
                    for si in 0..sc.segs.len() {
                        let (x0, x1, o0, e0) = sc.segs[si];
                        let mut c0 = 0;
                        while c0 < x1 - x0 {
                            let len = CHUNK.min(x1 - x0 - c0);
                            sc.reset(len);
                            for i in 0..n {
                                sc.fold_angle(
                                    &views[i],
                                    o0 + c0,
                                    e0 + c0,
                                    len,
                                    nexp[i],
                                    (cq[i], cu[i]),
                                    (bias, gain, sat, rn2),
                                );
                            }
                            let Scratch { q, u, vq, vu, isum, ok, bins, .. } = sc;
                            for k in 0..len {
                                if ok[k] {
                                    let bi = (x0 + c0 + k - geom.origin_x) / bp;
                                    bins[bi].push(PixelSample {
                                        q: q[k],
                                        u: u[k],
                                        i: isum[k] / n as f64,
                                        var_q: vq[k],
                                        var_u: vu[k],
                                    });
                                }
                            }
                            c0 += len;
                        }
                    }
                }
                sc.bins.iter().map(|b| clipped_bin(b, cfg.clip, min_pixels)).collect::<Vec<_>>()
            },
        )
        .flatten_iter()
        .collect();
    let mut map = StokesMap::empty(geom, &inst.name, filter, angles_deg.to_vec());
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
    Ok(map)
}

/// Pixels of a row processed together (a FORS row): the per-pixel buffers stay in L2 and each
/// angle's o and e rows are read in long runs the hardware prefetcher follows.
const CHUNK: usize = 2048;

/// Per-thread buffers of [`reduce_views`], reused across bin rows: running per-pixel sums
/// over the HWP angles of one chunk of a row (structure of arrays, so the loops vectorize),
/// and the samples of each bin of the current bin row.
struct Scratch {
    ro: Vec<f64>,
    re: Vec<f64>,
    fo: Vec<f64>,
    fe: Vec<f64>,
    so: Vec<f64>,
    se: Vec<f64>,
    /// `sigma_F` of the current angle.
    sf: Vec<f64>,
    q: Vec<f64>,
    u: Vec<f64>,
    vq: Vec<f64>,
    vu: Vec<f64>,
    isum: Vec<f64>,
    ok: Vec<bool>,
    /// Runs of sky pixels in one detector row: `(x0, x1, o index of x0, e index of x0)`,
    /// o and e both contiguous.
    segs: Vec<(usize, usize, usize, usize)>,
    bins: Vec<Vec<PixelSample>>,
}

impl Scratch {
    fn new(nbins: usize) -> Self {
        let z = || vec![0.0; CHUNK];
        Self {
            ro: z(),
            re: z(),
            fo: z(),
            fe: z(),
            so: z(),
            se: z(),
            sf: z(),
            q: z(),
            u: z(),
            vq: z(),
            vu: z(),
            isum: z(),
            ok: vec![true; CHUNK],
            segs: Vec::new(),
            bins: vec![Vec::new(); nbins],
        }
    }

    fn reset(&mut self, len: usize) {
        for v in [&mut self.q, &mut self.u, &mut self.vq, &mut self.vu, &mut self.isum] {
            v[..len].fill(0.0);
        }
        self.ok[..len].fill(true);
    }

    /// Fold one HWP angle into the running sums of `len` pixels whose o and e images start
    /// at detector indices `o0`, `e0`: the per-pixel steps of the module docs (mask, electrons,
    /// the one `F_i`, its photon + read noise variance, `Q`, `U` by the solver's weights), in
    /// the order a per-pixel `StokesSolver::solve` uses, so sums are the same to the bit.
    #[allow(clippy::too_many_arguments)]
    #[inline]
    fn fold_angle(
        &mut self,
        view: &PixelView,
        o0: usize,
        e0: usize,
        len: usize,
        nexp: usize,
        w: (f64, f64),
        det: (f64, f64, f64, f64),
    ) {
        // The loops are bound by sqrt and division: 4-wide AVX2 vectors where the CPU has
        // them (same IEEE operations, so the same bits; no FMA is enabled).
        #[cfg(target_arch = "x86_64")]
        if std::arch::is_x86_feature_detected!("avx2") {
            // SAFETY: AVX2 support was checked just above.
            unsafe { self.fold_angle_avx2(view, o0, e0, len, nexp, w, det) };
            return;
        }
        self.fold_angle_impl(view, o0, e0, len, nexp, w, det)
    }

    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2")]
    #[allow(clippy::too_many_arguments)]
    unsafe fn fold_angle_avx2(
        &mut self,
        view: &PixelView,
        o0: usize,
        e0: usize,
        len: usize,
        nexp: usize,
        w: (f64, f64),
        det: (f64, f64, f64, f64),
    ) {
        self.fold_angle_impl(view, o0, e0, len, nexp, w, det)
    }

    #[allow(clippy::too_many_arguments)]
    #[inline(always)]
    fn fold_angle_impl(
        &mut self,
        view: &PixelView,
        o0: usize,
        e0: usize,
        len: usize,
        nexp: usize,
        (cqi, cui): (f64, f64),
        (bias, gain, sat, rn2): (f64, f64, f64, f64),
    ) {
        let ne = nexp as f64;
        let (bias_n, sat_n, rn2_n) = (bias * ne, sat * ne, ne * rn2);
        view.load(o0, &mut self.ro[..len]);
        view.load(e0, &mut self.re[..len]);
        // Branch-free, vectorizable part.
        let (ro, re) = (&self.ro[..len], &self.re[..len]);
        let (fo, fe, so, se) = (&mut self.fo[..len], &mut self.fe[..len], &mut self.so[..len], &mut self.se[..len]);
        let (q, u, isum, ok) = (&mut self.q[..len], &mut self.u[..len], &mut self.isum[..len], &mut self.ok[..len]);
        for k in 0..len {
            let (r_o, r_e) = (ro[k], re[k]);
            let bad = !(r_o.is_finite() & r_e.is_finite()) | (r_o >= sat_n) | (r_e >= sat_n);
            let f_o = (r_o - bias_n) * gain;
            let f_e = (r_e - bias_n) * gain;
            let tot = f_o + f_e;
            ok[k] &= !bad & (tot > 0.0);
            let f = normalized_difference(f_o, f_e);
            q[k] += cqi * f;
            u[k] += cui * f;
            // x / 1 is x exactly: skip the division for single exposures.
            isum[k] += if nexp == 1 { tot } else { tot / ne };
            fo[k] = f_o;
            fe[k] = f_e;
            so[k] = (f_o.max(0.0) + rn2_n).sqrt();
            se[k] = (f_e.max(0.0) + rn2_n).sqrt();
        }
        let (cq2, cu2) = (cqi * cqi, cui * cui);
        let (vq, vu) = (&mut self.vq[..len], &mut self.vu[..len]);
        let sf = &mut self.sf[..len];
        sigma_normalized_difference_into(fo, fe, so, se, sf);
        for k in 0..len {
            let vf = sf[k].powi(2);
            vq[k] += cq2 * vf;
            vu[k] += cu2 * vf;
        }
    }

    /// The runs of sky pixels of row `y` within columns `[xa, xb)`.
    fn segments_of_row(&mut self, g: &BeamGeometry, y: usize, xa: usize, xb: usize) {
        self.segs.clear();
        if xa >= xb {
            return;
        }
        if g.along_y {
            // Strips stacked along y: a row is all sky or all masked, with one e shift.
            if let Some((o, e)) = g.beams_of_sky(xa, y) {
                self.segs.push((xa, xb, o, e));
            }
            return;
        }
        let mut cur: Option<(usize, usize, usize, usize)> = None;
        for x in xa..xb {
            match (g.beams_of_sky(x, y), cur.as_mut()) {
                (Some((o, e)), Some(c)) if c.2 + (x - c.0) == o && c.3 + (x - c.0) == e => c.1 = x + 1,
                (Some((o, e)), _) => {
                    if let Some(c) = cur.take() {
                        self.segs.push(c);
                    }
                    cur = Some((x, x + 1, o, e));
                }
                (None, _) => {
                    if let Some(c) = cur.take() {
                        self.segs.push(c);
                    }
                }
            }
        }
        if let Some(c) = cur {
            self.segs.push(c);
        }
    }
}

/// Read, check and reduce frame files in one call; `on_read` ticks once per file read.
///
/// Same result as [`read_frames`] + [`FrameSet::from_frames`] + [`reduce_set`], but the frames
/// stay in their stored pixel type (f32 frames are not widened to f64 copies) and an angle's
/// frame is summed into f64 only when it has repeats.
pub fn reduce_files(
    paths: &[PathBuf],
    inst: &Instrument,
    cfg: &ReduceConfig,
    on_read: &(dyn Fn() + Sync),
) -> Result<Reduced, Error> {
    let frames = read_frames_raw(paths, inst, on_read)?;
    let meta: Vec<_> =
        frames.iter().map(|(f, _)| (f.path.as_path(), f.filter.as_str(), f.nx, f.ny, f.hwp_deg)).collect();
    let bad: Vec<BadCounts> = frames.iter().map(|(_, c)| *c).collect();
    let g = group_frames(&meta, &bad, inst, cfg.require_complete_set)?;
    let sums: Vec<Option<Vec<f64>>> = g
        .members
        .par_iter()
        .map(|m| {
            (m.len() > 1).then(|| {
                let mut d = frames[m[0]].0.pixels.clone().into_f64();
                const CH: usize = 1 << 14;
                let mut row = vec![0.0; d.len().min(CH)];
                for &k in &m[1..] {
                    let v = frames[k].0.pixels.view();
                    for (c, chunk) in d.chunks_mut(CH).enumerate() {
                        let r = &mut row[..chunk.len()];
                        v.load(c * CH, r);
                        for (a, s) in chunk.iter_mut().zip(r.iter()) {
                            *a += s;
                        }
                    }
                }
                d
            })
        })
        .collect();
    let views: Vec<PixelView> = g
        .members
        .iter()
        .zip(&sums)
        .map(|(m, s)| match s {
            Some(d) => PixelView::F64(d),
            None => frames[m[0]].0.pixels.view(),
        })
        .collect();
    let nexp: Vec<usize> = g.members.iter().map(|m| m.len()).collect();
    let map = reduce_views(&views, &nexp, g.nx, g.ny, &g.angles, &g.filter, inst, cfg)?;
    Ok(Reduced { map, warnings: g.warnings })
}

#[cfg(test)]
mod tests {
    use super::*;

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
            let set =
                FrameSet { filter: "V".into(), angles_deg: angles, data, files, nx: g.nx, ny: g.ny, warnings: vec![] };
            let cfg = ReduceConfig { bin_px: 4, ..Default::default() };
            let m = reduce_set(&set, &inst, &cfg).unwrap().map;
            assert!(m.n_valid() >= 10, "axis {axis}: {} valid bins", m.n_valid());
            for k in (0..m.q.len()).filter(|&k| m.valid[k]) {
                assert!((m.q[k] - q0).abs() < 1e-12 && (m.u[k] - u0).abs() < 1e-12, "axis {axis} bin {k}");
                assert!((m.intensity[k] - i0).abs() < 1e-8, "axis {axis} bin {k}: {}", m.intensity[k]);
            }
        }
    }

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
