//! A simulated night at La Silla on a Nasmyth instrument (at the level of
//! measured Stokes parameters: binned sky-field maps and standard-star photometry, not pixel
//! frames): a known M3 (aluminium, Wiersema factor and offset) turned by each exposure's
//! parallactic-angle track, then the paper's V-band field pattern. Standards observed through
//! the night give back the mirror within errors; a sky-field map taken during the night gives
//! back the field pattern once the sky is passed through the fitted telescope, and a wrong one
//! when it is not. The parallactic angle itself is checked against a vector construction.

use crate::common;

use common::*;
use fit::telescope::{exposure_track, fit_band, parallactic_angle, BandModel, FitOptions, ModelKind, Observation};
use fit::{fit_radial, Bin, RadialFitOptions};
use mueller::mirror::MetalTable;
use mueller::Stokes;
use rand::SeedableRng;
use rand_distr::{Distribution, Normal};

#[test]
fn parallactic_angle_is_the_position_angle_of_the_zenith() {
    // Vectors in the hour-angle frame: x to the meridian on the equator, y to the east, z to the
    // pole. The zenith's direction at the star, projected on the sky, measured from north
    // (towards the pole) through east.
    let unit = |v: [f64; 3]| {
        let n = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt();
        [v[0] / n, v[1] / n, v[2] / n]
    };
    let dot = |a: [f64; 3], b: [f64; 3]| a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
    let cross =
        |a: [f64; 3], b: [f64; 3]| [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]];
    let tangent = |v: [f64; 3], s: [f64; 3]| {
        let k = dot(v, s);
        unit([v[0] - k * s[0], v[1] - k * s[1], v[2] - k * s[2]])
    };
    let d = f64::to_radians;
    for lat in [-29.26, -24.6, 19.8, 52.0] {
        for dec in [-70.0, -30.0, 0.0, 25.0] {
            for ha in [-75.0, -20.0, -1.0, 3.0, 40.0, 100.0] {
                let (phi, de, h) = (d(lat), d(dec), d(ha));
                let s = [de.cos() * h.cos(), -de.cos() * h.sin(), de.sin()];
                let zen = [phi.cos(), 0.0, phi.sin()];
                if dot(s, zen) < 0.05 {
                    continue; // below the horizon
                }
                let north = tangent([0.0, 0.0, 1.0], s);
                let east = cross(north, s);
                let t = tangent(zen, s);
                let pa = dot(t, east).atan2(dot(t, north));
                let q = parallactic_angle(phi, de, h);
                assert!(
                    mueller::wrap_half_pi(0.5 * (q - pa)).abs() < 1e-12,
                    "lat {lat} dec {dec} ha {ha}: {q} vs {pa}"
                );
                // West of the meridian the zenith lies to the east: positive.
                if ha > 0.0 && (q.sin() * pa.sin()) != 0.0 {
                    assert!(q.signum() == pa.signum());
                }
            }
        }
    }
}

/// The paper's V pattern (fractions) as a field model, evaluated here.
fn field_v(x: f64, y: f64) -> (f64, f64) {
    radial_field(&V_COEFFS, (0.0, 0.0))(x, y)
}

#[test]
fn a_night_with_a_known_mirror_and_field_gives_both_back() {
    let lat = f64::to_radians(-29.26); // La Silla, instruments/efosc2.toml [telescope]
    let inst = instrument::Instrument::load("efosc2").unwrap();
    assert!((inst.telescope.unwrap().site_latitude_deg.unwrap() - (-29.26)).abs() < 1e-9);
    let table = MetalTable::builtin("aluminium").unwrap();
    let truth = BandModel {
        wavelength_um: 0.55,
        index: table.index(0.55).unwrap(),
        factor: 0.86,
        thickness_nm: 0.0,
        offset: f64::to_radians(40.0),
        q0: 0.0,
        u0: 0.0,
    };
    let sigma = 6e-4;
    let mut rng = rand_xoshiro::Xoshiro256PlusPlus::seed_from_u64(2024);
    let g = Normal::new(0.0, sigma).unwrap();
    // What the instrument measures of a sky Stokes vector over a track at field position
    // (x, y): the telescope (mean over the track), then the paper's partial polarizer.
    let measure = |sky: (f64, f64), track, x: f64, y: f64| -> (f64, f64) {
        let t = truth.matrix_track(track).unwrap() * Stokes::new(1.0, sky.0, sky.1, 0.0);
        let (qi, ui) = field_v(x, y);
        let (p, phi) = (qi.hypot(ui), 0.5 * ui.atan2(qi));
        let s = mueller::partial_polarizer(p, phi) * t;
        (s[1] / s[0], s[2] / s[0])
    };
    // Standards: six unpolarized stars at declinations -70..+10 deg, 10-min exposures every
    // 40 min from 4 h east to 4 h west, near the field centre (within 0.3').
    let mut obs = vec![];
    let minute = std::f64::consts::PI / 720.0; // hour angle of one minute of time
    for (k, dec) in [-70.0, -55.0, -40.0, -20.0, -5.0, 10.0].iter().enumerate() {
        let dec = f64::to_radians(*dec);
        let mut ha = -240.0 * minute + 7.0 * k as f64 * minute;
        while ha < 240.0 * minute {
            let track = exposure_track(lat, dec, ha, ha + 10.0 * minute);
            let (x, y) = (0.3 * (k as f64 - 2.5) / 2.5, 0.1);
            let (q, u) = measure((0.0, 0.0), track, x, y);
            // The catalog gives one angle per exposure: the mid-exposure one.
            let pa = parallactic_angle(lat, dec, ha + 5.0 * minute);
            obs.push(Observation {
                star: format!("std{k}"),
                parallactic: pa,
                qu: mueller::Qu::from_sigmas(q + g.sample(&mut rng), u + g.sample(&mut rng), sigma, sigma, 0.0),
                wavelength_um: 0.55,
                band: "V".into(),
                rotator: 0.0,
                sky: (0.0, 0.0),
                source: format!("night:{k}:{ha:.3}"),
            });
            ha += 40.0 * minute;
        }
    }
    assert!(obs.len() >= 60);
    let f = fit_band(ModelKind::Wiersema, &obs, &table, &FitOptions::default()).unwrap();
    let (fa, off) = (f.param("factor").unwrap(), f.param("offset").unwrap());
    eprintln!(
        "night: {} standards; factor {:.4} +- {:.4} (0.86), offset {:.3} +- {:.3} deg (40); chi2/dof {:.2}",
        obs.len(),
        fa.value,
        fa.sigma,
        off.value.to_degrees(),
        off.sigma.to_degrees(),
        f.chi2_reduced
    );
    assert!((fa.value - 0.86).abs() < 3.0 * fa.sigma, "factor {} +- {}", fa.value, fa.sigma);
    assert!(mueller::wrap_half_pi(off.value - truth.offset).abs() < 3.0 * off.sigma, "offset {:?}", off);
    assert!(f.chi2_reduced < 1.6, "{}", f.chi2_reduced);

    // A sky-field map during the night (an empty field at dec -30 deg, 20 min from HA +1 h):
    // sky polarization 1.5% at 30 deg, the paper's V pattern, noise 1e-4 per bin.
    let dec = f64::to_radians(-30.0);
    let track = exposure_track(lat, dec, 60.0 * minute, 80.0 * minute);
    let sky = (0.015 * f64::to_radians(60.0).cos(), 0.015 * f64::to_radians(60.0).sin());
    let centres = fors1_bin_centres(128);
    let noise = Normal::new(0.0, SIGMA_BIN).unwrap();
    let measured: Vec<(f64, f64, f64, f64)> = centres
        .iter()
        .map(|&(x, y)| {
            let (q, u) = measure(sky, track, x, y);
            (x, y, q + noise.sample(&mut rng), u + noise.sample(&mut rng))
        })
        .collect();
    // The instrumental field from each bin, given what the instrument saw of the sky.
    let solve = |q0: f64, u0: f64| -> Vec<Bin> {
        measured
            .iter()
            .map(|&(x, y, q1, u1)| {
                let (p, phi) = skyfield::solve::solve_exact(q1, u1, q0, u0).unwrap();
                Bin::new(x, y, p * (2.0 * phi).cos(), p * (2.0 * phi).sin(), SIGMA_BIN, SIGMA_BIN)
            })
            .collect()
    };
    // The sky through the fitted telescope over the map's track.
    let fitted = f.band("V").unwrap();
    let (qs, us) = fitted.sky_through(sky.0, sky.1, track).unwrap();
    let opts = RadialFitOptions { include_c0: true, ..Default::default() };
    let good = fit_radial(&solve(qs, us), &opts).unwrap().model;
    // Truth: c0 = 0 and the paper's c1..c3.
    let errs = good.coefficient_errors();
    for (i, (c, e)) in good.coeffs.iter().zip(&errs).enumerate() {
        let t = if i == 0 { 0.0 } else { V_COEFFS[i - 1] };
        // The fitted telescope's own error moves the whole field by a constant of its size
        // (a few 1e-5): allowed for in c0.
        let allow = if i == 0 { 3.0 * e + 1e-4 } else { 4.0 * e };
        assert!((c - t).abs() < allow, "c{i} = {c} +- {e}, truth {t}");
    }
    for &(x, y) in &[(-3.0, -3.0), (2.0, 1.0), (0.5, -2.5)] {
        let (a, b) = (good.qu(x, y), field_v(x, y));
        assert!((a.0 - b.0).hypot(a.1 - b.1) < 1.5e-4, "at ({x}, {y}): {a:?} vs {b:?}");
    }
    // Without the telescope term (the sky as catalogued), the "field" carries the M3's
    // few percent as a constant: wrong by far more than the pattern.
    let off = |bins: &[Bin]| {
        let d: f64 = bins.iter().map(|b| (b.qu.q - field_v(b.x, b.y).0).hypot(b.qu.u - field_v(b.x, b.y).1)).sum();
        d / bins.len() as f64
    };
    let (with, without) = (off(&solve(qs, us)), off(&solve(sky.0, sky.1)));
    eprintln!("sky-field bins off the true pattern by {with:.2e} with the telescope term, {without:.2e} without");
    assert!(with < 3.0 * SIGMA_BIN && without > 0.01, "{with} {without}");
    let bad = fit_radial(&solve(sky.0, sky.1), &opts).unwrap();
    assert!(bad.chi2_reduced > 100.0, "{}", bad.chi2_reduced);
}
