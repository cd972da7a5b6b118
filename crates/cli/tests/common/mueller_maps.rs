//! Stokes maps of sky fields seen through a given Mueller field (a closure), for the tests of
//! the Mueller-field smooth forms and of explain / plan reading the calibration file, and of
//! calibrate-mueller itself (each test binary uses a part of it).
#![allow(dead_code)]

use mueller::linear::LinearBlock;
use skyfield::maps::{BinGeometry, StokesMap};
use std::path::{Path, PathBuf};

/// A noiseless FORS1 B map (128 px bins, errors `sigma` per bin) of a sky of `p`, `chi_deg`
/// seen through `truth`.
pub fn map(
    dir: &Path,
    name: &str,
    p: f64,
    chi_deg: f64,
    sigma: f64,
    truth: &dyn Fn(f64, f64) -> LinearBlock,
) -> PathBuf {
    map_binned(dir, name, p, chi_deg, sigma, truth, 128)
}

/// [`map`] with bins of `bin_px` detector pixels.
pub fn map_binned(
    dir: &Path,
    name: &str,
    p: f64,
    chi_deg: f64,
    sigma: f64,
    truth: &dyn Fn(f64, f64) -> LinearBlock,
    bin_px: usize,
) -> PathBuf {
    let g = BinGeometry::covering(bin_px, 0, 0, 2048, 2048, 0.2);
    let mut m = StokesMap::empty(g.clone(), "fors1", "B", vec![0.0, 22.5, 45.0, 67.5]);
    let c = 2.0 * chi_deg.to_radians();
    for j in 0..g.ny {
        for i in 0..g.nx {
            let k = j * g.nx + i;
            let (x, y) = g.centre_arcmin(i, j);
            let (q, u) = truth(x, y).forward(p * c.cos(), p * c.sin()).unwrap();
            (m.q[k], m.u[k]) = (q, u);
            (m.sigma_q[k], m.sigma_u[k], m.cov_qu[k]) = (sigma, sigma, 0.0);
            (m.sigma_q_phot[k], m.sigma_u_phot[k]) = (sigma, sigma);
            (m.p[k], m.chi[k]) = stokes::polarization(q, u);
            (m.n_pixels[k], m.intensity[k], m.intensity_snr[k]) = ((bin_px * bin_px) as u32, 1000.0, 100.0);
            m.valid[k] = true;
        }
    }
    let path = dir.join(name);
    m.write_fits(&path).unwrap();
    path
}

/// The three skies of the Mueller tests: `(file, P percent, chi deg)`.
pub const SKIES: [(&str, f64, f64); 3] = [("b1.fits", 6.45, 68.4), ("b2.fits", 4.0, 10.0), ("b3.fits", 8.0, 130.0)];

/// The three sky maps through `truth` and the `--field` arguments naming them.
pub fn sky_args(dir: &Path, sigma: f64, truth: &dyn Fn(f64, f64) -> LinearBlock) -> Vec<String> {
    let mut v = vec![];
    for (name, p, chi) in SKIES {
        let m = map(dir, name, p / 100.0, chi, sigma, truth);
        v.extend(["--field".to_string(), format!("{}:{p}:{chi}", m.display())]);
    }
    v
}
