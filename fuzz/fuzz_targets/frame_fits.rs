//! The frame reader `skyfield::io::read_frame` (CFITSIO through fitsio) with the 64 x 64
//! instrument: shape, pixel type, scaling, HWP-angle/filter/exposure keywords, then the
//! frame's pixel count against its header.
#![no_main]
use libfuzzer_sys::fuzz_target;

fuzz_target!(
    init: {
        instpol_fuzz::seed_mode(instpol_fuzz::write_frame_seeds);
    },
    |data: &[u8]| {
        let inst = instpol_fuzz::mini();
        let p = instpol_fuzz::write_input("frame.fits", data);
        if let Ok(f) = skyfield::io::read_frame(&p, inst) {
            assert_eq!(f.data.len(), f.nx * f.ny, "{}: pixels against header", p.display());
            assert!(f.hwp_deg.is_finite());
        }
    }
);
