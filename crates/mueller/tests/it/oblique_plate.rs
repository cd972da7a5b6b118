//! The closed-form retardance of a uniaxial plate at oblique incidence
//! (`mueller::causes::UniaxialPlate::retardance`) against the two roots of the Fresnel wave
//! equation in the crystal, found numerically here: `det(k k^T - |k|^2 I + eps) = 0` for the
//! normal component `k_z` at a given transverse wave vector (units of `k0`), with the uniaxial
//! dielectric tensor `eps = n_o^2 I + (n_e^2 - n_o^2) c c^T`.

use mueller::causes::UniaxialPlate;
use nalgebra::{Matrix3, Vector3};

fn det(kx: f64, ky: f64, kz: f64, c: &Vector3<f64>, no: f64, ne: f64) -> f64 {
    let k = Vector3::new(kx, ky, kz);
    let eps = Matrix3::identity() * (no * no) + c * c.transpose() * (ne * ne - no * no);
    (k * k.transpose() - Matrix3::identity() * k.norm_squared() + eps).determinant()
}

/// Roots of the determinant in `kz` on (0, 2): scan and bisect.
fn roots(kx: f64, ky: f64, c: &Vector3<f64>, no: f64, ne: f64) -> Vec<f64> {
    let mut out = Vec::new();
    let n = 200_000;
    let (lo, hi) = (1.0, 2.0);
    let f = |z: f64| det(kx, ky, z, c, no, ne);
    let mut a = lo;
    let mut fa = f(a);
    for k in 1..=n {
        let b = lo + (hi - lo) * k as f64 / n as f64;
        let fb = f(b);
        if fa == 0.0 || fa.signum() != fb.signum() {
            let (mut x0, mut x1) = (a, b);
            for _ in 0..100 {
                let m = 0.5 * (x0 + x1);
                if f(x0).signum() == f(m).signum() {
                    x0 = m;
                } else {
                    x1 = m;
                }
            }
            out.push(0.5 * (x0 + x1));
        }
        a = b;
        fa = fb;
    }
    out
}

#[test]
fn closed_form_retardance_matches_the_fresnel_equation_roots() {
    let plate = UniaxialPlate::quartz_half_wave_b(3);
    for &(inc_deg, az) in &[(3.0f64, 0.0f64), (10.0, 0.7), (25.0, 1.3), (40.0, std::f64::consts::FRAC_PI_2)] {
        let s = inc_deg.to_radians().sin();
        // Axis along x; plane of incidence at `az` from it.
        let c = Vector3::new(1.0, 0.0, 0.0);
        let r = roots(s * az.cos(), s * az.sin(), &c, plate.n_o, plate.n_e);
        assert!(r.len() == 2 || (r.len() == 1 && az.sin().abs() < 1e-12), "roots {r:?}");
        let (ko, ke) = if r.len() == 2 {
            // The ordinary root is sqrt(n_o^2 - s^2) whatever the azimuth.
            let o = (plate.n_o * plate.n_o - s * s).sqrt();
            if (r[0] - o).abs() < (r[1] - o).abs() {
                (r[0], r[1])
            } else {
                (r[1], r[0])
            }
        } else {
            (r[0], r[0])
        };
        let want = 2.0 * std::f64::consts::PI * plate.thickness_waves * (ke - ko);
        let got = plate.retardance(inc_deg.to_radians(), az);
        assert!((got - want).abs() < 1e-6, "i {inc_deg} az {az}: closed form {got} vs roots {want}");
    }
}
