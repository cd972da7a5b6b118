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
