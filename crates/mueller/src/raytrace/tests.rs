//! Checks of the polarization ray tracer against closed forms, symmetry and the paper.

use super::*;
use crate::fresnel::{interface, C64};
use crate::thinfilm::{stack, Layer};
use nalgebra::Vector3;

#[derive(serde::Deserialize)]
struct Wrap {
    optics: Prescription,
}

fn fors1() -> Prescription {
    let w: Wrap = toml::from_str(include_str!("../../../../instruments/fors1.toml")).unwrap();
    w.optics
}

/// One flat surface into glass of index `n`, optionally coated with one MgF2 quarter-wave.
fn single_surface(n: f64, coated: bool) -> Prescription {
    let layers = if coated {
        vec![CoatingLayer { material: None, index: Some(1.38), thickness_nm: None, quarter_wave_nm: Some(450.0) }]
    } else {
        vec![]
    };
    Prescription {
        description: "test".into(),
        focal_ratio: 10.0,
        field_scale_arcsec_per_mm: 1.0,
        field_radius_arcmin: 1.0,
        exit_pupil_distance_mm: None,
        central_obstruction: 0.0,
        first_surface_distance_mm: 10.0,
        default_coating: None,
        glasses: vec![GlassDef {
            name: "test glass".into(),
            sellmeier_b: None,
            sellmeier_c: None,
            cauchy: None,
            index: Some(n),
        }],
        surfaces: vec![Surface {
            name: "S".into(),
            radius_mm: None,
            conic: 0.0,
            thickness_mm: 10.0,
            glass: "test glass".into(),
            clear_aperture_mm: 100.0,
            coating: Some(Coating { layers }),
        }],
    }
}

#[test]
fn on_axis_polarization_is_zero() {
    let c = fors1().compile(554.0).unwrap();
    let f = c.field_point(0.0, 0.0, &Sampling::default(), None).unwrap();
    assert!(f.p < 1e-14, "p on axis = {}", f.p);
    assert!(c.chief_ray(0.0, 0.0, None).unwrap().p < 1e-15);
}

#[test]
fn pattern_is_radial_everywhere() {
    // sec:fors1 / fig:radprofV lower panel: phi = alpha (mod 180).
    let c = fors1().compile(554.0).unwrap();
    let s = Sampling::default();
    for k in 0..12 {
        let alpha = (k as f64 * 31.0 + 7.0).to_radians();
        for r in [0.7, 2.5, 4.5] {
            let f = c.field_point(r * alpha.cos(), r * alpha.sin(), &s, None).unwrap();
            assert!(f.phi_rel().abs() < 1e-3, "r {r} alpha {alpha}: phi - alpha = {}", f.phi_rel());
            assert!((0.0..std::f64::consts::PI).contains(&f.phi));
        }
    }
}

#[test]
fn p_grows_as_r_squared_near_the_axis() {
    let c = fors1().compile(554.0).unwrap();
    let s = Sampling::default();
    let p = |r: f64| c.field_point(r, 0.0, &s, None).unwrap().p;
    let ratios: Vec<f64> = [0.4, 0.2, 0.1, 0.05].iter().map(|&r| p(2.0 * r) / p(r)).collect();
    // Tends to 4 (p = a r^2 + b r^4 + ...), monotonically as r -> 0.
    assert!((ratios[3] - 4.0).abs() < 2e-3, "{ratios:?}");
    for w in ratios.windows(2) {
        assert!((w[1] - 4.0).abs() <= (w[0] - 4.0).abs() + 1e-6, "{ratios:?}");
    }
}

#[test]
fn single_uncoated_surface_at_30_deg_gives_sec_cause_1_7_percent() {
    let c = single_surface(1.5, false).compile(550.0).unwrap();
    let a = 30f64.to_radians();
    let (j, k) = c.trace_ray(Vector3::zeros(), Vector3::new(a.sin(), 0.0, a.cos()), None, |_| {}).unwrap();
    let m = crate::jones_to_mueller(&j);
    // Snell: the refracted direction.
    assert!((k.x - a.sin() / 1.5).abs() < 1e-15);
    // Textbook Fresnel transmittances (Born & Wolf 1.5), written out here.
    let t = (a.sin() / 1.5).asin();
    let f = 1.5 * t.cos() / a.cos();
    let ts = f * (2.0 * a.cos() / (a.cos() + 1.5 * t.cos())).powi(2);
    let tp = f * (2.0 * a.cos() / (1.5 * a.cos() + t.cos())).powi(2);
    let d = (tp - ts) / (tp + ts);
    let p = m[(1, 0)].hypot(m[(2, 0)]) / m[(0, 0)];
    assert!((p - d).abs() < 1e-13, "{p} vs {d}");
    assert!((p - 0.017).abs() < 5e-4, "sec:cause: about 1.7%, got {p}");
    // Along the plane of incidence (x-z): Q > 0.
    assert!(m[(1, 0)] > 0.0 && m[(2, 0)].abs() < 1e-15);
    assert!((m[(0, 0)] - 0.5 * (ts + tp)).abs() < 1e-14);
}

#[test]
fn pupil_integrated_agrees_with_chief_ray_at_mid_field() {
    let c = fors1().compile(554.0).unwrap();
    for r in [2.4, 3.0] {
        let f = c.field_point(r, 0.0, &Sampling::default(), None).unwrap();
        let ch = c.chief_ray(r, 0.0, None).unwrap();
        assert!((f.p / ch.p - 1.0).abs() < 0.01, "r {r}: pupil {} chief {}", f.p, ch.p);
    }
}

#[test]
fn energy_is_conserved_at_every_intersection() {
    for p in [fors1(), single_surface(1.5, false), single_surface(1.7, true)] {
        for lam in [450.0, 800.0] {
            let c = p.compile(lam).unwrap();
            let mut n = 0;
            for (x, dx) in [(0.0, 0.0), (2.0, 0.03), (4.5, -0.02), (3.0, 0.3)] {
                let o = Vector3::new(x * 31.7, 0.3 * x, 0.0);
                c.trace_ray(o, Vector3::new(dx, 0.01, 1.0), None, |i| {
                    assert!(i.lossless);
                    let k = &i.coefficients;
                    assert!((k.transmittance_s + k.reflectance_s - 1.0).abs() < 1e-12, "s at {}", i.surface);
                    assert!((k.transmittance_p + k.reflectance_p - 1.0).abs() < 1e-12, "p at {}", i.surface);
                    n += 1;
                });
            }
            assert!(n >= p.surfaces.len(), "{n} intersections");
        }
    }
}

/// Airy summation for one layer, from textbook Fresnel coefficients of its two interfaces
/// (Born & Wolf 1.6): the transmitted diattenuation, written independently of thinfilm.
fn airy_diattenuation(n0: f64, n1: f64, d: f64, ns: f64, lam: f64, a: f64) -> f64 {
    let t1 = (n0 * a.sin() / n1).asin();
    let t2 = (n0 * a.sin() / ns).asin();
    let b = 2.0 * std::f64::consts::PI * n1 * d * t1.cos() / lam;
    let e = C64::new(0.0, 2.0 * b).exp();
    let tpow = |s: bool| {
        let f = |na: f64, ta: f64, nb: f64, tb: f64| {
            let (x, y) = if s { (na * ta.cos(), nb * tb.cos()) } else { (nb * ta.cos(), na * tb.cos()) };
            ((x - y) / (x + y), 2.0 * na * ta.cos() / (x + y))
        };
        let (r01, t01) = f(n0, a, n1, t1);
        let (r12, t12) = f(n1, t1, ns, t2);
        let t = t01 * t12 / (1.0 + r01 * r12 * e);
        ns * t2.cos() / (n0 * a.cos()) * t.norm_sqr()
    };
    let (ts, tp) = (tpow(true), tpow(false));
    (tp - ts) / (tp + ts)
}

#[test]
fn coated_diattenuation_matches_closed_form_single_layer() {
    let presc = fors1();
    let mgf2 = catalog("MgF2").unwrap();
    let silica = catalog("fused silica").unwrap();
    let d = 450.0 / (4.0 * mgf2.index(450.0));
    for lam in [450.0, 554.0, 800.0] {
        let c = presc.compile(lam).unwrap();
        let mut checked = 0;
        c.trace_ray(Vector3::new(140.0, 0.0, 0.0), Vector3::new(0.005, 0.0, 1.0), None, |i| {
            if i.surface == 0 {
                let want = airy_diattenuation(1.0, mgf2.index(lam), d, silica.index(lam), lam, i.aoi);
                assert!((i.coefficients.diattenuation_t() - want).abs() < 1e-12);
                assert!(want > 1e-4);
                checked += 1;
            }
        });
        assert_eq!(checked, 1);
    }
    // And the coating does reduce the bare-glass diattenuation at the same angle.
    let a = 20f64.to_radians();
    let bare = interface(1.0, C64::new(1.46, 0.0), a).unwrap().diattenuation_t();
    let coated = stack(1.0, &[Layer::quarter_wave(1.38, 450.0)], C64::new(1.46, 0.0), 554.0, a).unwrap();
    assert!(coated.diattenuation_t() < bare);
}

/// sec:cause: p(lambda)/p(550) ~ 0.02 + 1.73e-3 lambda from the FORS1 ray tracing.
/// This FORS1-like approximation gives p(800)/p(550) = 1.41 (paper 1.40) and
/// p(450)/p(550) = 0.88 (paper 0.80): the single MgF2 layer has its best transmission
/// diattenuation near 450 nm, so this model flattens below 500 nm where the paper's straight
/// line keeps falling. Tolerance stated: slope of the same sign, ratios within 15%.
#[test]
fn chromatic_ratios_follow_the_paper_law() {
    let p = fors1();
    let s = Sampling::default();
    let law = p.wavelength_law(4.5, &s, &[450.0, 550.0, 650.0, 800.0]).unwrap();
    let paper = |l: f64| PAPER_LAW_A + PAPER_LAW_B * l;
    assert!(law.b > 0.0, "{law:?}");
    for (l, ratio) in &law.samples {
        if *l == 550.0 {
            assert!((ratio - 1.0).abs() < 1e-15);
            continue;
        }
        assert!((ratio / paper(*l) - 1.0).abs() < 0.15, "{l} nm: {ratio} vs paper {}", paper(*l));
    }
}

#[test]
fn pupil_sampling_converges() {
    // Doubling the pupil rays at the default density changes p by < 1e-5 (absolute).
    let c = fors1().compile(554.0).unwrap();
    let s1 = Sampling::default();
    let s2 = Sampling::from_rays(2 * Sampling::DEFAULT_RAYS);
    assert!(s2.rays() as f64 > 1.8 * s1.rays() as f64);
    // 4.8' is vignetted by the clear apertures, where the quadrature converges slowest.
    for r in [1.0, 3.0, 4.5, 4.8] {
        let a = c.field_point(r, 0.0, &s1, None).unwrap().p;
        let b = c.field_point(r, 0.0, &s2, None).unwrap().p;
        assert!((a - b).abs() < 1e-5, "r {r}: {a} vs {b}");
    }
}

#[test]
fn fors1_like_collimator_is_of_the_papers_size() {
    // sec:fors1: V-band p(r) = 0.012 r + 0.046 r^2 + 0.002 r^3 (percent, r arcmin): 1.17% at
    // 4.5'. "Plausible, not fitted": within a factor 1.5.
    let c = fors1().compile(554.0).unwrap();
    let p = c.field_point(4.5, 0.0, &Sampling::default(), None).unwrap().p;
    let v = 0.01 * (0.012 * 4.5 + 0.046 * 4.5f64.powi(2) + 0.002 * 4.5f64.powi(3));
    assert!(p > v / 1.5 && p < v * 1.5, "{p} vs {v}");
    // The per-surface contributions add up roughly (the effect is "roughly additive").
    let per = c.per_surface(4.5, 0.0, &Sampling::default()).unwrap();
    let sum: f64 = per.iter().map(|f| f.p).sum();
    assert!((sum / p - 1.0).abs() < 0.1, "sum {sum} vs {p}");
}

#[test]
fn radial_fit_recovers_a_polynomial() {
    let r: Vec<f64> = (0..20).map(|i| 0.25 * i as f64).collect();
    let p: Vec<f64> = r.iter().map(|&r| 0.012 * r + 0.046 * r * r + 0.002 * r * r * r).collect();
    let f = fit_radial(&r, &p, &[1, 2, 3]).unwrap();
    for (c, want) in f.coefficients.iter().zip([0.012, 0.046, 0.002]) {
        assert!((c - want).abs() < 1e-12);
    }
    assert!(fit_radial(&r[..2], &p[..2], &[1, 2, 3]).is_err());
}

#[test]
fn field_file_interpolates_radially() {
    let c = fors1().compile(554.0).unwrap();
    let radii = [0.0, 1.0, 2.0, 3.0];
    let pts = c.profile(&radii, 0.0, &Sampling::default(), None).unwrap();
    let poly = fit_radial(&radii, &pts.iter().map(|p| p.p).collect::<Vec<_>>(), &[2, 4]).unwrap();
    let ff = FieldFile::new("test", 554.0, &pts, poly);
    let (p, phi) = ff.eval(0.0, 2.0);
    assert!((p - pts[2].p).abs() < 1e-15);
    assert!((phi - std::f64::consts::FRAC_PI_2).abs() < 1e-3);
    let (p, _) = ff.eval(1.5 * 0.6, 1.5 * 0.8);
    assert!((p - 0.5 * (pts[1].p + pts[2].p)).abs() < 1e-12);
}

#[test]
fn bad_prescriptions_are_named() {
    let mut p = fors1();
    p.surfaces[2].glass = "unobtainium".into();
    let e = p.validate().unwrap_err().to_string();
    assert!(e.contains("surfaces[2]") && e.contains("unobtainium"), "{e}");
    let mut p = fors1();
    p.surfaces[1].radius_mm = Some(0.0);
    assert!(p.validate().unwrap_err().to_string().contains("radius_mm"));
    let mut p = fors1();
    p.default_coating = Some(Coating {
        layers: vec![CoatingLayer {
            material: Some("MgF2".into()),
            index: None,
            thickness_nm: None,
            quarter_wave_nm: None,
        }],
    });
    assert!(p.validate().unwrap_err().to_string().contains("default_coating"));
    let text = include_str!("../../../../instruments/fors1.toml")
        .replace("clear_aperture_mm = 390.0", "clear_aperture = 390.0");
    assert!(toml::from_str::<Wrap>(&text).is_err());
    assert!(fors1().compile(50.0).is_err());
}
