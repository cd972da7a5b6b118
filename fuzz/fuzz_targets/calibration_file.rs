//! The calibration-file reader `fit::Calibration::load` (CFITSIO through fitsio: primary
//! header keywords, the QMAP/UMAP/QERR/UERR images and their WCS, the BINS and INPUTS tables,
//! the residual interpolant rebuilt from the bins), then what `correct` and `plot` do with a
//! loaded calibration: evaluate it and test coverage at a few positions, the centre in
//! pixels, and the grid that `plot` draws (same step rule as crates/cli/src/plot.rs).
#![no_main]
use fit::FieldModel;
use libfuzzer_sys::fuzz_target;

fuzz_target!(
    init: {
        instpol_fuzz::seed_mode(instpol_fuzz::write_calibration_seeds);
    },
    |data: &[u8]| {
        let p = instpol_fuzz::write_input("cal.fits", data);
        let Ok(cal) = fit::Calibration::load(&p) else { return };
        let c = cal.centre_arcmin();
        for (x, y) in [(0.0, 0.0), (c[0], c[1]), (2.0, -1.5), (1e3, 1e3), (1e300, -1e300), (1e-310, 3e-300), (f64::NAN, 0.0), (0.0, f64::INFINITY)] {
            let _ = cal.eval(x, y);
            let _ = cal.contains(x, y);
        }
        let _ = cal.centre_px();
        let r = &cal.region;
        let h = 0.5 * (r.x_max - r.x_min).max(r.y_max - r.y_min) * 1.04;
        if !matches!(cal.model, fit::Model::Map(_)) {
            let _ = cal.gridded((2.0 * h / 120.0).max(0.02));
        }
    }
);
