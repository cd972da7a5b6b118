//! The plate and the analyser at the end of the chain: the wave plate with its defects and its
//! motion during an exposure, the Wollaston prism and the post-analyser optics, giving the two
//! beams' fluxes of the light that reaches the plate (`eq:WP`).

use mueller::{BeamFluxes, CompiledDualBeam, DualBeam, Stokes};

/// How the plate moves during an exposure about its commanded (middle) angle.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum PlateMotion {
    /// The plate stands still.
    Fixed,
    /// The plate turns uniformly through `sweep` (rad): its matrix averaged over the motion
    /// (`mueller::Hwp::matrix_swept`).
    Swept { sweep: f64 },
    /// The same motion as the mean of the fixed plate's fluxes at `n` sub-steps, each the
    /// middle of its `sweep / n`.
    Substeps { sweep: f64, n: u32 },
}

/// The plate and the analyser: the wave plate with its retardance, zero angle and defects,
/// its motion during an exposure, the Wollaston prism and the post-analyser optics
/// (`mueller::DualBeam` without elements before the plate: the chain's elements are those).
#[derive(Clone, Debug)]
pub struct Analyser {
    train: CompiledDualBeam,
    motion: PlateMotion,
    zero_angle: f64,
}

impl Analyser {
    /// The analyser of `beam` (its `pre` elements must be empty: they belong to the chain's
    /// [`crate::FieldChain`]) with the plate moving as `motion`.
    pub fn new(beam: &DualBeam, motion: PlateMotion) -> Self {
        Self { train: beam.compile(), motion, zero_angle: beam.hwp.chi_offset }
    }

    /// The plate's zero angle (its `chi_offset`, rad).
    pub fn zero_angle(&self) -> f64 {
        self.zero_angle
    }

    /// The fluxes of the Stokes vector `s` at the plate in the exposure at commanded (middle)
    /// plate angle `theta` (rad).
    pub fn fluxes_at_plate(&self, s: &Stokes, theta: f64) -> BeamFluxes {
        match self.motion {
            PlateMotion::Fixed => self.train.fluxes_at_plate(s, theta),
            PlateMotion::Swept { sweep } => self.train.fluxes_at_plate_swept(s, theta, sweep),
            PlateMotion::Substeps { sweep, n } => {
                let (d, nf) = (sweep, n as f64);
                let (mut fo, mut fe) = (0.0, 0.0);
                for j in 0..n {
                    let f = self.train.fluxes_at_plate(s, theta - 0.5 * d + (j as f64 + 0.5) * d / nf);
                    fo += f.f_o;
                    fe += f.f_e;
                }
                BeamFluxes { f_o: fo / nf, f_e: fe / nf }
            }
        }
    }
}
