//! A pixel's sky position through a gnomonic (TAN) WCS against the projection's closed forms
//! (Calabretta & Greisen 2002, A&A 395, 1077, sec. 5.1.3): a point due north of the tangent
//! point at projected distance `eta` lies at Dec `dec0 + atan(eta)`; one due east on the equator
//! at RA `ra0 + atan(xi)`; the pole of a field centred on it is reached; the axes given in the
//! other order give the same sky; other projections give no position.

use skyfield::wcs::CelestialWcs;

fn wcs(ctype: [&str; 2], crval: [f64; 2], cd: [[f64; 2]; 2]) -> CelestialWcs {
    CelestialWcs {
        ctype: [ctype[0].into(), ctype[1].into()],
        crpix: [101.0, 51.0],
        crval,
        cd,
        radesys: None,
        equinox: None,
    }
}

#[test]
fn tan_positions_follow_the_closed_forms() {
    let s = 1e-3; // deg per px: 0.1 deg from the tangent point at 100 px
    let north = wcs(["RA---TAN", "DEC--TAN"], [30.0, 40.0], [[-s, 0.0], [0.0, s]]);
    // CRPIX is 1-based: 0-based (100, 50) is the tangent point.
    for k in [-400.0, -100.0, 0.0, 37.5, 250.0] {
        let (ra, dec) = north.sky_of_pixel(100.0, 50.0 + k).unwrap();
        let want = 40.0 + (k * s).to_radians().atan().to_degrees();
        assert!((ra - 30.0).abs() < 1e-9 && (dec - want).abs() < 1e-11, "k {k}: ({ra}, {dec}) vs {want}");
    }
    let equator = wcs(["RA---TAN", "DEC--TAN"], [10.0, 0.0], [[-s, 0.0], [0.0, s]]);
    for k in [-300.0, -20.0, 80.0, 400.0] {
        // East (RA growing) is to the left: x decreasing.
        let (ra, dec) = equator.sky_of_pixel(100.0 - k, 50.0).unwrap();
        let want = (10.0 + (k * s).to_radians().atan().to_degrees()).rem_euclid(360.0);
        assert!((ra - want).abs() < 1e-11 && dec.abs() < 1e-11, "k {k}: ({ra}, {dec}) vs {want}");
    }
    // RA wraps into [0, 360).
    let near_zero = wcs(["RA---TAN", "DEC--TAN"], [0.05, 0.0], [[-s, 0.0], [0.0, s]]);
    let (ra, _) = near_zero.sky_of_pixel(200.0, 50.0).unwrap();
    assert!((ra - (360.0 + 0.05 - (0.1f64).to_radians().atan().to_degrees())).abs() < 1e-11, "{ra}");
    // A field 0.1 deg below the pole reaches it 100 px north.
    let pole = wcs(["RA---TAN", "DEC--TAN"], [120.0, 89.9], [[-s, 0.0], [0.0, s]]);
    let (_, dec) = pole.sky_of_pixel(100.0, 150.0).unwrap();
    assert!((dec - (89.9 + (0.1f64).to_radians().atan().to_degrees()).min(90.0)).abs() < 1e-9, "{dec}");
    // Declination first: the same sky as the CD rows swapped.
    let swapped = wcs(["DEC--TAN", "RA---TAN"], [40.0, 30.0], [[0.0, s], [-s, 0.0]]);
    let (a, b) = (north.sky_of_pixel(123.0, 77.0).unwrap(), swapped.sky_of_pixel(123.0, 77.0).unwrap());
    assert!((a.0 - b.0).abs() < 1e-12 && (a.1 - b.1).abs() < 1e-12, "{a:?} vs {b:?}");
    assert!(wcs(["RA---SIN", "DEC--SIN"], [30.0, 40.0], [[-s, 0.0], [0.0, s]]).sky_of_pixel(1.0, 1.0).is_none());
}
