//! The correction of measured Stokes parameters (`fit::correction::correct`) against the forward model
//! (`mueller`: `M_I` of `eq:instpol`, the dual-beam train with a plate zero-angle offset, the one
//! Stokes solver), against `eq:approx`, against finite differences and against Monte Carlo.

use approx::assert_relative_eq;
use fit::correction::correct::{
    exact_jacobian, invert_exact, invert_first_order, CorrectOptions, Corrected, Corrector, Error, Measurement, Method,
};
use fit::models::model::{FieldModel, InstPol};
use mueller::Qu;
use mueller::{optimal_angles, partial_polarizer, stokes_p_chi, DualBeam, Element, Hwp};
use rand::SeedableRng;
use rand_distr::{Distribution, Normal};
use rand_xoshiro::Xoshiro256PlusPlus;
use std::f64::consts::PI;
use stokes::{normalized_difference, polarization, StokesSolver};

/// Test double: a radial instrumental field `p(r) = sum c_k r^k` (fraction, r in arcmin) with
/// `phi` equal to the polar angle (the FORS1 V/I pattern of section `sec:fors1`), a constant
/// model covariance, over a square field of half-width `half` arcmin.
struct Radial {
    c: Vec<f64>,
    sigma: f64,
    cov: f64,
    half: f64,
}

impl Radial {
    /// FORS1 V of section `sec:fors1`: `p(r) = 0.012 r + 0.046 r^2 + 0.002 r^3` percent.
    fn fors1_v() -> Self {
        Self { c: vec![0.0, 0.012e-2, 0.046e-2, 0.002e-2], sigma: 0.0005, cov: 0.0, half: 0.5 * 2048.0 * 0.2 / 60.0 }
    }
    /// FORS1 I of section `sec:fors1`: `p(r) = -0.017 r + 0.105 r^2 - 0.006 r^3` percent.
    fn fors1_i() -> Self {
        Self { c: vec![0.0, -0.017e-2, 0.105e-2, -0.006e-2], sigma: 0.0005, cov: 0.0, half: 0.5 * 2048.0 * 0.2 / 60.0 }
    }
    fn p(&self, r: f64) -> f64 {
        self.c.iter().rev().fold(0.0, |acc, c| acc * r + c)
    }
}

impl FieldModel for Radial {
    fn eval(&self, x: f64, y: f64) -> InstPol {
        let r2 = x * x + y * y;
        let (q, u) = if r2 > 0.0 {
            let p = self.p(r2.sqrt());
            (p * (x * x - y * y) / r2, p * 2.0 * x * y / r2)
        } else {
            (0.0, 0.0)
        };
        InstPol { q, u, var_q: self.sigma * self.sigma, var_u: self.sigma * self.sigma, cov_qu: self.cov }
    }
    fn contains(&self, x: f64, y: f64) -> bool {
        x.abs() <= self.half && y.abs() <= self.half
    }
}

/// The measured `(q1, u1)` of a star with intrinsic `(p0, chi0)` seen through `M_I(p, phi)` and a
/// plate whose zero angle is off by `chi_offset`: the full dual-beam forward model, reduced by
/// the one `F_i` and the one Stokes solver on 16 optimal HWP angles.
fn observe(p: f64, phi: f64, p0: f64, chi0: f64, chi_offset: f64) -> (f64, f64) {
    let train = DualBeam {
        pre: vec![Element::PartialPolarizer { p, phi }],
        hwp: Hwp { chi_offset, ..Hwp::ideal() },
        ..Default::default()
    };
    let th = optimal_angles(16);
    let f: Vec<f64> =
        train.fluxes(&stokes_p_chi(1.0, p0, chi0), &th).iter().map(|b| normalized_difference(b.f_o, b.f_e)).collect();
    StokesSolver::new(&th).unwrap().solve(&f)
}

fn grid() -> Vec<(f64, f64)> {
    let h = Radial::fors1_v().half;
    let n = 9;
    let mut v = Vec::new();
    for i in 0..n {
        for j in 0..n {
            v.push((-h + 2.0 * h * i as f64 / (n - 1) as f64, -h + 2.0 * h * j as f64 / (n - 1) as f64));
        }
    }
    v
}

fn angle_diff(a: f64, b: f64) -> f64 {
    let d = (a - b).rem_euclid(PI);
    d.min(PI - d)
}

/// Round trip: a star of P0 = 1% at every position of the field, through the FORS1 V
/// field (p up to 1.36% at the corners, so p ~ P0 and beyond), comes back exactly (noise-free)
/// with the exact inversion, for several angles of the star.
#[test]
fn round_trip_polarized_star_over_the_field_exact() {
    let model = Radial::fors1_v();
    let c = Corrector::new(&model, CorrectOptions::default());
    let mut worst = 0.0f64;
    let mut max_p = 0.0f64;
    for (x, y) in grid() {
        let inst = model.eval(x, y);
        let (p, phi) = inst.p_chi();
        max_p = max_p.max(p);
        for chi0 in [0.0, 0.4, 1.0, 2.2, 3.0] {
            let (q1, u1) = observe(p, phi, 0.01, chi0, 0.0);
            let r = c.correct(&Measurement::at_plate(x, y, q1, u1, 1e-4, 1e-4, 0.0)).unwrap();
            assert!((r.p0 - 0.01).abs() < 1e-12, "P0 at ({x},{y}) chi0={chi0}: {}", r.p0);
            assert!(angle_diff(r.chi0, chi0) < 1e-9, "chi0 at ({x},{y}): {} vs {chi0}", r.chi0);
            worst = worst.max((r.p0 - 0.01).abs());
        }
    }
    // The field reaches p > P0 at the corners: the case the paper calls severe.
    assert!(max_p > 0.0130 && max_p < 0.0140, "corner p = {max_p}");
    assert!(worst < 1e-12);
}

/// Round trip with noise: at each position and angle, noisy measurements (sigma 0.05% on q, u)
/// and a noisy calibration (the model's own sigma 0.05%) are corrected; the normalized
/// residuals of (q0, u0) have unit variance and nothing lies beyond 5 sigma, everywhere,
/// including where p ~ P0.
#[test]
fn round_trip_with_noise_recovered_within_errors_everywhere() {
    let model = Radial::fors1_v();
    let c = Corrector::new(&model, CorrectOptions::default());
    let mut rng = Xoshiro256PlusPlus::seed_from_u64(6);
    let g = Normal::new(0.0, 1.0).unwrap();
    let s_meas = 0.0005;
    let (mut sum2, mut n, mut worst) = (0.0, 0usize, 0.0f64);
    for (x, y) in grid() {
        let truth = model.eval(x, y);
        let (p, phi) = truth.p_chi();
        for k in 0..8 {
            let chi0 = k as f64 * PI / 8.0 + 0.1;
            let (q1, u1) = observe(p, phi, 0.01, chi0, 0.0);
            // The calibration a pipeline would hold: the truth plus its own error.
            let noisy_cal =
                Shifted { inner: &model, dq: model.sigma * g.sample(&mut rng), du: model.sigma * g.sample(&mut rng) };
            let cn = Corrector::new(&noisy_cal, CorrectOptions::default());
            let m = Measurement::at_plate(
                x,
                y,
                q1 + s_meas * g.sample(&mut rng),
                u1 + s_meas * g.sample(&mut rng),
                s_meas,
                s_meas,
                0.0,
            );
            let r = cn.correct(&m).unwrap();
            let (tq, tu) = (0.01 * (2.0 * chi0).cos(), 0.01 * (2.0 * chi0).sin());
            for z in [(r.q0 - tq) / r.var_q0.sqrt(), (r.u0 - tu) / r.var_u0.sqrt()] {
                sum2 += z * z;
                n += 1;
                worst = worst.max(z.abs());
            }
            // The noise-free corrector gives the same kind of answer.
            let _ = c.correct(&m).unwrap();
        }
    }
    let var = sum2 / n as f64;
    // 1296 normalized residuals: the variance is 1 within ~4% (1 sigma).
    assert!((var - 1.0).abs() < 0.15, "variance of normalized residuals = {var}");
    assert!(worst < 5.0, "worst residual {worst} sigma");
}

/// A field model shifted by a constant: a calibration with an error.
struct Shifted<'a> {
    inner: &'a Radial,
    dq: f64,
    du: f64,
}

impl FieldModel for Shifted<'_> {
    fn eval(&self, x: f64, y: f64) -> InstPol {
        let mut a = self.inner.eval(x, y);
        a.q += self.dq;
        a.u += self.du;
        a
    }
    fn contains(&self, x: f64, y: f64) -> bool {
        self.inner.contains(x, y)
    }
}

/// eq:approx vs eq:instpol: with p and P0 of several percent the first-order form is off by
/// ~p P0 while the exact inversion recovers the star.
#[test]
fn exact_inversion_correct_where_eq_approx_is_not() {
    let (p, phi, p0, chi0): (f64, f64, f64, f64) = (0.05, 0.3, 0.05, 1.2);
    let (q1, u1) = observe(p, phi, p0, chi0, 0.0);
    let (qi, ui) = (p * (2.0 * phi).cos(), p * (2.0 * phi).sin());
    let (tq, tu) = (p0 * (2.0 * chi0).cos(), p0 * (2.0 * chi0).sin());
    let ex = invert_exact(qi, ui, q1, u1).unwrap();
    let ap = invert_first_order(qi, ui, q1, u1);
    assert!((ex.0 - tq).abs() < 1e-14 && (ex.1 - tu).abs() < 1e-14);
    let err_ap = (ap.0 - tq).hypot(ap.1 - tu);
    // Leading order of the difference: p times the part of P0 perpendicular to phi.
    assert!(err_ap > 0.5 * p * p0 * (2.0 * (chi0 - phi)).sin().abs(), "eq:approx error {err_ap}");
    assert!(err_ap > 1e-3);
}

/// Both forms agree to second order: the difference is `p P0 |sin 2(chi0 - phi)|` to leading
/// order (derived from the closed form), so it falls as eps^2 when p and P0 both scale with
/// eps, and vanishes to that order when the star is aligned with the instrument.
#[test]
fn exact_and_approx_agree_to_second_order() {
    let (phi, chi0) = (0.3, 1.2);
    let mut prev: Option<f64> = None;
    for k in 0..6 {
        let eps = 0.04 / 2f64.powi(k);
        let (p, p0) = (eps, 0.7 * eps);
        let (q1, u1) = observe(p, phi, p0, chi0, 0.0);
        let (qi, ui) = (p * (2.0 * phi).cos(), p * (2.0 * phi).sin());
        let ex = invert_exact(qi, ui, q1, u1).unwrap();
        let ap = invert_first_order(qi, ui, q1, u1);
        let d = (ex.0 - ap.0).hypot(ex.1 - ap.1);
        let lead = p * p0 * (2.0 * (chi0 - phi)).sin().abs();
        // Relative deviation from the leading term is O(eps).
        assert!((d / lead - 1.0).abs() < 3.0 * eps, "eps={eps}: d={d}, p P0 sin = {lead}");
        if let Some(dp) = prev {
            assert_relative_eq!(dp / d, 4.0, epsilon = 0.2);
        }
        prev = Some(d);
    }
    // Aligned star: the difference is third order.
    let (p, p0) = (0.01, 0.01);
    let (q1, u1) = observe(p, phi, p0, phi, 0.0);
    let (qi, ui) = (p * (2.0 * phi).cos(), p * (2.0 * phi).sin());
    let ex = invert_exact(qi, ui, q1, u1).unwrap();
    let ap = invert_first_order(qi, ui, q1, u1);
    assert!((ex.0 - ap.0).hypot(ex.1 - ap.1) < 5.0 * p * p * p0);
}

/// The analytic Jacobians against central finite differences, including large p.
#[test]
fn jacobian_matches_finite_differences() {
    for &(qi, ui, q1, u1) in
        &[(0.01, -0.004, 0.02, 0.015), (0.05, 0.03, -0.04, 0.06), (-0.3, 0.2, 0.1, -0.25), (0.0, 1e-3, 0.01, 0.0)]
    {
        let (_, jm, ja) = exact_jacobian(qi, ui, q1, u1).unwrap();
        let h = 1e-7;
        let f = |a: f64, b: f64, c: f64, d: f64| invert_exact(a, b, c, d).unwrap();
        let dm = [
            {
                let (p, m) = (f(qi, ui, q1 + h, u1), f(qi, ui, q1 - h, u1));
                ((p.0 - m.0) / (2.0 * h), (p.1 - m.1) / (2.0 * h))
            },
            {
                let (p, m) = (f(qi, ui, q1, u1 + h), f(qi, ui, q1, u1 - h));
                ((p.0 - m.0) / (2.0 * h), (p.1 - m.1) / (2.0 * h))
            },
        ];
        let da = [
            {
                let (p, m) = (f(qi + h, ui, q1, u1), f(qi - h, ui, q1, u1));
                ((p.0 - m.0) / (2.0 * h), (p.1 - m.1) / (2.0 * h))
            },
            {
                let (p, m) = (f(qi, ui + h, q1, u1), f(qi, ui - h, q1, u1));
                ((p.0 - m.0) / (2.0 * h), (p.1 - m.1) / (2.0 * h))
            },
        ];
        for col in 0..2 {
            assert_relative_eq!(jm[0][col], dm[col].0, epsilon = 1e-6);
            assert_relative_eq!(jm[1][col], dm[col].1, epsilon = 1e-6);
            assert_relative_eq!(ja[0][col], da[col].0, epsilon = 1e-6);
            assert_relative_eq!(ja[1][col], da[col].1, epsilon = 1e-6);
        }
    }
    // Small p and small m: eq:approx's Jacobians, I and -I.
    let (_, jm, ja) = exact_jacobian(1e-5, 2e-5, 1e-5, -1e-5).unwrap();
    assert_relative_eq!(jm[0][0], 1.0, epsilon = 1e-4);
    assert_relative_eq!(jm[1][1], 1.0, epsilon = 1e-4);
    assert_relative_eq!(ja[0][0], -1.0, epsilon = 1e-4);
    assert_relative_eq!(ja[1][1], -1.0, epsilon = 1e-4);
    assert!(jm[0][1].abs() < 1e-4 && ja[1][0].abs() < 1e-4);
}

/// Error propagation checked by simulation: the reported errors of q0, u0, P0 and
/// chi0 match the scatter of 20000 noisy realizations (measurement noise and calibration noise,
/// both correlated) within 10%, for p and P0 of several percent where the exact map is not
/// the identity.
#[test]
fn reported_errors_match_monte_carlo_scatter() {
    struct Const(InstPol);
    impl FieldModel for Const {
        fn eval(&self, _: f64, _: f64) -> InstPol {
            self.0
        }
        fn contains(&self, _: f64, _: f64) -> bool {
            true
        }
    }
    let (p, phi, p0, chi0): (f64, f64, f64, f64) = (0.06, 0.5, 0.05, 1.9);
    let truth = InstPol {
        q: p * (2.0 * phi).cos(),
        u: p * (2.0 * phi).sin(),
        var_q: 0.002f64.powi(2),
        var_u: 0.0015f64.powi(2),
        cov_qu: 0.5 * 0.002 * 0.0015,
    };
    let (q1, u1) = observe(p, phi, p0, chi0, 0.0);
    let (sq, su, rho) = (0.003, 0.002, -0.3);
    let reported = Corrector::new(&Const(truth), CorrectOptions::default())
        .correct(&Measurement::at_plate(0.0, 0.0, q1, u1, sq, su, rho * sq * su))
        .unwrap();
    let mut rng = Xoshiro256PlusPlus::seed_from_u64(2006);
    let g = Normal::new(0.0, 1.0).unwrap();
    // Correlated Gaussian pairs by Cholesky.
    let draw = |rng: &mut Xoshiro256PlusPlus, s1: f64, s2: f64, r: f64| {
        let (a, b) = (g.sample(rng), g.sample(rng));
        (s1 * a, s2 * (r * a + (1.0 - r * r).sqrt() * b))
    };
    let n = 20000;
    let mut out: Vec<Corrected> = Vec::with_capacity(n);
    for _ in 0..n {
        let (dq, du) = draw(&mut rng, sq, su, rho);
        let (cq, cu) = draw(&mut rng, 0.002, 0.0015, 0.5);
        let cal = Const(InstPol { q: truth.q + cq, u: truth.u + cu, ..truth });
        let r = Corrector::new(&cal, CorrectOptions::default())
            .correct(&Measurement::at_plate(0.0, 0.0, q1 + dq, u1 + du, sq, su, 0.0))
            .unwrap();
        out.push(r);
    }
    let std = |f: &dyn Fn(&Corrected) -> f64| {
        let m = out.iter().map(f).sum::<f64>() / n as f64;
        (out.iter().map(|r| (f(r) - m).powi(2)).sum::<f64>() / (n - 1) as f64).sqrt()
    };
    let sq0 = std(&|r| r.q0);
    let su0 = std(&|r| r.u0);
    let sp0 = std(&|r| r.p0);
    let sc0 = std(&|r| {
        // Unwrap around the true angle.
        let d = (r.chi0 - chi0 + PI / 2.0).rem_euclid(PI) - PI / 2.0;
        chi0 + d
    });
    for (name, mc, rep) in [
        ("q0", sq0, reported.var_q0.sqrt()),
        ("u0", su0, reported.var_u0.sqrt()),
        ("P0", sp0, reported.sigma_p0),
        ("chi0", sc0, reported.sigma_chi0),
    ] {
        assert!((rep / mc - 1.0).abs() < 0.10, "{name}: reported {rep}, scatter {mc}");
    }
    // The calibration's error matters here: without it the reported error would be too small.
    assert!(reported.var_q0.sqrt() > 1.1 * sq);
}

/// The HWP chromatic zero angle is undone before M_I is inverted: the full dual-beam forward
/// model (M_I, then a plate whose zero is off) is inverted exactly. Undoing it after M_I leaves a
/// residual of order p * chi_offset.
#[test]
fn forward_model_with_hwp_offset_round_trip() {
    struct Const(InstPol);
    impl FieldModel for Const {
        fn eval(&self, _: f64, _: f64) -> InstPol {
            self.0
        }
        fn contains(&self, _: f64, _: f64) -> bool {
            true
        }
    }
    let (p, phi, p0, chi0, off): (f64, f64, f64, f64, f64) = (0.02, 0.7, 0.03, 2.5, 0.15);
    let (q1, u1) = observe(p, phi, p0, chi0, off);
    let model = Const(InstPol { q: p * (2.0 * phi).cos(), u: p * (2.0 * phi).sin(), ..Default::default() });
    let opts = CorrectOptions { zero_angle_deg: off.to_degrees(), ..Default::default() };
    let m = Measurement::at_plate(0.0, 0.0, q1, u1, 1e-4, 1e-4, 0.0);
    let r = Corrector::new(&model, opts).correct(&m).unwrap();
    assert!((r.p0 - p0).abs() < 1e-13);
    assert!(angle_diff(r.chi0, chi0) < 1e-11);
    // The other order: invert M_I on the plate-frame data, then rotate.
    let (a, b) = invert_exact(model.0.q, model.0.u, q1, u1).unwrap();
    let (a, b) = fit::correction::correct::rotate_chi(a, b, off);
    let wrong = (a - p0 * (2.0 * chi0).cos()).hypot(b - p0 * (2.0 * chi0).sin());
    assert!(wrong > 1e-3, "the order matters at the p * offset level: {wrong}");
    // Without the offset the angle is off by the offset.
    let r0 = Corrector::new(&model, CorrectOptions::default()).correct(&m).unwrap();
    let d0 = (r0.q0 - p0 * (2.0 * chi0).cos()).hypot(r0.u0 - p0 * (2.0 * chi0).sin());
    assert!(d0 > 0.1 * p0, "an uncorrected zero angle leaves {d0}");
}

/// Outside the field: an error naming the position; with extrapolation, a flagged result
/// with the documented inflation (f p)^2 added to the calibration variances.
#[test]
fn outside_the_field_is_an_error_or_an_inflated_extrapolation() {
    let model = Radial::fors1_v();
    let m = Measurement::at_plate(3.6, -1.0, 0.01, 0.0, 1e-4, 1e-4, 0.0);
    let e = Corrector::new(&model, CorrectOptions::default()).correct(&m).unwrap_err();
    assert_eq!(e, Error::OutsideField { x: 3.6, y: -1.0 });
    assert!(e.to_string().contains("3.6"));
    let opts = CorrectOptions { allow_extrapolation: true, ..Default::default() };
    let r = Corrector::new(&model, opts).correct(&m).unwrap();
    assert!(r.extrapolated);
    let a = model.eval(3.6, -1.0);
    let p2 = a.q * a.q + a.u * a.u;
    assert_relative_eq!(r.inst.var_q, a.var_q + 0.25 * p2, epsilon = 1e-18);
    assert_relative_eq!(r.inst.var_u, a.var_u + 0.25 * p2, epsilon = 1e-18);
    // Inside: not flagged, not inflated.
    let r = Corrector::new(&model, opts).correct(&Measurement { x: 1.0, ..m }).unwrap();
    assert!(!r.extrapolated);
    assert_eq!(r.inst.var_q, model.sigma * model.sigma);
}

/// A model with no value somewhere (a map's hole) is an error there, extrapolation or not.
#[test]
fn model_without_value_is_an_error() {
    struct Holey;
    impl FieldModel for Holey {
        fn eval(&self, x: f64, _: f64) -> InstPol {
            if x > 1.0 {
                InstPol { q: f64::NAN, u: f64::NAN, ..Default::default() }
            } else {
                InstPol { q: 0.01, ..Default::default() }
            }
        }
        fn contains(&self, x: f64, _: f64) -> bool {
            x <= 1.0
        }
    }
    let m = Measurement::at_plate(2.0, 0.0, 0.01, 0.0, 1e-4, 1e-4, 0.0);
    let opts = CorrectOptions { allow_extrapolation: true, ..Default::default() };
    let e = Corrector::new(&Holey, opts).correct(&m).unwrap_err();
    assert_eq!(e, Error::NoModelValue { x: 2.0, y: 0.0 });
    assert!(Corrector::new(&Holey, opts).correct(&Measurement { x: 0.5, ..m }).unwrap().p0 < 1e-15);
}

/// Bad input names what was wrong; batches name the row.
#[test]
fn bad_input_and_batches() {
    let model = Radial::fors1_v();
    let c = Corrector::new(&model, CorrectOptions::default());
    let good = Measurement::at_plate(1.0, 1.0, 0.01, 0.0, 1e-3, 1e-3, 0.0);
    assert!(matches!(
        c.correct(&Measurement { qu: Qu { q: f64::NAN, ..good.qu }, ..good }),
        Err(Error::NonFinite { what: "q", .. })
    ));
    assert!(matches!(
        c.correct(&Measurement::at_plate(
            good.x,
            good.y,
            good.qu.q,
            good.qu.u,
            good.qu.sigma_q(),
            -1.0,
            good.qu.cov_qu
        )),
        Err(Error::Negative { what: "sigma_u", .. })
    ));
    let mut inputs = vec![good; 10000];
    let mut out = vec![Corrected::default(); inputs.len()];
    assert_eq!(c.correct_batch(&inputs, &mut out).unwrap(), 0);
    let single = c.correct(&good).unwrap();
    assert_eq!(out[9999], single);
    let mut out2 = vec![Corrected::default(); inputs.len()];
    c.par_correct_batch(&inputs, &mut out2).unwrap();
    assert_eq!(out, out2);
    inputs[7000].x = 10.0;
    let e = c.par_correct_batch(&inputs, &mut out2).unwrap_err();
    assert!(matches!(e, Error::Row { row: 7000, .. }), "{e}");
    assert!(e.to_string().starts_with("row 7000:"));
    assert!(matches!(c.correct_batch(&inputs, &mut out2[..3]), Err(Error::Length { .. })));
    // First-order method: q0 = q1 - qi exactly, variances add.
    let fo = Corrector::new(&model, CorrectOptions { method: Method::FirstOrder, ..Default::default() });
    let r = fo.correct(&good).unwrap();
    let a = model.eval(1.0, 1.0);
    assert_eq!(r.q0, 0.01 - a.q);
    assert_relative_eq!(r.var_q0, 1e-6 + a.var_q, epsilon = 1e-18);
}

/// Edges: P0 -> 0 (angle unconstrained: capped error), p = 0 on the axis (identity map).
#[test]
fn edges_zero_polarization_and_zero_instrumental() {
    let model = Radial::fors1_v();
    let c = Corrector::new(&model, CorrectOptions::default());
    let a = model.eval(2.0, -1.0);
    let r = c.correct(&Measurement::at_plate(2.0, -1.0, a.q, a.u, 1e-3, 1e-3, 0.0)).unwrap();
    assert!(r.p0 < 1e-15);
    assert_relative_eq!(r.sigma_chi0, PI / 12f64.sqrt(), epsilon = 1e-12);
    assert!(r.sigma_p0 > 0.0 && r.sigma_p0.is_finite());
    let r = c.correct(&Measurement::at_plate(0.0, 0.0, 0.02, -0.01, 1e-3, 1e-3, 0.0)).unwrap();
    assert_eq!((r.q0, r.u0), (0.02, -0.01));
    let (p, chi) = polarization(0.02, -0.01);
    assert_eq!((r.p0, r.chi0), (p, chi));
}

/// The paper's validation geometry (section `sec:fors1`): the V polynomial predicts p = 0.96%
/// at phi = -51.9 deg (= 128.1 deg) where p(r) = 0.96%, i.e. r = 4.10', on the radial pattern
/// at polar angle -51.9 deg: (2.53', -3.23'), in the lower-right corner region of the 6.83'
/// field (the corner itself, r = 4.83', gives 1.36% at -45 deg).
#[test]
fn paper_validation_position_in_fors1_v_field() {
    let v = Radial::fors1_v();
    // Solve p(r) = 0.96% by bisection.
    let (mut lo, mut hi) = (3.0, 4.8);
    for _ in 0..60 {
        let mid = 0.5 * (lo + hi);
        if v.p(mid) < 0.0096 {
            lo = mid
        } else {
            hi = mid
        }
    }
    let r = 0.5 * (lo + hi);
    assert!((r - 4.10).abs() < 0.01, "r = {r}");
    let alpha = (-51.9f64).to_radians();
    let (x, y) = (r * alpha.cos(), r * alpha.sin());
    assert!(v.contains(x, y) && x > 2.5 && y < -3.2, "({x}, {y})");
    let (p, phi) = v.eval(x, y).p_chi();
    assert_relative_eq!(p, 0.0096, epsilon = 1e-9);
    assert_relative_eq!(phi.to_degrees(), 128.1, epsilon = 1e-9);
    // The corner itself.
    let (pc, phic) = v.eval(v.half, -v.half).p_chi();
    assert!((pc - 0.01355).abs() < 0.0001, "corner p = {pc}");
    assert_relative_eq!(phic.to_degrees(), 135.0, epsilon = 1e-9);
    // The I polynomial there predicts a different instrumental polarization (1.28%), six times
    // the paper's 0.05% fit RMS away.
    let (pi_, _) = Radial::fors1_i().eval(x, y).p_chi();
    assert!((pi_ - 0.0096).abs() > 0.003, "I prediction {pi_}");
    // An unpolarized star seen there (M_I applied to (1, 0, 0)) has exactly (p, phi).
    let s1 = partial_polarizer(p, phi) * mueller::stokes_qu(1.0, 0.0, 0.0);
    let (p1, chi1) = polarization(s1[1] / s1[0], s1[2] / s1[0]);
    assert_relative_eq!(p1, p, epsilon = 1e-15);
    assert_relative_eq!(chi1, phi, epsilon = 1e-12);
}
