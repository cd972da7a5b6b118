//! What a Mueller-field calibration costs: how many sky fields, which ones
//! and how long per HWP angle reach a target accuracy of the corrected `(q, u)` over the field,
//! from the error propagation of the one fit ([`crate::mueller_field`]): the covariance of a
//! fit to noiseless maps with the predicted per-bin errors is the inverse Fisher matrix of the
//! same model, and the correction's model error follows from it ([`MuellerField::correct`]).
//! [`simulate_plan`] checks a plan by fitting noisy maps of a given true field.
//!
//! Per-bin errors: `sigma_q = sigma_u = 1 / (sqrt(N/2) SNR)` (`eq:sigp`, optimal angle sets)
//! with `SNR = S / sqrt(S + 2 n_px RN^2)` of one exposure's `f_O + f_E` in the bin
//! (`S = rate t n_px` electrons, photon and read noise of both beams).

use crate::models::model::{FieldModel, InstPol};
use crate::mueller_field::{fit_mueller_field, CalField, MuellerField, MuellerFitOptions, Observation};
use crate::{Error, Result};
use rand::SeedableRng;
use rand_distr::{Distribution, Normal};

/// What the plan is for.
#[derive(Clone)]
pub struct PlanSetup {
    /// Bin centres (arcmin) of the calibration maps.
    pub positions: Vec<(f64, f64)>,
    /// Sky pixels per bin (both beams see this many).
    pub bin_npix: f64,
    /// HWP angles per field (optimal set).
    pub n_angles: usize,
    /// Sky count rate, `f_O + f_E`, e- per sky pixel per second.
    pub sky_rate: f64,
    pub read_noise_e: f64,
    /// Candidate fields: sky `(P, chi)` (fraction, rad).
    pub candidates: Vec<(f64, f64)>,
    pub fit: MuellerFitOptions,
    /// Polarization degree of the targets the accuracy is for (their chi averaged over).
    pub target_p: f64,
    /// The field the calibration expects (a previous calibration, the ray trace; `None`: no
    /// instrumental effect). The Fisher matrix is taken there: a retarder is invisible to
    /// light polarized along its axis, so the information on a retardance depends on the
    /// retardance present, and an identity linearization can misjudge it by a factor of 2.
    pub expected: Option<std::sync::Arc<dyn FieldModel>>,
}

/// No instrumental effect: the identity at every position (the default `M_I(0)`).
struct Clear;

impl FieldModel for Clear {
    fn eval(&self, _: f64, _: f64) -> InstPol {
        InstPol::ZERO
    }
    fn contains(&self, _: f64, _: f64) -> bool {
        true
    }
}

impl std::fmt::Debug for PlanSetup {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "PlanSetup({} positions, {} candidates)", self.positions.len(), self.candidates.len())
    }
}

/// One plan: which fields and how long.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct PlanRow {
    pub n_fields: usize,
    /// Indices into the candidates.
    pub fields: Vec<usize>,
    pub exposure_s: f64,
    pub total_s: f64,
    /// Predicted RMS of the corrected q, u over the field (model error only).
    pub rms_qu: f64,
}

impl PlanSetup {
    /// Per-bin `sigma_q = sigma_u` for an exposure of `t` s per HWP angle (`eq:sigp`).
    pub fn sigma_qu(&self, t: f64) -> f64 {
        let s = self.sky_rate * t * self.bin_npix;
        let snr = s / (s + 2.0 * self.bin_npix * self.read_noise_e * self.read_noise_e).sqrt();
        1.0 / ((self.n_angles as f64 / 2.0).sqrt() * snr)
    }

    /// The exposure per angle at which [`sigma_qu`](Self::sigma_qu) is `sigma` (solves the
    /// quadratic in `S`).
    pub fn exposure_for_sigma(&self, sigma: f64) -> f64 {
        let snr = 1.0 / ((self.n_angles as f64 / 2.0).sqrt() * sigma);
        let r = 2.0 * self.bin_npix * self.read_noise_e * self.read_noise_e;
        // S^2 = snr^2 (S + r)
        let k = snr * snr;
        let s = 0.5 * (k + (k * k + 4.0 * k * r).sqrt());
        s / (self.sky_rate * self.bin_npix)
    }

    fn fields(&self, chosen: &[usize], truth: &dyn FieldModel, sigma: f64, seed: Option<u64>) -> Vec<CalField> {
        chosen
            .iter()
            .map(|&k| {
                let (p, chi) = self.candidates[k];
                let (q0, u0) = (p * (2.0 * chi).cos(), p * (2.0 * chi).sin());
                let mut rng = seed.map(|s| rand_xoshiro::Xoshiro256PlusPlus::seed_from_u64(s + 7919 * k as u64));
                let n = Normal::new(0.0, sigma).expect("positive sigma");
                let obs = self
                    .positions
                    .iter()
                    .map(|&(x, y)| {
                        let (q, u) = truth.block_at(x, y).forward(q0, u0).unwrap_or((q0, u0));
                        let (dq, du) = match rng.as_mut() {
                            Some(r) => (n.sample(r), n.sample(r)),
                            None => (0.0, 0.0),
                        };
                        Observation::new(x, y, q + dq, u + du, sigma * sigma, sigma * sigma, 0.0)
                    })
                    .collect();
                CalField::from_p_chi(&format!("candidate {k}"), p, chi, 0.0, obs)
            })
            .collect()
    }

    /// RMS over the positions (and 4 target angles) of the model error of the corrected q, u.
    fn model_rms(&self, mf: &MuellerField) -> Result<f64> {
        let mut s = 0.0;
        let mut n = 0.0;
        for &(x, y) in &self.positions {
            for a in 0..4 {
                let chi = a as f64 * std::f64::consts::FRAC_PI_4;
                let (q0, u0) = (self.target_p * (2.0 * chi).cos(), self.target_p * (2.0 * chi).sin());
                let (qm, um) = mf.forward_at(x, y, q0, u0).unwrap_or((q0, u0));
                let (_, c) = mf.correct(x, y, qm, um, [0.0; 3])?;
                s += 0.5 * (c[0] + c[2]);
                n += 1.0;
            }
        }
        Ok((s / n).sqrt())
    }

    /// Predicted RMS of the corrected q, u for fields `chosen` at per-bin error `sigma`: the
    /// fit to noiseless maps of an identity field returns the inverse Fisher matrix as its
    /// covariance (at the expected field, [`PlanSetup::expected`]). Refused (with the fit's reason) when the fields cannot constrain the model.
    pub fn predict(&self, chosen: &[usize], sigma: f64) -> Result<f64> {
        let mf = fit_mueller_field(&self.fields(chosen, self.expected_field(), sigma, None), &self.fit)?;
        self.model_rms(&mf)
    }

    /// The field the calibration expects ([`PlanSetup::expected`]), the identity without one.
    fn expected_field(&self) -> &dyn FieldModel {
        match &self.expected {
            Some(m) => m.as_ref(),
            None => &Clear,
        }
    }

    /// For every number of fields, the cheapest choice of candidates and its exposure per HWP
    /// angle reaching `target_rms`; the model error scales as the per-bin error (the Fisher
    /// matrix scales as `1 / sigma^2`), so one fit per choice suffices. Choices the model
    /// cannot use are skipped; their reasons are returned.
    pub fn plan(&self, target_rms: f64) -> Result<(Vec<PlanRow>, Vec<String>)> {
        self.plan_with_progress(target_rms, &|_, _| {})
    }

    /// [`plan`](Self::plan), calling `step(done, total)` after every choice of fields tried.
    pub fn plan_with_progress(
        &self,
        target_rms: f64,
        step: &dyn Fn(usize, usize),
    ) -> Result<(Vec<PlanRow>, Vec<String>)> {
        if !(target_rms > 0.0) || self.candidates.is_empty() || self.positions.is_empty() {
            return Err(Error::Input("plan: need a positive target, candidates and positions".into()));
        }
        let k = self.candidates.len();
        if k > 8 {
            return Err(Error::Input(format!("plan: {k} candidate fields; at most 8")));
        }
        let sigma0 = 1e-3;
        let mut rows = Vec::new();
        let mut reasons = Vec::new();
        let total = (1usize << k) - 1;
        let mut done = 0;
        for n in 1..=k {
            let mut best: Option<PlanRow> = None;
            for mask in 0u32..(1 << k) {
                if mask.count_ones() as usize != n {
                    continue;
                }
                let chosen: Vec<usize> = (0..k).filter(|i| mask & (1 << i) != 0).collect();
                let predicted = self.predict(&chosen, sigma0);
                done += 1;
                step(done, total);
                match predicted {
                    Ok(rms0) => {
                        let t = self.exposure_for_sigma(sigma0 * target_rms / rms0);
                        // A target beyond reach (1e-300) or met by no light at all (1e300, or a
                        // sky rate of 1e308) gives an exposure of inf or 0 s: no plan, and a
                        // plot of it never ended.
                        if !(t.is_finite() && t > 0.0) {
                            return Err(Error::Input(format!(
                                "plan: the target RMS {target_rms:e} needs an exposure of {t:e} s per HWP angle at a sky rate of {:e} e-/px/s ({n} field(s) {chosen:?}): not a time that can be observed; give a target and a sky rate that need a finite, positive exposure",
                                self.sky_rate
                            )));
                        }
                        let row = PlanRow {
                            n_fields: n,
                            fields: chosen,
                            exposure_s: t,
                            total_s: t * (n * self.n_angles) as f64,
                            rms_qu: target_rms,
                        };
                        if best.as_ref().is_none_or(|b| row.total_s < b.total_s) {
                            best = Some(row);
                        }
                    }
                    Err(e) => {
                        let s = format!("{n} field(s) {chosen:?}: {e}");
                        if !reasons.iter().any(|r: &String| r.starts_with(&format!("{n} field"))) {
                            reasons.push(s);
                        }
                    }
                }
            }
            rows.extend(best);
        }
        Ok((rows, reasons))
    }

    /// Accuracy against total time for one choice of fields: `(total_s, rms_qu)` at the given
    /// exposures per HWP angle.
    pub fn curve(&self, chosen: &[usize], exposures_s: &[f64]) -> Result<Vec<(f64, f64)>> {
        let sigma0 = 1e-3;
        let rms0 = self.predict(chosen, sigma0)?;
        Ok(exposures_s
            .iter()
            .map(|&t| (t * (chosen.len() * self.n_angles) as f64, rms0 * self.sigma_qu(t) / sigma0))
            .collect())
    }
}

/// Bins of the timing probe of [`PlanSetup::estimate`].
pub const PROBE_BINS: usize = 1024;

/// Memory of a plan's fit per bin and field (bytes): measured as the growth of the peak
/// resident size of `instpol plan` (FORS1, three candidates, the default model) from `--bin
/// 32` to `--bin 16`, 14.6 MB for 36,864 more bin-fields (about 400 B), rounded up.
pub const BYTES_PER_BIN_FIELD: f64 = 500.0;

/// The longest plan (estimated, seconds) and the largest (estimated memory, bytes) run
/// without being asked to: `plan --bin 1` on FORS1 grew past 4 GB and ran for most of an hour.
pub const MAX_SECONDS: f64 = 600.0;
pub const MAX_BYTES: f64 = 2.0 * 1024.0 * 1024.0 * 1024.0;

/// The estimated cost of a plan ([`PlanSetup::estimate`]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Work {
    pub bins: usize,
    pub seconds: f64,
    pub bytes: f64,
}

impl Work {
    /// Why the plan should not run unless forced: beyond [`MAX_SECONDS`] or [`MAX_BYTES`].
    pub fn over_limit(&self) -> Option<String> {
        if self.bytes > MAX_BYTES {
            Some(format!(
                "{} bins: the fits need about {:.1} GB of memory (limit {:.0} GB)",
                self.bins,
                self.bytes / 1e9,
                MAX_BYTES / 1e9
            ))
        } else if self.seconds > MAX_SECONDS {
            Some(format!("{} bins: about {:.0} s of fitting (limit {:.0} s)", self.bins, self.seconds, MAX_SECONDS))
        } else {
            None
        }
    }
}

/// Check a plan by simulation: noisy maps of the true field `truth` with the plan's per-bin
/// errors, fitted, and the corrected q, u of targets (degree `target_p`, 4 angles) at every
/// position compared with their truth. Returns the RMS error of the corrected q, u (model
/// error only: the targets are noiseless).
pub fn simulate_plan(setup: &PlanSetup, row: &PlanRow, truth: &dyn FieldModel, seed: u64) -> Result<f64> {
    let sigma = setup.sigma_qu(row.exposure_s);
    let mf = fit_mueller_field(&setup.fields(&row.fields, truth, sigma, Some(seed)), &setup.fit)?;
    let (mut s, mut n) = (0.0, 0.0);
    for &(x, y) in &setup.positions {
        for a in 0..4 {
            let chi = a as f64 * std::f64::consts::FRAC_PI_4;
            let (q0, u0) = (setup.target_p * (2.0 * chi).cos(), setup.target_p * (2.0 * chi).sin());
            let (qm, um) = truth
                .block_at(x, y)
                .forward(q0, u0)
                .ok_or_else(|| Error::Input(format!("the true field at ({x}, {y}) passes no light")))?;
            let ((qc, uc), _) = mf.correct(x, y, qm, um, [0.0; 3])?;
            s += 0.5 * ((qc - q0).powi(2) + (uc - u0).powi(2));
            n += 1.0;
        }
    }
    Ok((s / n).sqrt())
}

/// A plan's simulated RMS above this factor times its target says the Fisher prediction does
/// not hold at this field (near zero retardance the errors are not Gaussian).
pub const SIMULATION_TOLERANCE: f64 = 1.25;

/// Noise draws of [`PlanSetup::simulated_rms`].
pub const SIMULATION_DRAWS: u64 = 4;

/// What a plan is asked for: everything of a [`PlanSetup`] but the positions, which
/// [`PlanSetup::for_instrument`] takes from the instrument's detector.
#[derive(Clone)]
pub struct PlanRequest {
    /// Bin side (px) of the maps the calibration will be fitted to.
    pub bin_px: usize,
    /// HWP angles per field (an optimal set).
    pub n_angles: usize,
    /// Sky count rate (e-/px/s, both beams).
    pub sky_rate: f64,
    /// Candidate sky fields `(P, chi)` (fraction, rad).
    pub candidates: Vec<(f64, f64)>,
    /// What the fit frees, and the degree of its polynomials.
    pub kind: crate::mueller_field::Kind,
    pub deg: usize,
    /// Polarization degree (fraction) of the targets the correction is for.
    pub target_p: f64,
    /// The field expected to be present, where the Fisher matrix is taken (identity: none).
    pub expected: Option<std::sync::Arc<MuellerField>>,
}

/// The centres (arcmin from the detector centre) of the `bin_px` bins covering the detector of
/// `inst`, row by row: the positions of the maps `instpol reduce --bin` makes
/// (`skyfield::BinGeometry::covering`).
pub fn detector_bin_centres(inst: &instrument::Instrument, bin_px: usize) -> Vec<(f64, f64)> {
    let d = &inst.detector;
    let g = skyfield::maps::BinGeometry::covering(bin_px, 0, 0, d.nx, d.ny, d.pixel_scale_arcsec);
    let mut positions = Vec::with_capacity(g.len());
    for j in 0..g.ny {
        for i in 0..g.nx {
            positions.push(g.centre_arcmin(i, j));
        }
    }
    positions
}

/// The first of `positions` (arcmin) where `field` has no value (an interpolated form outside
/// the hull of the bins it was built from), where a plan would see a silent NaN field.
pub fn uncovered_position(field: &MuellerField, positions: &[(f64, f64)]) -> Option<(f64, f64)> {
    positions.iter().copied().find(|&(x, y)| !field.full_at(x, y).iter().all(|v| v.is_finite()))
}

impl PlanSetup {
    /// The plan of `req` over the bins of `inst`'s detector ([`detector_bin_centres`]), with its
    /// read noise; the fit's polynomials scaled by the field's half-width (the largest |x| or
    /// |y| of a bin centre, at least 0.1 arcmin).
    pub fn for_instrument(inst: &instrument::Instrument, req: PlanRequest) -> Result<Self> {
        let positions = detector_bin_centres(inst, req.bin_px);
        if let Some(m) = &req.expected {
            if let Some((x, y)) = uncovered_position(m, &positions) {
                return Err(Error::Input(format!(
                    "the expected {} field has no value at the plan's bin centre ({x:.2}, {y:.2}) arcmin",
                    m.smooth.name()
                )));
            }
        }
        let radius = positions.iter().map(|&(x, y)| x.abs().max(y.abs())).fold(0.0, f64::max).max(0.1);
        Ok(PlanSetup {
            positions,
            bin_npix: (req.bin_px * req.bin_px) as f64,
            n_angles: req.n_angles,
            sky_rate: req.sky_rate,
            read_noise_e: inst.detector.read_noise_e,
            candidates: req.candidates,
            fit: MuellerFitOptions { kind: req.kind, deg: req.deg, scale_arcmin: radius, ..Default::default() },
            target_p: req.target_p,
            expected: req.expected.map(|m| -> std::sync::Arc<dyn FieldModel> { m }),
        })
    }

    /// What [`plan`](Self::plan) will cost, before it runs: its fits scale with the bins
    /// times the fields of every choice of candidates (`k 2^(k-1)` for `k` candidates), so one
    /// fit of all the candidates over at most [`PROBE_BINS`] of the bins is timed and scaled;
    /// the memory is that of the largest fit, [`BYTES_PER_BIN_FIELD`] per bin and field.
    pub fn estimate(&self) -> Result<Work> {
        let k = self.candidates.len();
        let n = self.positions.len();
        // Bins spread over the field (a multiplicative hash of the index), not every m-th in
        // reading order: that picked one column of the detector, a fit that fails at once.
        let positions: Vec<(f64, f64)> = if n <= PROBE_BINS {
            self.positions.clone()
        } else {
            (0..PROBE_BINS).map(|j| self.positions[(j as u64 * 2_654_435_761 % n as u64) as usize]).collect()
        };
        let probe = PlanSetup { positions, ..self.clone() };
        let all: Vec<usize> = (0..k).collect();
        let t0 = std::time::Instant::now();
        // A probe the model cannot fit still took its time; plan reports the reason.
        let _ = probe.predict(&all, 1e-3);
        let per_bin_field = t0.elapsed().as_secs_f64() / (probe.positions.len() * k.max(1)) as f64;
        let fields_in_all_choices = (k * (1usize << k.saturating_sub(1))) as f64;
        Ok(Work {
            bins: n,
            seconds: per_bin_field * n as f64 * fields_in_all_choices,
            bytes: BYTES_PER_BIN_FIELD * (n * k) as f64,
        })
    }

    /// The plan to take among `rows`: the one of least total observing time.
    pub fn cheapest(rows: &[PlanRow]) -> Option<PlanRow> {
        rows.iter().min_by(|x, y| x.total_s.total_cmp(&y.total_s)).cloned()
    }

    /// The RMS error of the corrected q, u of `row` by simulation ([`simulate_plan`]) against
    /// the expected field (identity without one), over [`SIMULATION_DRAWS`] noise draws
    /// (seeds 0, 1, ...): the root of the mean of their squares.
    pub fn simulated_rms(&self, row: &PlanRow) -> Result<f64> {
        let mut s = 0.0;
        for seed in 0..SIMULATION_DRAWS {
            let r = simulate_plan(self, row, self.expected_field(), seed)?;
            s += r * r;
        }
        Ok((s / SIMULATION_DRAWS as f64).sqrt())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The bins cover the detector row by row, centres one bin apart and symmetric about the
    /// centre for a detector of whole bins; the cheapest plan is the one of least total time.
    #[test]
    fn bin_centres_and_cheapest() {
        let inst = instrument::Instrument::load("fors1").unwrap();
        let d = &inst.detector;
        let bin = 256;
        let c = detector_bin_centres(&inst, bin);
        assert_eq!(c.len(), d.nx.div_ceil(bin) * d.ny.div_ceil(bin));
        let step = bin as f64 * d.pixel_scale_arcsec / 60.0;
        assert!((c[1].0 - c[0].0 - step).abs() < 1e-12 && c[1].1 == c[0].1);
        if d.nx.is_multiple_of(bin) && d.ny.is_multiple_of(bin) {
            let (first, last) = (c[0], c[c.len() - 1]);
            assert!((first.0 + last.0).abs() < 1e-12 && (first.1 + last.1).abs() < 1e-12, "{first:?} {last:?}");
        }
        let row = |t: f64| PlanRow { n_fields: 1, fields: vec![0], exposure_s: t, total_s: t, rms_qu: 0.0 };
        assert_eq!(PlanSetup::cheapest(&[row(3.0), row(1.0), row(2.0)]).unwrap().total_s, 1.0);
        assert!(PlanSetup::cheapest(&[]).is_none());
    }
}
