//! The reader of other tools' Q/U maps (`fit::files::import::import_map`, `instpol import-map`: two
//! `(2, NY, NX)` FITS cubes, value and error planes), with the input as both the Q and the U
//! cube, then the imported calibration evaluated and tested for coverage at a few positions.
#![no_main]
use fit::FieldModel;
use libfuzzer_sys::fuzz_target;

fuzz_target!(
    init: {
        instpol_fuzz::seed_mode(instpol_fuzz::write_map_seeds);
    },
    |data: &[u8]| {
        let p = instpol_fuzz::write_input("cube.fits", data);
        let opts = fit::files::import::ImportOptions {
            pixel_scale_arcsec: 0.25,
            bin: 32,
            instrument: "FORS2".into(),
            filter: "V".into(),
            lambda_nm: 554.0,
            origin_px: None,
        };
        let Ok(cal) = fit::files::import::import_map(&p, &p, &opts) else { return };
        for (x, y) in [(0.0, 0.0), (0.3, -0.2), (1e3, 1e3), (f64::NAN, 0.0)] {
            let _ = cal.eval(x, y);
            let _ = cal.contains(x, y);
        }
    }
);
