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
//! A [`Chain`] holds the same chain as the one forward model ([`field::InstrumentChain`], built
//! once by [`Chain::new`]; [`Chain::chain`], [`Chain::instrument`]), the one the simulator
//! renders through, so that what a correction undoes can be checked against what a simulation
//! put in.

use crate::correction::correct::{CorrectOptions, Corrected, CorrectedMap, Corrector, MapError, Measurement};
use crate::files::calfile::Calibration;
use crate::files::elements::Element;
use crate::models::model::FieldModel;
use crate::mueller_field::cal::MuellerCal;
use crate::response::cal::ResponseCal;
use crate::telescope::cal::ChainCorrected;
use crate::telescope::{PreparedExposures, Seen, TelescopeFit, Track};
use std::sync::Arc;

/// The field elements of a file whose own model is its one field element.
static MODEL_ALONE: [Element; 1] = [Element::Model];

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
    /// The same chain as the one forward model, built once ([`Chain::new`]).
    one: field::InstrumentChain,
    /// The file's field elements in order when it holds several ([`Chain::with_elements`]);
    /// empty: the field step alone, inverted by its own path.
    order: &'a [Element],
}

impl<'a> FieldStep<'a> {
    /// The partial polarizer of `calibration` with `opts`.
    pub fn partial_polarizer(calibration: &'a Calibration, opts: CorrectOptions) -> Self {
        FieldStep::PartialPolarizer { corrector: Corrector::new(calibration, opts), calibration }
    }
}

impl<'a> Chain<'a> {
    /// The chain of `field` behind `telescope`, its models in the sky frame of
    /// `zero_angle_deg` ([`Chain::zero_angle_deg`]), with the one forward model it is
    /// ([`field::InstrumentChain`], [`chain`](Self::chain)) built once.
    pub fn new(zero_angle_deg: Option<f64>, field: FieldStep<'a>, telescope: Option<TelescopeStep<'a>>) -> Self {
        // A Mueller field behind a telescope has no inverse of its own there: the whole chain's.
        let order: &[Element] = match (&field, &telescope) {
            (FieldStep::Mueller(..), Some(_)) => &MODEL_ALONE,
            _ => &[],
        };
        let one = one_chain(zero_angle_deg, &field, telescope.as_ref(), order);
        Self { zero_angle_deg, field, telescope, one, order }
    }

    /// The file's field elements in order when it holds several
    /// ([`with_elements`](Self::with_elements)), else none.
    pub fn elements(&self) -> &[Element] {
        if self.order.len() > 1 {
            self.order
        } else {
            &[]
        }
    }

    /// This chain with the field elements of a file that holds several, in the order light
    /// meets them ([`crate::files::elements`]; the field step is the file's own model among
    /// them): every row and bin is then corrected by inverting the whole chain
    /// ([`field::InstrumentChain::invert`], or `invert_first_order` for `eq:approx`, or
    /// `invert_exposures` over recorded exposures). Itself for an empty order.
    pub fn with_elements(self, order: &'a [Element]) -> Self {
        if order.is_empty() {
            return self;
        }
        let one = one_chain(self.zero_angle_deg, &self.field, self.telescope.as_ref(), order);
        Self { one, order, ..self }
    }
}

/// The forward model of a correction's chain: the telescope's band model, the field model,
/// Mueller field or constant response as the one element, and the zero angle of the models'
/// sky frame (0 for a telescope model alone, which takes data in their own frame). The
/// telescope's constant `q0, u0`, which a telescope model alone subtracts, is not an element.
fn one_chain(
    zero_angle_deg: Option<f64>,
    field: &FieldStep,
    telescope: Option<&TelescopeStep>,
    order: &[Element],
) -> field::InstrumentChain {
    let own = own_element(field);
    let elements = if order.is_empty() {
        own.into_iter().fold(field::FieldChain::new(), |c, (e, what)| c.then(e, what))
    } else {
        elements_in_order(order, own)
    };
    let telescope = telescope.and_then(|t| t.fit.band(&t.band).copied());
    // The forward model ends at the plate: its zero angle is the one the models' sky frame has.
    let zero_angle = zero_angle_deg.unwrap_or(0.0).to_radians();
    field::InstrumentChain { telescope, elements, zero_angle, analyser: None }
}

/// The field step's own element as a chain element, with what it is; `None` without one.
fn own_element(field: &FieldStep) -> Option<(Arc<dyn field::FieldModel>, &'static str)> {
    match field {
        FieldStep::PartialPolarizer { calibration, .. } => {
            Some((Arc::new((*calibration).clone()), "the field calibration's M_I(p, phi)"))
        }
        FieldStep::Mueller(mc, _) => Some((Arc::new(mc.field.clone()), "the Mueller field")),
        FieldStep::Response(r) => Some((Arc::new(r.response), "the constant response from standards")),
        FieldStep::None => None,
    }
}

/// The chain of a file's field elements in `order`, the file's own model `own` at its place.
fn elements_in_order(order: &[Element], own: Option<(Arc<dyn field::FieldModel>, &str)>) -> field::FieldChain {
    order.iter().fold(field::FieldChain::new(), |c, e| match (e, &own) {
        (Element::Model, Some((m, what))) => c.then(m.clone(), *what),
        (Element::Model, None) => c,
        (Element::StressedLens(l), _) => c.then(Arc::new(*l), "a stressed lens"),
    })
}

impl Chain<'_> {
    /// The one forward model this correction inverts ([`field::InstrumentChain`]): what the
    /// simulator renders through, so that what a correction undoes can be checked against what
    /// a simulation put in.
    pub fn chain(&self) -> &field::InstrumentChain {
        &self.one
    }

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
        if !self.order.is_empty() {
            return self.invert_elements(i, m);
        }
        let alone = |corrected| ChainCorrected { corrected, q_tel: 0.0, u_tel: 0.0 };
        match (&self.telescope, &self.field) {
            (None, FieldStep::PartialPolarizer { corrector, .. }) => Ok(alone(corrector.correct(m)?)),
            (None, FieldStep::Mueller(mc, o)) => Ok(alone(mc.correct(m, o)?)),
            (None, FieldStep::Response(r)) => Ok(alone(r.correct(m)?)),
            (Some(t), field) => {
                let cor = match field {
                    FieldStep::PartialPolarizer { corrector, .. } => Some(corrector),
                    FieldStep::None => None,
                    FieldStep::Mueller(..) => return self.invert_elements(i, m),
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
                        e.whole.get_or_init(|| field::InstrumentChain { zero_angle: e.plate, ..self.one.clone() });
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

    /// Row `i` through the whole chain of a file's several field elements
    /// ([`with_elements`](Self::with_elements)): the measurement turned into the models' sky
    /// frame, then the chain inverted at its position, exactly or to first order as the
    /// options say (over recorded exposures: the whole chain's exact inverse from the plate).
    /// The file's own model enters as its value here: a field calibration's `M_I` with the
    /// model's covariance (inflated outside the field, [`Corrector::instrumental`]), carried
    /// through the chain's Jacobians; a Mueller field or a constant response as its matrix.
    /// `inst` is the field elements' polarization of unpolarized light, `q_tel, u_tel` the
    /// telescope's over the row's track.
    fn invert_elements(&self, i: usize, m: &Measurement) -> Result<ChainCorrected, RowError> {
        use crate::correction::correct::{Error as E, Method};
        crate::correction::correct::check_measurement(m)?;
        let (x, y) = (m.x, m.y);
        let (own, opts, extrapolated) = match &self.field {
            FieldStep::PartialPolarizer { corrector, .. } => {
                let (a, ex) = corrector.instrumental(x, y)?;
                let own: Arc<dyn field::FieldModel> = Arc::new(field::PartialPolarizer(a));
                (Some((own, "the field calibration's M_I(p, phi)")), *corrector.options(), ex)
            }
            FieldStep::Mueller(mc, o) => {
                let inside = field::FieldModel::contains(&mc.field, x, y);
                if !inside && !o.allow_extrapolation {
                    return Err(E::OutsideField { x, y }.into());
                }
                (own_element(&self.field), *o, !inside)
            }
            FieldStep::Response(r) => {
                let o = CorrectOptions { zero_angle_deg: r.hwp_chi_offset_deg, ..CorrectOptions::default() };
                (own_element(&self.field), o, false)
            }
            FieldStep::None => {
                return Err(E::Chain("the file's field elements have no model of their own".into()).into())
            }
        };
        let chain = field::InstrumentChain {
            telescope: self.one.telescope,
            elements: elements_in_order(self.order, own),
            zero_angle: 0.0,
            analyser: None,
        };
        let at = m.in_sky(opts.zero_angle_deg).qu;
        let track = self.instrument(i).1;
        let chain_err = |e: field::ChainError| RowError::Field(E::Chain(e.to_string()));
        let mut sky = match (self.telescope.as_ref().map(|t| &t.tracks), opts.method) {
            (Some(Tracks::Exposures(e)), _) => field::InstrumentChain { zero_angle: e.plate, ..chain.clone() }
                .invert_exposures(x, y, &m.frame.at_plate(&m.qu), &e.list),
            (_, Method::Exact) => chain.invert(x, y, &at, track),
            (_, Method::FirstOrder) => chain.invert_first_order(x, y, &at, track),
        }
        .map_err(chain_err)?;
        if extrapolated && matches!(self.field, FieldStep::Mueller(..)) {
            // The Mueller form of the `(F p)^2` rule, as a Mueller field alone is corrected.
            let f = opts.extrapolation_rel_error;
            let add = f * f * ((sky.q - at.q).powi(2) + (sky.u - at.u).powi(2));
            (sky.var_q, sky.var_u) = (sky.var_q + add, sky.var_u + add);
        }
        let inst = field::InstrumentChain { telescope: None, ..chain.clone() }
            .forward(x, y, &mueller::Qu::ZERO, None)
            .map_err(chain_err)?;
        let (q_tel, u_tel) = match (&chain.telescope, track) {
            (Some(t), Some(tr)) => {
                let mt = field::chain::telescope_matrix(t, tr).map_err(|e| chain_err(e.into()))?;
                (mt[(1, 0)], mt[(2, 0)])
            }
            _ => (0.0, 0.0),
        };
        Ok(ChainCorrected { corrected: Corrected::of(sky, inst, extrapolated), q_tel, u_tel })
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

    /// The same chain as a forward model ([`chain`](Self::chain)) with row `i`'s exposure: its
    /// track, or the shared one (a chain undone exposure by exposure gives the whole set's
    /// track); `None` without a telescope.
    pub fn instrument(&self, i: usize) -> (field::InstrumentChain, Option<Track>) {
        let track = self.telescope.as_ref().map(|t| match t.seen(i) {
            Seen::Track(tr) => tr,
            Seen::Prepared(p) => p.whole(),
            Seen::Exposures { whole, .. } => whole,
        });
        (self.one.clone(), track)
    }
}
