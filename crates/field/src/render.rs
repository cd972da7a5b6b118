//! The chain's forward model to the detector: through the plate and the analyser to the two
//! beams' fluxes, the form in which the simulator renders every frame.
//!
//! [`InstrumentChain::fluxes`] is the whole forward model of one exposure at one field
//! position: the sky's Stokes vector through the telescope's matrix over the exposure's track,
//! the field's elements at the position, and the [`Analyser`] (the plate with its defects and
//! its motion during the exposure, the Wollaston prism, the post-analyser optics) to
//! `f_O`, `f_E` (`eq:WP`). It is composed of three pieces, which a renderer computes once
//! each and keeps, so that a frame of millions of pixels costs one small product per pixel:
//!
//! - [`InstrumentChain::exposure_forward`], what changes from one exposure to the next (the
//!   telescope's matrix, the plate's angle): one [`ExposureForward`] per exposure;
//! - [`InstrumentChain::before_exposures`], what is the same in every exposure: without a
//!   telescope the field's elements, applied once to the source at its position;
//! - [`InstrumentChain::field_block_at`], the field's elements kept per position as one block
//!   when they act after a telescope (whose matrix changes from exposure to exposure, so
//!   that they cannot be applied once before them: [`InstrumentChain::elements_per_exposure`]).
//!
//! [`ExposureForward::fluxes`] puts them together; the renderer only places the fluxes.

use crate::analyser::Analyser;
use crate::chain::{telescope_matrix, ChainError, InstrumentChain};
use mueller::telescope::Exposure;
use mueller::{BeamFluxes, Mueller, Stokes};

/// Stokes `(I, Q, U)` (no circular polarization).
pub type Iqu = [f64; 3];

/// A telescope's Mueller matrix as a render keeps it: rows `I, Q, U, V`, columns `I, Q, U` (the
/// sky has no circular polarization behind a telescope; M3 makes some, which a retarder after it
/// turns back into linear polarization, so it is carried to the field's elements).
type TelBlock = [[f64; 3]; 4];

/// The field's elements at one position behind a telescope: rows `I, Q, U` of their Mueller
/// matrix (the analyser's rows are taken on `I, Q, U`), columns `I, Q, U, V`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct FieldBlock([[f64; 4]; 3]);

/// One exposure of the chain, compiled: the telescope's matrix over the exposure's track and
/// the analyser's rows at its plate angle (the fluxes of `I`, `Q`, `U` and `V` at the plate;
/// the model is linear).
#[derive(Clone, Debug)]
pub struct ExposureForward {
    telescope: Option<TelBlock>,
    o: Iqu,
    e: Iqu,
    v: (f64, f64),
}

impl ExposureForward {
    /// `(f_O, f_E)` of a source whose light, after [`InstrumentChain::before_exposures`], is
    /// `s` with circular polarization `v` (0: none), with the field's elements `field` at its
    /// position when they act after the telescope ([`InstrumentChain::field_block_at`]).
    /// Behind a telescope `v` is not carried (the simulator refuses a circularly polarized
    /// source behind one) and the light's `V` after the elements not analysed.
    #[inline]
    pub fn fluxes(&self, s: &Iqu, v: f64, field: Option<&FieldBlock>) -> (f64, f64) {
        let st = match &self.telescope {
            Some(t) => through(t, field, s),
            None => *s,
        };
        let dot = |r: &Iqu, rv: f64| {
            let f = r[0] * st[0] + r[1] * st[1] + r[2] * st[2];
            if v != 0.0 {
                f + rv * v
            } else {
                f
            }
        };
        (dot(&self.o, self.v.0), dot(&self.e, self.v.1))
    }

    /// The `(q, u)` the exposure's telescope gives unpolarized light; `None` without one.
    pub fn telescope_qu(&self) -> Option<[f64; 2]> {
        self.telescope.map(|t| [t[1][0], t[2][0]])
    }
}

/// The light after a telescope block and, when there is one, the field's block.
#[inline]
fn through(t: &TelBlock, f: Option<&FieldBlock>, s: &Iqu) -> Iqu {
    let v: [f64; 4] = std::array::from_fn(|i| t[i][0] * s[0] + t[i][1] * s[1] + t[i][2] * s[2]);
    match f {
        Some(FieldBlock(b)) => {
            std::array::from_fn(|i| b[i][0] * v[0] + b[i][1] * v[1] + b[i][2] * v[2] + b[i][3] * v[3])
        }
        None => [v[0], v[1], v[2]],
    }
}

impl InstrumentChain {
    /// The chain with `analyser` after its elements; its zero angle becomes the plate's.
    pub fn with_analyser(self, analyser: Analyser) -> Self {
        Self { zero_angle: analyser.zero_angle(), analyser: Some(analyser), ..self }
    }

    /// Whether the field's elements act after a telescope, so that they are kept per position
    /// ([`field_block_at`](Self::field_block_at)) instead of applied once
    /// ([`before_exposures`](Self::before_exposures)).
    pub fn elements_per_exposure(&self) -> bool {
        self.telescope.is_some() && !self.elements.is_empty()
    }

    /// The exposure `e` compiled ([`ExposureForward`]): the telescope's matrix over its track
    /// (divided by its `M_00`, [`telescope_matrix`]) and the analyser's rows at its plate angle.
    /// A chain without an analyser (one that starts from demodulated `(q, u)`) has none.
    pub fn exposure_forward(&self, e: &Exposure) -> Result<ExposureForward, ChainError> {
        let a = self.analyser.as_ref().ok_or(ChainError::NoAnalyser)?;
        let telescope = match &self.telescope {
            Some(t) => {
                let m = telescope_matrix(t, e.track)?;
                Some(std::array::from_fn(|i| std::array::from_fn(|j| m[(i, j)])))
            }
            None => None,
        };
        let basis = [Stokes::new(1.0, 0.0, 0.0, 0.0), Stokes::new(0.0, 1.0, 0.0, 0.0), Stokes::new(0.0, 0.0, 1.0, 0.0)];
        let (mut o, mut ex) = ([0.0; 3], [0.0; 3]);
        for (k, b) in basis.iter().enumerate() {
            let f = a.fluxes_at_plate(b, e.hwp);
            o[k] = f.f_o;
            ex[k] = f.f_e;
        }
        let f = a.fluxes_at_plate(&Stokes::new(0.0, 0.0, 0.0, 1.0), e.hwp);
        Ok(ExposureForward { telescope, o, e: ex, v: (f.f_o, f.f_e) })
    }

    /// The part of the forward model the same in every exposure, applied to the source `s`
    /// (`I, Q, U, V`) at `(x, y)` arcmin: without a telescope the field's elements (each
    /// element's linear block in turn, or, for a source with circular polarization, their
    /// Mueller matrices); behind a telescope nothing (the elements act after each exposure's
    /// telescope matrix: [`field_block_at`](Self::field_block_at)).
    pub fn before_exposures(&self, x: f64, y: f64, s: Stokes) -> Stokes {
        if self.telescope.is_some() || self.elements.is_empty() {
            return s;
        }
        if s[3] != 0.0 {
            return self.elements.mueller_at(x, y) * s;
        }
        let o = self.elements.apply_at(x, y, [s[0], s[1], s[2]]);
        Stokes::new(o[0], o[1], o[2], 0.0)
    }

    /// The field's elements at `(x, y)` arcmin as one block (the product of their Mueller
    /// matrices), for a chain whose elements act after a telescope
    /// ([`elements_per_exposure`](Self::elements_per_exposure)).
    pub fn field_block_at(&self, x: f64, y: f64) -> FieldBlock {
        let m: Mueller = self.elements.mueller_at(x, y);
        FieldBlock(std::array::from_fn(|i| std::array::from_fn(|j| m[(i, j)])))
    }

    /// The whole forward model of exposure `e` at `(x, y)` arcmin: `(f_O, f_E)` of the sky's
    /// Stokes vector `s` (`I, Q, U, V`), through the telescope, the elements, the plate and the
    /// analyser. A renderer keeps the three pieces this is made of (module docs).
    pub fn fluxes(&self, x: f64, y: f64, e: &Exposure, s: Stokes) -> Result<BeamFluxes, ChainError> {
        let fwd = self.exposure_forward(e)?;
        let at = self.before_exposures(x, y, s);
        let field = self.elements_per_exposure().then(|| self.field_block_at(x, y));
        let (f_o, f_e) = fwd.fluxes(&[at[0], at[1], at[2]], at[3], field.as_ref());
        Ok(BeamFluxes { f_o, f_e })
    }
}
