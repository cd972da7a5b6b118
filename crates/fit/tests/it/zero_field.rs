//! A field with no instrumental polarization at all (every bin exactly q = u = 0, the map a
//! perfect instrument gives): with a fixed centre the radial fit returns zero coefficients;
//! with a free centre it says that there is no pattern to centre, instead of "did not
//! converge".

use crate::common;

use common::*;
use fit::{fit_radial, RadialFitOptions};

#[test]
fn an_all_zero_map_fits_to_zero() {
    let mut bins = noisy_bins(&fors1_bin_centres(64), radial_field(&[0.0, 0.0, 0.0], (0.0, 0.0)), SIGMA_BIN, 3);
    for b in &mut bins {
        b.qu.q = 0.0;
        b.qu.u = 0.0;
    }
    let fit = fit_radial(&bins, &RadialFitOptions { free_centre: false, ..Default::default() }).unwrap();
    for c in &fit.model.coeffs {
        assert!(c.abs() < 1e-12, "{:?}", fit.model.coeffs);
    }
    let e = fit_radial(&bins, &RadialFitOptions { free_centre: true, ..Default::default() }).unwrap_err().to_string();
    assert!(e.contains("no radial pattern") && e.contains("fixed centre"), "{e}");
}
