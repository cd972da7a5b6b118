//! What several of the simulator's tests share.

/// A Nasmyth M3 (aluminium at 45 deg) at Paranal's latitude.
const NASMYTH: &str = "[telescope]\nfocus = \"nasmyth\"\nsite_latitude_deg = -24.63\n\n[[telescope.mirrors]]\nname = \"M3\"\nmetal = \"aluminium\"\naoi_deg = 45.0\n";

/// An instrument file's text with its `[telescope]` sections replaced by a Nasmyth M3.
pub fn with_nasmyth_m3(text: &str) -> String {
    let mut out = String::new();
    let mut skip = false;
    for line in text.lines() {
        let t = line.trim_start();
        if t.starts_with('[') {
            skip = t.starts_with("[telescope") || t.starts_with("[[telescope");
        }
        if !skip {
            out += line;
            out += "\n";
        }
    }
    out + NASMYTH
}

/// FORS1's instrument file on a coarse detector: its 6.8' field on 256 x 256 px of 1.6" (the
/// whole field in few pixels), the strips' throw and first row to match.
pub fn coarse_fors1_text() -> String {
    let text = include_str!("../../../../instruments/fors1.toml")
        .replace("nx = 2048", "nx = 256")
        .replace("ny = 2048", "ny = 256")
        .replace("pixel_scale_arcsec = 0.2 ", "pixel_scale_arcsec = 1.6 ")
        .replace("throw_arcsec = 22.0", "throw_arcsec = 22.4")
        .replace("first_strip_y_px = 34", "first_strip_y_px = 4");
    assert!(text.contains("pixel_scale_arcsec = 1.6"), "the instrument file changed: adapt the test");
    text
}
