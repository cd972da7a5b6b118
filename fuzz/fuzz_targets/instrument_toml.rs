//! `instrument::Instrument::from_toml_str`, then what every caller does with a loaded
//! instrument: the strip layout, pixel <-> arcmin both ways, each filter by name and alias.
#![no_main]
use libfuzzer_sys::fuzz_target;
use std::path::Path;

fuzz_target!(|data: &[u8]| {
    let Ok(text) = std::str::from_utf8(data) else { return };
    let Ok(inst) = instrument::Instrument::from_toml_str(text, Path::new("fuzz.toml")) else { return };
    let strips = inst.strips();
    let d = &inst.detector;
    let extent = if inst.polarimetry.strip_axis == "y" { d.ny } else { d.nx };
    for s in &strips {
        // A loaded layout lies on the detector (validate's promise, which BeamGeometry relies on).
        assert!(
            s.height >= 1 && s.o_start + s.height <= extent && s.e_start + s.height <= extent,
            "{s:?} off a detector of {extent} px"
        );
    }
    let _ = inst.throw_px();
    for (x, y) in [(0.0, 0.0), (d.nx as f64 - 1.0, d.ny as f64 - 1.0), (0.5 * d.nx as f64, -3.0)] {
        let (ax, ay) = inst.pixel_to_arcmin(x, y);
        let _ = inst.arcmin_to_pixel(ax, ay);
    }
    for f in &inst.filters {
        // Every filter the file lists must be found by its own name and aliases.
        inst.filter(&f.name).expect("a listed filter is found by name");
        for a in &f.aliases {
            inst.filter(a).expect("a listed alias is found");
        }
    }
});
