//! The two-camera instrument of the simulator's two-camera tests (`two_cameras.rs`,
//! `two_cameras_map.rs`): two 160 x 160 px cameras, 10 px apart in the detector frame, 8
//! overscan columns each, the e camera flipped in x with a gain 3 % above the o camera's.

/// The sky's point at o camera pixel (x, y) falls at (x + 1.7, y - 2.3) on the e camera once
/// that is flipped back in x.
pub const TRANSFORM: &str = "[1.0, 0.0, 1.7, 0.0, 1.0, -2.3]";

/// The instrument file's text, with `plate` the plate's lines of `[polarimetry]` (its angle
/// keyword, or a turning rotor) and `cameras` the lines of `[polarimetry.cameras]` after the
/// chips and the flip (a transform, a bound on the measured one's residual), each line ended.
pub fn instrument_text(plate: &str, cameras: &str) -> String {
    format!(
        r#"name = "TWOCAM"
[detector]
nx = 330
ny = 160
pixel_scale_arcsec = 0.44
gain_e_per_adu = 1.0
read_noise_e = 5.0
saturation_adu = 65535.0
[field]
width_arcmin = 2.42
height_arcmin = 1.17
[polarimetry]
layout = "two_cameras"
filter_keyword = "FILTER1"
exptime_keyword = "EXPTIME"
{plate}
[polarimetry.cameras]
o_chip = "CAM1"
e_chip = "CAM2"
e_orientation = "flip_x"
{cameras}[format]
exposure_keywords = ["MOPRUN"]
[[format.chips]]
name = "CAM1"
match_keyword = "CAMERA"
match_value = "1"
origin_px = [0, 0]
size_px = [160, 160]
overscan_x = 8
gain_e_per_adu = 1.0
[[format.chips]]
name = "CAM2"
match_keyword = "CAMERA"
match_value = "2"
origin_px = [170, 0]
size_px = [160, 160]
overscan_x = 8
gain_e_per_adu = 1.03
[[filters]]
name = "R"
lambda_eff_nm = 650.0
"#
    )
}
