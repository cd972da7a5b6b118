//! The rotator / adapter angle in the telescope model and the oxide model's several thickness
//! minima.
//!
//! Conventions are checked against constructions written here: the rotation of the
//! instrument's axes by the rotator angle as a rotation of the coherency matrix of the light's
//! Jones vector (not `mueller::rotation`), and the whole chain for an unpolarized star as the
//! coherency `J J^+` of a mirror that reflects `|r_p|^2` along its plane of incidence and
//! `|r_s|^2` across it, the plane at the angle that reproduces the published form of Wiersema
//! et al. 2018 (q = P cos 2(offset - pa), u = -P sin 2(offset - pa)).

use fit::telescope::{fit_band, parse_observations, BandModel, FitOptions, ModelKind, Observation, Track};
use mueller::mirror::{alumina_index, reflect, MetalTable};
use mueller::thinfilm::Layer;
use nalgebra::{Complex, Matrix2};
use std::f64::consts::{FRAC_PI_2, FRAC_PI_4};
use std::path::Path;

type C = Complex<f64>;

/// Stokes `(I, Q, U, V)` of a coherency matrix `<E E^+>` in axes x, y (chi from x towards y,
/// V > 0 for light turning from x to y).
fn stokes_of(c: &Matrix2<C>) -> [f64; 4] {
    [(c[(0, 0)] + c[(1, 1)]).re, (c[(0, 0)] - c[(1, 1)]).re, 2.0 * c[(0, 1)].re, -2.0 * c[(0, 1)].im]
}

/// The coherency matrix of a Stokes vector (inverse of [`stokes_of`]).
fn coherency(s: [f64; 4]) -> Matrix2<C> {
    let h = 0.5;
    Matrix2::new(
        C::new(h * (s[0] + s[1]), 0.0),
        C::new(h * s[2], -h * s[3]),
        C::new(h * s[2], h * s[3]),
        C::new(h * (s[0] - s[1]), 0.0),
    )
}

/// Field components in axes turned by `t` (from +x towards +y): `E' = A E`.
fn axes(t: f64) -> Matrix2<C> {
    let (s, c) = t.sin_cos();
    Matrix2::new(C::new(c, 0.0), C::new(s, 0.0), C::new(-s, 0.0), C::new(c, 0.0))
}

fn model(factor: f64, thickness: f64, offset: f64) -> BandModel {
    BandModel {
        wavelength_um: 0.55,
        index: MetalTable::builtin("aluminium").unwrap().index(0.55).unwrap(),
        factor,
        thickness_nm: thickness,
        offset,
        q0: 0.0,
        u0: 0.0,
    }
}

#[test]
fn the_rotator_turns_the_instrument_axes_as_a_jones_rotation_does() {
    let b = model(0.9, 12.0, 0.4);
    let d = f64::to_radians;
    for (pa, rho) in [(10.0, 0.0), (10.0, 30.0), (-75.0, -50.0), (140.0, 95.0), (0.0, 180.0)] {
        let track = Track::at(d(pa));
        let m0 = b.matrix_track(track).unwrap();
        let m = b.matrix_track(track.with_rotator(d(rho))).unwrap();
        // Every sky Stokes vector: through the chain without the rotator, then the axes turned
        // by rho in the Jones picture (C' = A C A^+), must equal the chain with the rotator.
        for sky in [[1.0, 0.0, 0.0, 0.0], [1.0, 0.6, 0.0, 0.0], [1.0, 0.0, -0.5, 0.0], [1.0, 0.2, 0.3, 0.4]] {
            let s0 = m0 * nalgebra::Vector4::from(sky);
            let a = axes(d(rho));
            let want = stokes_of(&(a * coherency([s0[0], s0[1], s0[2], s0[3]]) * a.adjoint()));
            let got = m * nalgebra::Vector4::from(sky);
            for k in 0..4 {
                assert!(
                    (got[k] - want[k]).abs() < 1e-12,
                    "pa {pa} rho {rho} sky {sky:?}: {k}: {} vs {}",
                    got[k],
                    want[k]
                );
            }
        }
        // The sense in words: a rotator angle rho lowers every measured angle by rho.
        let chi = |m: &nalgebra::Matrix4<f64>| 0.5 * m[(2, 0)].atan2(m[(1, 0)]);
        let dchi = mueller::wrap_half_pi(chi(&m) - chi(&m0));
        assert!(mueller::wrap_half_pi(dchi + d(rho)).abs() < 1e-12, "{pa} {rho}: {}", dchi.to_degrees());
    }
}

#[test]
fn an_unpolarized_star_through_m3_and_the_rotator_matches_the_jones_mirror() {
    let (factor, thick, offset) = (0.86, 0.0, f64::to_radians(40.0));
    let b = model(factor, thick, offset);
    let r = reflect(b.index * factor, &[], 550.0, FRAC_PI_4).unwrap();
    for pa_deg in [-170.0, -60.0, 0.0, 33.0, 120.0] {
        for rho_deg in [0.0, 25.0, -70.0] {
            let (pa, rho) = (f64::to_radians(pa_deg), f64::to_radians(rho_deg));
            // Mirror with its plane of incidence at pa - 90 deg (s along pa): J J^+ =
            // P_plane |r_p|^2 + P_across |r_s|^2, then the instrument axes at offset + rho.
            let plane = axes(pa - FRAC_PI_2);
            let diag = Matrix2::new(
                C::new(r.r_p.norm_sqr(), 0.0),
                C::new(0.0, 0.0),
                C::new(0.0, 0.0),
                C::new(r.r_s.norm_sqr(), 0.0),
            );
            let c = plane.adjoint() * diag * plane * C::new(0.5, 0.0);
            let a = axes(offset + rho);
            let s = stokes_of(&(a * c * a.adjoint()));
            let m = b.matrix_track(Track::at(pa).with_rotator(rho)).unwrap();
            let (q, u) = (m[(1, 0)] / m[(0, 0)], m[(2, 0)] / m[(0, 0)]);
            assert!(
                (q - s[1] / s[0]).abs() < 1e-12 && (u - s[2] / s[0]).abs() < 1e-12,
                "{pa_deg} {rho_deg}: ({q}, {u}) vs {s:?}"
            );
            // ... which is the published form with offset + rho for offset.
            let p = r.polarization;
            let t = 2.0 * (offset + rho - pa);
            assert!((q - p * t.cos()).abs() < 1e-12 && (u + p * t.sin()).abs() < 1e-12);
        }
    }
}

/// Unpolarized standards drawn from the published form with the rotator at `rho` (rad) per
/// row, noise from a fixed sequence of normal deviates.
fn standards(offset: f64, factor: f64, rhos: &[f64], sigma: f64) -> Vec<Observation> {
    let b = model(factor, 0.0, offset);
    let p = b.m3().unwrap().polarization;
    let mut state = 12345u64;
    let mut gauss = move || {
        let mut u = || {
            state = state.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
            ((state >> 11) as f64 + 0.5) / (1u64 << 53) as f64
        };
        (-2.0 * u().ln()).sqrt() * (std::f64::consts::TAU * u()).cos()
    };
    (0..36)
        .map(|i| {
            let pa = f64::to_radians(-170.0 + 9.7 * i as f64);
            let rho = rhos[i % rhos.len()];
            let t = 2.0 * (offset + rho - pa);
            Observation {
                star: format!("S{i}"),
                parallactic: pa,
                qu: mueller::Qu::from_sigmas(
                    p * t.cos() + sigma * gauss(),
                    -p * t.sin() + sigma * gauss(),
                    sigma,
                    sigma,
                    0.0,
                ),
                wavelength_um: 0.55,
                band: "V".into(),
                rotator: rho,
                sky: (0.0, 0.0),
                source: format!("sim:{i}"),
            }
        })
        .collect()
}

#[test]
fn standards_at_several_rotator_angles_give_the_offset_at_rotator_zero() {
    let t = MetalTable::builtin("aluminium").unwrap();
    let rhos = [0.0, f64::to_radians(35.0), f64::to_radians(-60.0)];
    let obs = standards(0.7, 0.9, &rhos, 5e-4);
    let f = fit_band(ModelKind::Wiersema, &obs, &t, &FitOptions::default()).unwrap();
    let (fa, off) = (f.param("factor").unwrap(), f.param("offset").unwrap());
    assert!((fa.value - 0.9).abs() < 3.0 * fa.sigma, "{fa:?}");
    assert!(mueller::wrap_half_pi(off.value - 0.7).abs() < 3.0 * off.sigma, "{off:?}");
    assert!(f.with_rotator && f.chi2_reduced < 2.0, "{}", f.chi2_reduced);
    // Ignoring the rotator column, no single offset fits.
    let blind: Vec<Observation> = obs.iter().map(|o| Observation { rotator: 0.0, ..o.clone() }).collect();
    let g = fit_band(ModelKind::Wiersema, &blind, &t, &FitOptions { clip: None, ..Default::default() }).unwrap();
    assert!(!g.with_rotator && g.chi2_reduced > 50.0, "{}", g.chi2_reduced);
    // The column is read from a catalog, in degrees.
    let o = parse_observations(
        "star,parallactic_deg,q,sigma_q,u,sigma_u,wavelength_um,filter,rotator_deg\nA,10,0.01,0.001,0.02,0.001,0.55,V,-35\n",
        Path::new("c.csv"),
    )
    .unwrap();
    assert!((o[0].rotator - f64::to_radians(-35.0)).abs() < 1e-15);
    let e = parse_observations(
        "star,parallactic_deg,q,sigma_q,u,sigma_u,wavelength_um,rotator_deg\nA,10,0.01,0.001,0.02,0.001,0.55,x\n",
        Path::new("c.csv"),
    )
    .unwrap_err()
    .to_string();
    assert!(e.contains("line 2, column 8") && e.contains("rotator"), "{e}");
}

#[test]
fn the_oxide_model_reports_every_thickness_minimum_within_delta_chi2_4() {
    // Below ~30 nm two thicknesses give each polarization: data from 8 nm.
    let t = MetalTable::builtin("aluminium").unwrap();
    let truth = 8.0;
    let n = t.index(0.55).unwrap();
    let pol = |d: f64| {
        let layers = if d > 0.0 { vec![Layer::new(alumina_index(0.55), d)] } else { vec![] };
        reflect(n, &layers, 550.0, FRAC_PI_4).unwrap().polarization
    };
    let p = pol(truth);
    let sigma = 4e-4;
    let mut obs = standards(-0.5, 1.0, &[0.0], sigma);
    for o in &mut obs {
        // Rescale the bare mirror's curve to the layer's polarization (closed form above).
        let scale = p / pol(0.0);
        o.qu.q *= scale;
        o.qu.u *= scale;
    }
    let f = fit_band(ModelKind::Oxide, &obs, &t, &FitOptions::default()).unwrap();
    eprintln!("minima: {:?}", f.minima);
    assert!(f.minima.len() >= 2, "{:?}", f.minima);
    assert_eq!(f.minima[0].delta_chi2, 0.0);
    assert!((f.minima[0].thickness_nm - f.param("thickness_nm").unwrap().value).abs() < 1e-6);
    for w in f.minima.windows(2) {
        assert!(w[1].delta_chi2 >= w[0].delta_chi2);
    }
    for m in &f.minima {
        assert!(m.delta_chi2 < 4.0);
        // Each minimum is a mirror of the data's polarization: P(thickness) matches P(truth)
        // to the precision 36 points of sigma give (about sigma / sqrt(36)), by the Fresnel
        // and thin-film equations evaluated here.
        assert!((pol(m.thickness_nm) - p).abs() < 5.0 * sigma / 6.0, "{m:?}: {} vs {p}", pol(m.thickness_nm));
    }
    let near = f.minima.iter().any(|m| (m.thickness_nm - truth).abs() < 5.0);
    let far = f.minima.iter().any(|m| (m.thickness_nm - truth).abs() > 8.0);
    assert!(near && far, "{:?}", f.minima);
}
