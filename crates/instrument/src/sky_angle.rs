//! `[polarimetry.sky_angle]`: where the instrument's position angle on the sky is read, so that
//! polarization angles can be given in the sky's frame (north through east) on an instrument
//! that a rotator turns against the sky.
//!
//! The instrument measures `chi` from its own reference direction (the plate's zero, with the
//! filter's HWP zero angle added). On a rotator that direction points elsewhere on the sky in
//! every set, so the angle on the sky is `chi_sky = chi_instrument + PA`, where `PA` is the
//! position angle on the sky (north through east) of the instrument's reference direction:
//!
//! - from a header keyword: `PA = sense * value + offset_deg` (`keyword = "ROTSKYPA"`);
//! - from each frame's celestial WCS (`from_wcs = true`): `PA = pa_y + offset_deg`, with
//!   `pa_y` the position angle of the detector's +y axis that the WCS gives.
//!
//! The frames of one set must share their angle: their Stokes parameters are demodulated
//! together, and a set whose instrument turned against the sky between exposures mixes `Q` and
//! `U` in a way the demodulation cannot undo (`skyfield::sky_angle` refuses it).

use serde::{Deserialize, Serialize};

/// The `[polarimetry.sky_angle]` table.
///
/// ```
/// let a = instrument::SkyAngle { keyword: "ROTSKYPA".into(), from_wcs: false, sense: -1, offset_deg: 90.0 };
/// assert_eq!(a.position_angle_deg(30.0), 60.0);
/// assert_eq!(a.header_value_deg(60.0), 30.0);
/// ```
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SkyAngle {
    /// The header keyword (deg) of the instrument's position angle on the sky; empty with
    /// `from_wcs`.
    #[serde(default)]
    pub keyword: String,
    /// Read the angle from each frame's celestial WCS (the +y axis's position angle) instead.
    #[serde(default)]
    pub from_wcs: bool,
    /// `+1`: the keyword's angle counts north through east; `-1`: the other way. Must be `+1`
    /// with `from_wcs` (a WCS's angles count north through east).
    #[serde(default = "plus_one")]
    pub sense: i32,
    /// Added (deg) after the sense: the position angle of the instrument's reference direction
    /// when the keyword (or the WCS's +y axis) reads 0.
    #[serde(default)]
    pub offset_deg: f64,
}

fn plus_one() -> i32 {
    1
}

impl SkyAngle {
    /// The instrument's position angle on the sky (deg, north through east) from the header's
    /// value (or the WCS's +y axis position angle) `value_deg`.
    pub fn position_angle_deg(&self, value_deg: f64) -> f64 {
        self.sense as f64 * value_deg + self.offset_deg
    }

    /// The header value (deg) that says the position angle `pa_deg`: the inverse of
    /// [`SkyAngle::position_angle_deg`] (what a simulator writes).
    pub fn header_value_deg(&self, pa_deg: f64) -> f64 {
        self.sense as f64 * (pa_deg - self.offset_deg)
    }

    /// The file's checks: one source of the angle, a sense of +-1, a finite offset;
    /// `Err((key, value, why))`.
    pub(crate) fn check(&self) -> Result<(), (String, String, String)> {
        let key = |k: &str| format!("polarimetry.sky_angle.{k}");
        if self.keyword.trim().is_empty() != self.from_wcs {
            return Err((
                key("keyword/from_wcs"),
                format!("'{}' / {}", self.keyword, self.from_wcs),
                "give either keyword (the header keyword of the position angle) or from_wcs = true (each frame's \
                 WCS), not both and not neither"
                    .into(),
            ));
        }
        if self.sense != 1 && self.sense != -1 {
            return Err((key("sense"), self.sense.to_string(), "must be 1 or -1".into()));
        }
        if self.from_wcs && self.sense != 1 {
            return Err((
                key("sense"),
                self.sense.to_string(),
                "a WCS's position angle counts north through east: from_wcs takes sense = 1".into(),
            ));
        }
        if !self.offset_deg.is_finite() {
            return Err((key("offset_deg"), self.offset_deg.to_string(), "must be a finite angle in degrees".into()));
        }
        Ok(())
    }
}
