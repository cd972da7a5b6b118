//! `fit::correction::correct::correct_map` (moved from `instpol correct`): a Stokes map of sources of known
//! intrinsic polarization seen through `M_I` (`eq:instpol`, `mueller::partial_polarizer`
//! applied here, independently of the correction's closed form) is corrected back to that
//! polarization in every valid bin; invalid bins are left alone; the scatter and photon errors
//! are propagated as central differences of the correction say.

use field::{FieldModel, RadialPattern};
use fit::correction::correct::{correct_map, CorrectOptions, Corrector, MapError, Measurement};
use skyfield::{BinGeometry, StokesMap};

fn map_through(model: &dyn FieldModel, q0: f64, u0: f64) -> StokesMap {
    let geom = BinGeometry::covering(256, 0, 0, 2048, 2048, 0.2);
    let mut map = StokesMap::empty(geom.clone(), "FORS1", "V", vec![0.0, 22.5, 45.0, 67.5]);
    for k in 0..geom.len() {
        let (x, y) = geom.centre_arcmin(k % geom.nx, k / geom.nx);
        let (p, phi) = model.eval(x, y).p_chi();
        let s1 = mueller::partial_polarizer(p, phi) * mueller::stokes_qu(1.0, q0, u0);
        map.q[k] = s1[1] / s1[0];
        map.u[k] = s1[2] / s1[0];
        map.sigma_q[k] = 1e-3;
        map.sigma_u[k] = 1e-3;
        map.cov_qu[k] = 0.0;
        map.sigma_q_phot[k] = 5e-4;
        map.sigma_u_phot[k] = 5e-4;
        map.valid[k] = k % 5 != 3;
    }
    map
}

#[test]
fn a_map_through_m_i_is_corrected_back_bin_by_bin() {
    // The paper's I pattern (sec:fors1), exaggerated x 5.
    let model = RadialPattern::new(vec![0.0, -0.085e-2, 0.525e-2, -0.03e-2], [0.0, 0.0]);
    let (q0, u0) = (0.012, -0.004);
    let map = map_through(&model, q0, u0);
    let c = correct_map(&model, &map, CorrectOptions::default()).unwrap();
    let n_valid = map.valid.iter().filter(|v| **v).count();
    assert_eq!(c.n_bins, n_valid);
    assert_eq!(c.n_extrapolated, 0);
    assert_eq!(c.p0.len(), n_valid);
    for k in 0..map.q.len() {
        if !map.valid[k] {
            assert!(c.map.q[k] == map.q[k] && c.map.u[k] == map.u[k], "invalid bin {k} untouched");
            continue;
        }
        assert!((c.map.q[k] - q0).abs() < 1e-12 && (c.map.u[k] - u0).abs() < 1e-12, "bin {k}");
        assert!((c.map.p[k] - q0.hypot(u0)).abs() < 1e-12);
        // Errors propagated (the model has no error of its own here): against the Jacobian of
        // the correction by central differences, sigma_q0^2 = sum_j (dq0/dm_j)^2 sigma^2.
        let (x, y) = map.geometry.centre_arcmin(k % map.geometry.nx, k / map.geometry.nx);
        let cor = Corrector::new(&model, CorrectOptions::default());
        let at = |dq: f64, du: f64| {
            let m = Measurement::at_plate(x, y, map.q[k] + dq, map.u[k] + du, 0.0, 0.0, 0.0);
            let r = cor.correct(&m).unwrap();
            (r.q0, r.u0)
        };
        let h = 1e-6;
        let (a, b) = (at(h, 0.0), at(-h, 0.0));
        let (c1, d1) = (at(0.0, h), at(0.0, -h));
        let j = [
            [(a.0 - b.0) / (2.0 * h), (c1.0 - d1.0) / (2.0 * h)],
            [(a.1 - b.1) / (2.0 * h), (c1.1 - d1.1) / (2.0 * h)],
        ];
        for (s_in, s_q, s_u) in
            [(1e-3, c.map.sigma_q[k], c.map.sigma_u[k]), (5e-4, c.map.sigma_q_phot[k], c.map.sigma_u_phot[k])]
        {
            let want_q = s_in * j[0][0].hypot(j[0][1]);
            let want_u = s_in * j[1][0].hypot(j[1][1]);
            assert!(
                (s_q / want_q - 1.0).abs() < 1e-6 && (s_u / want_u - 1.0).abs() < 1e-6,
                "bin {k}: {s_q} vs {want_q}"
            );
        }
    }
}

#[test]
fn a_map_without_valid_bins_is_an_error() {
    let model = RadialPattern::new(vec![0.0, 0.001], [0.0, 0.0]);
    let mut map = map_through(&model, 0.0, 0.0);
    map.valid.iter_mut().for_each(|v| *v = false);
    assert!(matches!(correct_map(&model, &map, CorrectOptions::default()), Err(MapError::NoValidBins)));
}

/// A map of an instrument on a rotator (`SKYPA`): its bins are at the plate, the sky turned by
/// minus the position angle, through `M_I` (`mueller::partial_polarizer`, applied here) and
/// back by minus the HWP zero angle; corrected, every bin is the sky's `(q, u)` north through
/// east, and without `SKYPA` the same map comes back turned by the angle.
#[test]
fn a_map_on_a_rotator_is_corrected_onto_the_sky() {
    let model = RadialPattern::new(vec![0.0, -0.085e-2, 0.525e-2, -0.03e-2], [0.0, 0.0]);
    let (q0, u0, z, pa) = (0.012, -0.004, 2.9, 60.0);
    let turn = |q: f64, u: f64, deg: f64| {
        let (s, c) = (2.0 * deg.to_radians()).sin_cos();
        (c * q - s * u, s * q + c * u)
    };
    let (qs, us) = turn(q0, u0, -pa);
    let mut map = map_through(&model, qs, us);
    for k in 0..map.q.len() {
        (map.q[k], map.u[k]) = turn(map.q[k], map.u[k], -z);
    }
    map.sky_pa_deg = Some(pa);
    let opts = CorrectOptions { zero_angle_deg: z, ..CorrectOptions::default() };
    let c = correct_map(&model, &map, opts).unwrap();
    let mut worst = 0.0f64;
    for k in (0..map.q.len()).filter(|&k| map.valid[k]) {
        worst = worst.max((c.map.q[k] - q0).abs()).max((c.map.u[k] - u0).abs());
    }
    assert!(worst < 1e-12, "bins miss the sky by {worst:e}");
    map.sky_pa_deg = None;
    let c = correct_map(&model, &map, opts).unwrap();
    let k = (0..map.q.len()).find(|&k| map.valid[k]).unwrap();
    assert!(
        (c.map.q[k] - qs).abs() < 1e-12 && (c.map.u[k] - us).abs() < 1e-12,
        "without SKYPA: the instrument's frame"
    );
}
