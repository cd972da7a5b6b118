//! The instrument's position angle on the sky for a set of frames, as its instrument file's
//! `[polarimetry.sky_angle]` says to read it (`instrument::SkyAngle`): a header keyword with its
//! sense and offset, or each frame's celestial WCS. A catalog of such an instrument gives its
//! rows' `q, u, chi` in the celestial frame, north through east (`mueller::Frame::Celestial`).
//!
//! One set, one angle: the exposures of a set are demodulated together, and an instrument that
//! turned against the sky between them saw another mix of the sky's `Q` and `U` in each, which
//! no single turn afterwards undoes. A set whose exposures' angles differ by more than
//! [`SAME_SET_TOLERANCE_DEG`] is refused, naming the two files and their angles: reduce each
//! rotator angle's exposures as a set of its own.

use crate::Error;
use instrument::{Instrument, SkyAngle};
use std::path::Path;

/// How far (deg) the position angles of one set's exposures may spread: a rotator that
/// tracks the sky holds its angle to the header's last digit (MOPTOP's ROTSKYPA is written to
/// 0.1 deg), and a spread of 0.1 deg turns `chi` by at most that, below the angle error of a
/// well-measured standard (0.3 deg for `P` = 5 % at `sigma_P` = 0.05 %).
pub const SAME_SET_TOLERANCE_DEG: f64 = 0.1;

/// The instrument's position angle on the sky (deg, north through east) of the frame file
/// `path`, as `a` says to read it. Errors name the file and the keyword or the WCS at fault.
pub fn of_file(path: &Path, a: &SkyAngle) -> Result<f64, Error> {
    let value = if a.from_wcs {
        let bad = |why: String| Error::Fits {
            path: path.into(),
            message: format!("the instrument's position angle on the sky (sky_angle from_wcs): {why}"),
        };
        let (wcs, _) =
            crate::wcs::celestial_wcs_in(path).map_err(&bad)?.ok_or_else(|| bad("no celestial WCS".into()))?;
        wcs.y_axis_position_angle_deg().map_err(bad)?
    } else {
        let mut img = crate::fits::open_image(path, "")?;
        img.number(path, &a.keyword, "a position angle in degrees")?
            .filter(|v| v.is_finite())
            .ok_or_else(|| Error::MissingKeyword { path: path.into(), keyword: a.keyword.clone() })?
    };
    Ok(a.position_angle_deg(value))
}

/// The position angle on the sky (deg) of the set of exposures whose first files are
/// `files`, when the instrument says where to read it (`None` otherwise): their circular mean,
/// after checking that they agree within [`SAME_SET_TOLERANCE_DEG`] (module docs).
pub fn of_set(files: &[&Path], inst: &Instrument) -> Result<Option<f64>, Error> {
    let Some(a) = &inst.polarimetry.sky_angle else { return Ok(None) };
    let angles: Vec<f64> = files.iter().map(|p| of_file(p, a)).collect::<Result<_, _>>()?;
    let Some(&first) = angles.first() else { return Ok(None) };
    let turn = stokes::stats::circular::Period::Turn;
    for (path, &pa) in files.iter().zip(&angles) {
        let d = stokes::stats::circular::difference(pa.to_radians(), first.to_radians(), turn).to_degrees();
        if d.abs() > SAME_SET_TOLERANCE_DEG {
            return Err(Error::Invalid(format!(
                "the instrument turned against the sky within one set: {} has position angle {pa:.3} deg, {} has \
                 {first:.3} deg (more than {SAME_SET_TOLERANCE_DEG} deg apart): the exposures of a set are \
                 demodulated together, so give each rotator angle's exposures as a set of their own",
                path.display(),
                files[0].display()
            )));
        }
    }
    let radians: Vec<f64> = angles.iter().map(|a| a.to_radians()).collect();
    Ok(stokes::stats::circular::mean(&radians, turn).map(|m| m.to_degrees()))
}
