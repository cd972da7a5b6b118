//! A calibration's correction as one value: the chain from the sky to the plate that a
//! calibration file defines for a set of data (rows of a catalog, or the bins of a Stokes
//! map), and its inversion with the errors of the measurement and of the models propagated.
//! [`crate::correction::request`] resolves a file and a request into a [`Chain`]; rows and maps are then
//! corrected by the same call, [`Chain::invert`].
//!
//! The elements, in the order light meets them (`docs/architecture.md`, "The optical chain"):
//!
//! - the telescope ([`TelescopeStep`]): a band of a fitted telescope model over each row's
//!   track, one shared track, or the recorded exposures each over its own track;
//! - the field ([`FieldStep`]): a partial polarizer `M_I(p, phi)` of `eq:instpol` (a field
//!   calibration, inverted exactly or to first order, `eq:approx`, with the model's own
//!   covariance, [`Corrector`]), or a fitted Mueller field ([`MuellerCal::correct`]), or an
//!   instrument's constant response from standards (`(q0, u0)`, efficiency and angle offset,
//!   [`ResponseCal::correct`], the same over the field);
//! - the half-wave plate's zero angle ([`Chain::zero_angle_deg`]): the models live in the sky
//!   frame of that zero angle; each measurement says its own frame ([`mueller::Frame`]: at the
//!   plate, or in a sky frame with the zero angle it carries) and is turned from there, once.
//!
//! [`Chain::instrument`] gives the same chain as a forward model ([`field::InstrumentChain`]),
//! the one the simulator renders through, so that what a correction undoes can be checked
//! against what a simulation put in.

use crate::correction::correct::{CorrectOptions, Corrected, CorrectedMap, Corrector, MapError, Measurement};
use crate::files::calfile::Calibration;
use crate::models::model::FieldModel;
use crate::mueller_field::cal::MuellerCal;
use crate::response::cal::ResponseCal;
use crate::telescope::cal::ChainCorrected;
use crate::telescope::{PreparedExposures, Seen, TelescopeFit, Track};
use std::sync::Arc;

/// The field-dependent part of a correction.
pub enum FieldStep<'a> {
    /// No field model (a telescope model alone).
    None,
    /// A field calibration's partial polarizer, with the method, the extrapolation rule and
    /// the zero angle of its sky frame in its options; the corrector's model is the
    /// calibration, or the calibration with an added model error
    /// ([`crate::correction::correct::WithModelError`]).
    PartialPolarizer { corrector: Corrector<'a, dyn FieldModel + 'a>, calibration: &'a Calibration },
    /// A Mueller field, inverted exactly; its options carry the zero angle of its sky frame.
    Mueller(&'a MuellerCal, CorrectOptions),
    /// A constant response from standards ([`field::ConstantResponse`]), inverted exactly in
    /// the sky frame of its own zero angle.
    Response(&'a ResponseCal),
}

/// How the data saw the telescope.
#[derive(Debug)]
pub enum Tracks {
    /// Each row over its own track.
    PerRow(Vec<Track>),
    /// All rows (or bins) over one track.
    Shared(Track),
    /// The recorded exposures, each over its own track, their demodulations built once.
    Exposures(Box<RecordedExposures>),
}

/// Exposures a set of data recorded (`skyfield::RecordedAngles`), ready for the correction:
/// the telescope's demodulations of them built once, and the exposures themselves (HWP angle
/// as read, track) with the zero angle of the plate they were taken through (the chain's, else
/// the one the data carry).
pub struct RecordedExposures {
    pub prepared: PreparedExposures,
    pub list: Vec<mueller::telescope::Exposure>,
    /// The HWP zero angle (rad) of the plate.
    pub plate: f64,
    /// The whole chain over these exposures behind a field model, built once for every row
    /// or bin ([`Chain::invert_parts`]): its field element is a copy of the calibration.
    whole: std::sync::OnceLock<field::InstrumentChain>,
}

impl std::fmt::Debug for RecordedExposures {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("RecordedExposures")
            .field("prepared", &self.prepared)
            .field("list", &self.list)
            .field("plate", &self.plate)
            .finish_non_exhaustive()
    }
}

impl RecordedExposures {
    /// The exposures `tracks` of a set over `track` (whose rotator angle they share) through
    /// the band `band` of `tel`, taken through a plate of zero angle `plate` (rad); `None` when
    /// none are recorded ([`crate::telescope::cal::prepare_recorded`]).
    pub fn new(
        tel: &TelescopeFit,
        band: &str,
        track: Track,
        tracks: &[skyfield::ExposureTrack],
        plate: f64,
    ) -> crate::Result<Option<Self>> {
        let Some(prepared) = crate::telescope::cal::prepare_recorded(tel, band, track, tracks, plate)? else {
            return Ok(None);
        };
        let list = tracks
            .iter()
            .map(|x| mueller::telescope::Exposure {
                hwp: x.hwp_deg.to_radians(),
                track: Track::new(x.start, Some(x.end)).with_rotator(track.rotator),
            })
            .collect();
        Ok(Some(Self { prepared, list, plate, whole: std::sync::OnceLock::new() }))
    }
}

/// The telescope part of a correction: a band of a fitted model and the tracks.
#[derive(Debug)]
pub struct TelescopeStep<'a> {
    pub fit: &'a TelescopeFit,
    pub band: String,
    pub tracks: Tracks,
}

impl TelescopeStep<'_> {
    /// How row `i` saw the telescope.
    fn seen(&self, i: usize) -> Seen<'_> {
        match &self.tracks {
            Tracks::PerRow(v) => Seen::Track(v[i]),
            Tracks::Shared(t) => Seen::Track(*t),
            Tracks::Exposures(p) => Seen::Prepared(&p.prepared),
        }
    }
}

/// Why one row (or bin) could not be corrected.
#[derive(Debug, thiserror::Error)]
pub enum RowError {
    #[error("{0}")]
    Field(#[from] crate::correction::correct::Error),
    #[error("{0}")]
    Chain(#[from] crate::Error),
}

/// The chain a calibration defines for a set of data, ready to invert (module docs).
pub struct Chain<'a> {
    /// The HWP zero angle (deg) of the sky frame the models live in (the field calibration's,
    /// else for a map the one it records): each measurement is turned into it from its own
    /// frame ([`Measurement::in_sky`]). `None`: the data's own frame, as a telescope model
    /// alone takes rows (its standards were measured so).
    pub zero_angle_deg: Option<f64>,
    pub field: FieldStep<'a>,
    pub telescope: Option<TelescopeStep<'a>>,
}

impl<'a> FieldStep<'a> {
    /// The partial polarizer of `calibration` with `opts`.
    pub fn partial_polarizer(calibration: &'a Calibration, opts: CorrectOptions) -> Self {
        FieldStep::PartialPolarizer { corrector: Corrector::new(calibration, opts), calibration }
    }
}

impl Chain<'_> {
    /// The sky's polarization of row `i` (its track, when the rows each have their own; any
    /// `i` otherwise) from its measurement in its frame: turned into the models' frame, then the field
    /// and the telescope undone in the reverse of the order light met them, the errors of the
    /// measurement and of the models propagated. With a telescope, the returned `inst` holds the
    /// field's and the telescope's instrumental polarization together (first order), as
    /// catalogs and maps report it ([`crate::telescope::cal::ChainCorrected::with_telescope_in_inst`]).
    pub fn invert(&self, i: usize, m: &Measurement) -> Result<Corrected, RowError> {
        // Corrected where the models live (the instrument's frame), then given back on the sky
        // when the measurement came in the celestial frame ([`Chain::turn_onto_sky_deg`]).
        let c = self.invert_parts(i, m)?.with_telescope_in_inst();
        Ok(c.turned(self.turn_onto_sky_deg(m.frame.position_angle_deg())))
    }

    /// The turn (deg) that puts a correction made in the instrument's frame onto the sky, for
    /// data taken at the instrument's position angle on the sky `pa_deg` (a celestial row's, a
    /// map's `SKYPA`): that angle, or 0 when the chain holds a telescope model, whose inverse
    /// ends on the sky already (its offset and rotator angle turn the sky into the instrument,
    /// `mueller::telescope`), or when the data give no angle.
    pub fn turn_onto_sky_deg(&self, pa_deg: Option<f64>) -> f64 {
        if self.telescope.is_some() {
            0.0
        } else {
            pa_deg.unwrap_or(0.0)
        }
    }

    /// [`invert`](Self::invert) with the telescope's part kept apart: `corrected.inst` is the
    /// field's alone, and `q_tel, u_tel` what the telescope makes of an unpolarized star as
    /// these data saw it (zero without a telescope).
    pub fn invert_parts(&self, i: usize, m: &Measurement) -> Result<ChainCorrected, RowError> {
        let alone = |corrected| ChainCorrected { corrected, q_tel: 0.0, u_tel: 0.0 };
        match (&self.telescope, &self.field) {
            (None, FieldStep::PartialPolarizer { corrector, .. }) => Ok(alone(corrector.correct(m)?)),
            (None, FieldStep::Mueller(mc, o)) => Ok(alone(mc.correct(m, o)?)),
            (None, FieldStep::Response(r)) => Ok(alone(r.correct(m)?)),
            (Some(t), field) => {
                let cor = match field {
                    FieldStep::PartialPolarizer { corrector, .. } => Some(corrector),
                    FieldStep::None => None,
                    FieldStep::Mueller(..) => {
                        return Err(RowError::Chain(crate::Error::Input(
                            "a Mueller field and a telescope model are not corrected together".into(),
                        )))
                    }
                    FieldStep::Response(..) => {
                        return Err(RowError::Chain(crate::Error::Input(
                            "a constant response and a telescope model are not corrected together".into(),
                        )))
                    }
                };
                let mut r =
                    crate::telescope::cal::correct_chain_seen(cor, t.fit, &t.band, m, t.seen(i), self.zero_angle_deg)?;
                let c = &mut r.corrected;
                if let (Some(_), Tracks::Exposures(e)) = (cor, &t.tracks) {
                    // Exposures that each saw another telescope matrix behind the same field:
                    // undoing the field and then the telescope is exact for one matrix only
                    // (1e-5 off over a set spanning 60 deg of parallactic angle). The value is
                    // the exact inverse of the whole chain over the set; the covariance, a
                    // linearization, is the one of the two steps.
                    let chain =
                        e.whole.get_or_init(|| field::InstrumentChain { zero_angle: e.plate, ..self.instrument(i).0 });
                    // The measurement as the plate gave it, whatever frame it came in.
                    let at_plate = m.frame.at_plate(&m.qu);
                    let exact = chain
                        .invert_exposures(m.x, m.y, &at_plate, &e.list)
                        .map_err(|err| crate::Error::Input(format!("the chain over the exposures: {err}")))?;
                    let (p0, sigma_p0, chi0, sigma_chi0) =
                        crate::correction::correct::p_chi_with_errors(exact.q, exact.u, c.var_q0, c.var_u0, c.cov_qu0);
                    (c.q0, c.u0, c.p0, c.sigma_p0, c.chi0, c.sigma_chi0) =
                        (exact.q, exact.u, p0, sigma_p0, chi0, sigma_chi0);
                }
                Ok(r)
            }
            (None, FieldStep::None) => {
                Err(RowError::Chain(crate::Error::Input("the chain holds neither a field nor a telescope".into())))
            }
        }
    }

    /// Every valid bin of a Stokes map through [`invert`](Self::invert) at the bin's centre
    /// (the bins share their exposures), the scatter and the photon-noise errors each
    /// propagated ([`crate::correction::correct::correct_map_with`]).
    pub fn invert_map(&self, map: &skyfield::StokesMap) -> Result<CorrectedMap, MapError> {
        let pa = self.turn_onto_sky_deg(map.sky_pa_deg);
        crate::correction::correct::correct_map_with(map, |m| {
            self.invert(0, m).map(|c| c.turned(pa)).map_err(|e| match e {
                RowError::Field(e) => e,
                RowError::Chain(e) => crate::correction::correct::Error::Telescope(e.to_string()),
            })
        })
    }

    /// The same chain as a forward model for row `i`'s exposure (its track, or the shared
    /// one; a chain undone exposure by exposure gives the whole set's track): the telescope's
    /// band model, the field model or Mueller field as the one element, and the zero angle.
    /// The telescope's constant `q0, u0`, which a telescope model alone subtracts, is not an
    /// element of it.
    pub fn instrument(&self, i: usize) -> (field::InstrumentChain, Option<Track>) {
        let mut elements = field::FieldChain::new();
        match &self.field {
            FieldStep::PartialPolarizer { calibration, .. } => {
                elements = elements.then(Arc::new((*calibration).clone()), "the field calibration's M_I(p, phi)")
            }
            FieldStep::Mueller(mc, _) => elements = elements.then(Arc::new(mc.field.clone()), "the Mueller field"),
            FieldStep::Response(r) => {
                elements = elements.then(Arc::new(r.response), "the constant response from standards")
            }
            FieldStep::None => {}
        }
        let (telescope, track) = match &self.telescope {
            None => (None, None),
            Some(t) => {
                let track = match t.seen(i) {
                    Seen::Track(tr) => tr,
                    Seen::Prepared(p) => p.whole(),
                    Seen::Exposures { whole, .. } => whole,
                };
                (t.fit.band(&t.band).copied(), Some(track))
            }
        };
        // The forward model ends at the plate: its zero angle is the one the models' sky frame
        // has (0 for a telescope model alone, which takes data in their own frame).
        let zero_angle = self.zero_angle_deg.unwrap_or(0.0).to_radians();
        (field::InstrumentChain { telescope, elements, zero_angle }, track)
    }
}
