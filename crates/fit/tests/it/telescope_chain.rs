//! The telescope model in a calibration file and the correction through the whole chain
//! (telescope, then field): the fitted EFOSC2 model written, read back and applied to the real
//! unpolarized standards (leave-one-out: each star corrected with the model fitted to the
//! others of its band, through the file), a polarized standard simulated through a
//! Jones-matrix chain written here (M3 by the textbook Fresnel equations, a field partial
//! polarizer as a diattenuator's Jones matrix, a parallactic-angle track summed finely), and
//! malformed telescope HDUs refused by keyword.

use crate::common;
use common::jones::{mul, rot, C, J};
use fit::correction::correct::{CorrectOptions, Corrector, Measurement};
use fit::files::calibration::load;
use fit::models::model::{FieldModel, InstPol};
use fit::telescope::cal::{correct_chain, save_alone, save_with_field};
use fit::telescope::{fit_band, read_observations, FitOptions, ModelKind, TelescopeFit, Track};
use mueller::mirror::MetalTable;
use rand::SeedableRng;
use rand_distr::{Distribution, Normal};
use std::path::PathBuf;

fn data_dir() -> Option<PathBuf> {
    crate::common::shared_data::shared_data("efosc2-standards", &[], "the EFOSC2 real-data chain tests")
}

const BANDS: [&str; 5] = ["pu", "pb", "pv", "pr", "pi"];

// ---- An independent Jones chain, written here ----

/// Sky to instrument of the Wiersema chain for a metal of index `n` at 45 deg: Rot(offset)
/// Rot(-pa) M3 Rot(-pa), M3 = diag(r_s, r_p) (textbook Fresnel amplitudes, Born & Wolf 14.2).
fn chain(n: C, offset: f64, pa: f64) -> J {
    let i = std::f64::consts::FRAC_PI_4;
    let w = (n * n - C::new(i.sin().powi(2), 0.0)).sqrt();
    let rs = (C::new(i.cos(), 0.0) - w) / (C::new(i.cos(), 0.0) + w);
    let rp = (n * n * i.cos() - w) / (n * n * i.cos() + w);
    let m3: J = [[rs, C::new(0.0, 0.0)], [C::new(0.0, 0.0), rp]];
    mul(&rot(offset), &mul(&rot(-pa), &mul(&m3, &rot(-pa))))
}
/// The paper's instrumental partial polarizer (section `sec:instr`) as what it is: light
/// through clear glass (weight `1 - p`) added incoherently to light through an ideal polarizer
/// at `phi` (weight `2p`); the Stokes vector of `c` after it.
fn partial_after(p: f64, phi: f64, c: &J) -> [f64; 4] {
    let d: J = [[C::new(1.0, 0.0), C::new(0.0, 0.0)], [C::new(0.0, 0.0), C::new(0.0, 0.0)]];
    let pol = mul(&rot(-phi), &mul(&d, &rot(phi)));
    let (a, b) = (through(&rot(0.0), c), through(&pol, c));
    [0, 1, 2, 3].map(|i| (1.0 - p) * a[i] + 2.0 * p * b[i])
}
/// `J C J^H` as a coherency matrix.
fn transform(j: &J, c: &J) -> J {
    let jh: J = [[j[0][0].conj(), j[1][0].conj()], [j[0][1].conj(), j[1][1].conj()]];
    mul(j, &mul(c, &jh))
}
/// Coherency matrix <E E^H> of Stokes (I, Q, U, V): Q = |Ex|^2 - |Ey|^2, U = 2 Re(Ex* Ey),
/// V = 2 Im(Ex* Ey).
fn coherency(s: [f64; 4]) -> J {
    let h = 0.5;
    [
        [C::new(h * (s[0] + s[1]), 0.0), C::new(h * s[2], -h * s[3])],
        [C::new(h * s[2], h * s[3]), C::new(h * (s[0] - s[1]), 0.0)],
    ]
}
/// Stokes of J C J^H.
fn through(j: &J, c: &J) -> [f64; 4] {
    let jh: J = [[j[0][0].conj(), j[1][0].conj()], [j[0][1].conj(), j[1][1].conj()]];
    let o = mul(j, &mul(c, &jh));
    [o[0][0].re + o[1][1].re, o[0][0].re - o[1][1].re, 2.0 * o[1][0].re, 2.0 * o[1][0].im]
}

fn tmp() -> tempfile::TempDir {
    tempfile::tempdir().unwrap()
}

fn fit_v(obs: &[fit::telescope::Observation], table: &MetalTable) -> TelescopeFit {
    fit_band(ModelKind::Wiersema, obs, table, &FitOptions::default()).unwrap()
}

#[test]
fn real_efosc2_standards_leave_one_out_through_the_calibration_file_are_unpolarized() {
    let Some(dir) = data_dir() else { return };
    let table = MetalTable::read(&dir.join("METALS_Aluminium_Rakic.txt")).unwrap();
    let t = tmp();
    let (mut n, mut within, mut raw, mut cor) = (0, 0, vec![], vec![]);
    for stem in BANDS {
        let obs = read_observations(&dir.join(format!("{stem}_standards.txt"))).unwrap();
        for k in 0..obs.len() {
            let rest: Vec<_> = obs.iter().enumerate().filter(|(i, _)| *i != k).map(|(_, o)| o.clone()).collect();
            let f = fit_v(&rest, &table);
            let path = t.path().join(format!("{stem}_{k}.fits"));
            save_alone(&path, "EFOSC2", &f, "Rakic 1995", &[], None).unwrap();
            let l = load(&path).unwrap();
            assert!(l.field.is_none());
            assert_eq!(l.kind(), fit::files::calibration::Kind::Telescope);
            let tel = l.telescope.unwrap();
            let o = &obs[k];
            // The measurement errors scaled as the fit scaled its own (the standards scatter
            // by sqrt(chi2/dof) more than their errors say).
            let s = tel.chi2_reduced.max(1.0).sqrt();
            let m = Measurement::at_plate(0.0, 0.0, o.qu.q, o.qu.u, o.qu.sigma_q() * s, o.qu.sigma_u() * s, 0.0);
            let r = correct_chain::<dyn FieldModel>(None, &tel, &o.band, &m, Track::at(o.parallactic), None).unwrap();
            let c = r.corrected;
            // 2-dof chi^2 of (q0, u0) against zero with the full covariance.
            let det = c.var_q0 * c.var_u0 - c.cov_qu0 * c.cov_qu0;
            let z2 = (c.q0 * c.q0 * c.var_u0 - 2.0 * c.q0 * c.u0 * c.cov_qu0 + c.u0 * c.u0 * c.var_q0) / det;
            n += 1;
            within += (z2 < 11.83) as usize; // 3 sigma
            raw.push(o.qu.q.hypot(o.qu.u));
            cor.push(c.p0);
            // What the telescope removes is what the star showed, to the scatter.
            assert!((r.q_tel - o.qu.q).hypot(r.u_tel - o.qu.u) < 0.012, "{}: {} {}", o.source, r.q_tel, r.u_tel);
        }
    }
    raw.sort_by(f64::total_cmp);
    cor.sort_by(f64::total_cmp);
    let (mr, mc) = (raw[n / 2], cor[n / 2]);
    eprintln!(
        "through the file: {within} of {n} within 3 sigma of P = 0; median P {:.2}% -> {:.3}%",
        100.0 * mr,
        100.0 * mc
    );
    assert!(mr > 0.025 && mc < 0.003, "{mr} {mc}");
    assert!(within as f64 >= 0.85 * n as f64, "{within} of {n}");
}

#[test]
fn polarized_standard_through_a_night_comes_back_with_its_catalogued_p_and_chi() {
    // The truth: the V-band model fitted to the real EFOSC2 standards when present (else a
    // factor 0.85, offset 40 deg, the V values of docs/guide/standards-and-telescope.md),
    // applied by the Jones chain above to Hiltner 652 (V: P = 6.25 +- 0.01 %, chi = 179.18 +- 0.20
    // deg, Fossati et al. 2007, in instruments/standards.toml), each exposure a 20-min track
    // summed finely.
    let table = MetalTable::builtin("aluminium").unwrap();
    let (factor, offset) = match data_dir() {
        Some(dir) => {
            let obs = read_observations(&dir.join("pv_standards.txt")).unwrap();
            let f = fit_v(&obs, &table);
            (f.param("factor").unwrap().value, f.param("offset").unwrap().value)
        }
        None => (0.85, 40f64.to_radians()),
    };
    let std = fit::standards::Standards::builtin().unwrap();
    let v = std.star("Hiltner 652").unwrap().band("V").unwrap().clone();
    let (p_true, chi_true) = (v.p_percent / 100.0, v.chi_deg.unwrap().to_radians());
    let n_idx = table.index(0.55).unwrap();
    // Observations of unpolarized stars over the night to fit the model on, then the
    // polarized star at other angles.
    let sigma = 0.0008;
    let mut rng = rand_xoshiro::Xoshiro256PlusPlus::seed_from_u64(17);
    let g = Normal::new(0.0, sigma).unwrap();
    let measure = |s: [f64; 4], a: f64, b: f64| -> (f64, f64) {
        let c = coherency(s);
        let mut acc = [0.0; 4];
        let k = 200;
        for j in 0..k {
            let pa = a + (b - a) * (j as f64 + 0.5) / k as f64;
            let o = through(&chain(n_idx * factor, offset, pa), &c);
            for i in 0..4 {
                acc[i] += o[i];
            }
        }
        (acc[1] / acc[0], acc[2] / acc[0])
    };
    let mut obs = vec![];
    for k in 0..30 {
        let pa = (-170.0 + 11.5 * k as f64).to_radians();
        let (q, u) = measure([1.0, 0.0, 0.0, 0.0], pa, pa);
        obs.push(fit::telescope::Observation {
            star: format!("WD{k}"),
            parallactic: pa,
            qu: mueller::Qu::from_sigmas(q + g.sample(&mut rng), u + g.sample(&mut rng), sigma, sigma, 0.0),
            wavelength_um: 0.55,
            band: "V".into(),
            rotator: 0.0,
            sky: (0.0, 0.0),
            source: format!("sim:{k}"),
        });
    }
    let f = fit_v(&obs, &table);
    let t = tmp();
    let path = t.path().join("tel.fits");
    save_alone(&path, "EFOSC2", &f, "aluminium", &[], None).unwrap();
    let tel = load(&path).unwrap().telescope.unwrap();
    let sky = [1.0, p_true * (2.0 * chi_true).cos(), p_true * (2.0 * chi_true).sin(), 0.0];
    let (mut chi2, mut n) = (0.0, 0);
    for k in 0..12 {
        // Exposures of 5 deg of parallactic angle each, around the night.
        let a = (-150.0 + 27.0 * k as f64).to_radians();
        let b = a + 5f64.to_radians();
        let (q, u) = measure(sky, a, b);
        let m = Measurement::at_plate(0.0, 0.0, q + g.sample(&mut rng), u + g.sample(&mut rng), sigma, sigma, 0.0);
        let c = correct_chain::<dyn FieldModel>(None, &tel, "V", &m, Track { start: a, end: b, rotator: 0.0 }, None)
            .unwrap()
            .corrected;
        let dchi = mueller::wrap_half_pi(c.chi0 - chi_true);
        chi2 += ((c.p0 - p_true) / c.sigma_p0).powi(2) + (dchi / c.sigma_chi0).powi(2);
        n += 2;
        assert!((c.p0 - p_true).abs() < 4.0 * c.sigma_p0, "P {} +- {} vs {p_true}", c.p0, c.sigma_p0);
        assert!(dchi.abs() < 4.0 * c.sigma_chi0, "chi {} +- {}", c.chi0.to_degrees(), c.sigma_chi0.to_degrees());
        // Uncorrected, the star is off by the M3's few percent.
        assert!((q.hypot(u) - p_true).abs() > 0.003 || mueller::wrap_half_pi(0.5 * u.atan2(q) - chi_true).abs() > 0.05);
    }
    assert!(chi2 < n as f64 + 4.0 * (2.0 * n as f64).sqrt(), "chi2 {chi2} for {n} terms");
}

/// A uniform field of instrumental polarization `p` along `phi`, known exactly.
struct Flat {
    p: f64,
    phi: f64,
}
impl FieldModel for Flat {
    fn eval(&self, _x: f64, _y: f64) -> InstPol {
        InstPol {
            q: self.p * (2.0 * self.phi).cos(),
            u: self.p * (2.0 * self.phi).sin(),
            var_q: 0.0,
            var_u: 0.0,
            cov_qu: 0.0,
        }
    }
    fn contains(&self, _x: f64, _y: f64) -> bool {
        true
    }
}

#[test]
fn the_chain_inverts_the_field_after_the_telescope_as_jones_matrices_say() {
    // Noise-free: sky -> M3 chain -> field partial polarizer (Jones, written above), then
    // correct_chain with the same telescope and field: the sky comes back. The other order
    // (telescope inverted first) would not.
    let table = MetalTable::builtin("aluminium").unwrap();
    let n = table.index(0.55).unwrap();
    let tel = TelescopeFit {
        model: ModelKind::Wiersema,
        bands: vec![(
            "V".into(),
            fit::telescope::BandModel {
                wavelength_um: 0.55,
                index: n,
                factor: 0.9,
                thickness_nm: 0.0,
                offset: 0.5,
                q0: 0.0,
                u0: 0.0,
            },
        )],
        params: vec![
            fit::telescope::Param { name: "factor".into(), value: 0.9, sigma: 0.0 },
            fit::telescope::Param { name: "offset".into(), value: 0.5, sigma: 0.0 },
        ],
        covariance: vec![vec![0.0; 2]; 2],
        chi2: 0.0,
        dof: 1,
        chi2_reduced: 1.0,
        error_scaling: fit::ErrorScaling::Conservative,
        error_factor: 1.0,
        rms_q: 0.0,
        rms_u: 0.0,
        with_rotator: false,
        minima: vec![],
        points: vec![],
    };
    let field = Flat { p: 0.012, phi: 0.3 };
    let cor = Corrector::new(&field, CorrectOptions::default());
    for &(pq, chi, pa) in &[(0.0, 0.0, 0.4), (0.05, 1.0, -2.0), (0.1, 2.5, 2.9)] {
        let sky = [1.0, pq * (2.0f64 * chi).cos(), pq * (2.0f64 * chi).sin(), 0.0];
        let o = partial_after(field.p, field.phi, &transform(&chain(n * 0.9, 0.5, pa), &coherency(sky)));
        let m = Measurement::at_plate(0.1, 0.2, o[1] / o[0], o[2] / o[0], 1e-4, 1e-4, 0.0);
        let c = correct_chain(Some(&cor), &tel, "V", &m, Track::at(pa), Some(0.0)).unwrap().corrected;
        assert!((c.q0 - sky[1]).abs() < 1e-9 && (c.u0 - sky[2]).abs() < 1e-9, "{} {} vs {:?}", c.q0, c.u0, sky);
        // The inverse order differs by terms of size p_field x P_M3.
        let [qa, ua, ..] = tel.correct_cov("V", m.qu.q, m.qu.u, [0.0; 3], Track::at(pa), false).unwrap();
        let (qb, ub) =
            fit::correction::correct::invert_exact(field.eval(0.0, 0.0).q, field.eval(0.0, 0.0).u, qa, ua).unwrap();
        assert!((qb - sky[1]).hypot(ub - sky[2]) > 1e-5, "order should matter");
        // Errors: the measurement's 1e-4 passes through nearly unchanged (|M| ~ 1).
        assert!(c.var_q0.sqrt() > 0.9e-4 && c.var_q0.sqrt() < 1.2e-4, "{}", c.var_q0.sqrt());

        // The same light read by a plate whose zero angle z makes every chi smaller by z (the
        // plate frame, written here as the rotation of (q, u) by -2z): the chain given z
        // brings it into the models' sky frame first and gives the sky back; given 0 it
        // corrects with models turned by z against the data, off by about 2 z P.
        let z = 7f64.to_radians();
        let (s2, c2) = (2.0 * z).sin_cos();
        let (qp, up) = (c2 * m.qu.q + s2 * m.qu.u, -s2 * m.qu.q + c2 * m.qu.u);
        // Unequal errors with a covariance, to see them turned back too.
        let (vq, vu, cv) = (c2 * c2 * 1e-8 + s2 * s2 * 4e-8, s2 * s2 * 1e-8 + c2 * c2 * 4e-8, s2 * c2 * 3e-8);
        let plate = Measurement::at_plate(m.x, m.y, qp, up, vq.sqrt(), vu.sqrt(), cv);
        let z_deg = z.to_degrees();
        let in_z = Corrector::new(&field, CorrectOptions { zero_angle_deg: z_deg, ..CorrectOptions::default() });
        let c = correct_chain(Some(&in_z), &tel, "V", &plate, Track::at(pa), Some(z_deg)).unwrap().corrected;
        assert!((c.q0 - sky[1]).abs() < 1e-9 && (c.u0 - sky[2]).abs() < 1e-9, "{} {} vs {:?}", c.q0, c.u0, sky);
        let unturned = correct_chain(Some(&cor), &tel, "V", &plate, Track::at(pa), Some(0.0)).unwrap().corrected;
        let off = (unturned.q0 - sky[1]).hypot(unturned.u0 - sky[2]);
        let p_meas = m.qu.q.hypot(m.qu.u);
        assert!(off > 0.5 * 2.0 * z.sin() * p_meas, "zero angle ignored: off by {off:e} only");
        // Errors turned back into the sky frame: the same as those of the measurement made
        // there with errors (1e-4, 2e-4) along q, u and no covariance.
        let c0 =
            correct_chain::<dyn FieldModel>(None, &tel, "V", &plate, Track::at(pa), Some(z_deg)).unwrap().corrected;
        let there = Measurement::at_plate(m.x, m.y, m.qu.q, m.qu.u, 1e-4, 2e-4, 0.0);
        let c1 = correct_chain::<dyn FieldModel>(None, &tel, "V", &there, Track::at(pa), None).unwrap().corrected;
        for (a, b) in [(c0.var_q0, c1.var_q0), (c0.var_u0, c1.var_u0), (c0.cov_qu0, c1.cov_qu0)] {
            assert!((a - b).abs() < 1e-9 * c1.var_u0, "{a:e} vs {b:e}");
        }
        assert!((c0.q0 - c1.q0).abs() < 1e-12 && (c0.u0 - c1.u0).abs() < 1e-12);
        // A field corrector in another sky frame than the chain's would undo the field in one
        // frame and the telescope in another: refused.
        assert!(correct_chain(Some(&cor), &tel, "V", &plate, Track::at(pa), Some(z_deg)).is_err());
        assert!(correct_chain(Some(&in_z), &tel, "V", &plate, Track::at(pa), None).is_err());
    }
}

#[test]
fn telescope_beside_a_field_model_and_bad_hdus() {
    let table = MetalTable::builtin("aluminium").unwrap();
    let obs: Vec<_> = (0..12)
        .map(|k| {
            let pa = (-160.0 + 29.0 * k as f64).to_radians();
            let a = 2.0 * (0.6 - pa);
            fit::telescope::Observation {
                star: format!("S{k}"),
                parallactic: pa,
                qu: mueller::Qu::from_sigmas(
                    0.035 * a.cos() + 1e-4 * ((k * 7 % 5) as f64 - 2.0),
                    -0.035 * a.sin() + 1e-4 * ((k * 3 % 5) as f64 - 2.0),
                    2e-4,
                    2e-4,
                    0.0,
                ),
                wavelength_um: 0.55,
                band: "V".into(),
                rotator: 0.0,
                sky: (0.0, 0.0),
                source: format!("t:{k}"),
            }
        })
        .collect();
    let f = fit_v(&obs, &table);
    let t = tmp();
    // Beside a field model: the paper's V field as a calibration, then the telescope HDU.
    let cal = crate::common::given::given_calibration(
        "EFOSC2",
        "V",
        550.0,
        0.0,
        fit::Model::Radial(fit::RadialModel {
            first_power: 0,
            coeffs: vec![2e-4, 0.0, 3e-4],
            centre: [0.0, 0.0],
            centre_free: false,
            cov: vec![0.0; 25],
            scaling: None,
        }),
        2.0,
    );
    let path = t.path().join("both.fits");
    save_with_field(&path, &cal, &f, "aluminium").unwrap();
    let l = load(&path).unwrap();
    assert_eq!(l.kind(), fit::files::calibration::Kind::FieldAndTelescope);
    assert_eq!(l.instrument, cal.instrument);
    let field = l.field.expect("the field model is still there");
    assert_eq!(field.model.kind(), cal.model.kind());
    let tel = l.telescope.unwrap();
    for (a, b) in tel.params.iter().zip(&f.params) {
        assert!((a.value - b.value).abs() <= 1e-12 * b.value.abs().max(1.0) && a.name == b.name);
    }
    // A telescope-only file is refused by the field reader, by name.
    let alone = t.path().join("alone.fits");
    save_alone(&alone, "EFOSC2", &f, "aluminium", &["pv_standards.txt".into()], None).unwrap();
    let e = fit::Calibration::load(&alone).unwrap_err().to_string();
    assert!(e.contains("only a telescope model"), "{e}");
    // Malformed HDUs (written by hand, e.g.) are refused by keyword or row.
    let mut extra = f.clone();
    extra.params.push(fit::telescope::Param { name: "spare".into(), value: 0.0, sigma: 0.0 });
    extra.covariance = vec![vec![0.0; 3]; 3];
    let mut neg = f.clone();
    neg.bands[0].1.factor = -0.5;
    for (bad, key) in [(extra, "HIERARCH IP TEL NPAR = 3"), (neg, "row 1 (band V)")] {
        let p = t.path().join("bad.fits");
        save_alone(&p, "EFOSC2", &bad, "aluminium", &[], None).unwrap();
        let e = load(&p).unwrap_err().to_string();
        assert!(e.contains(key) && e.contains("bad.fits"), "{key}: {e}");
    }
    // A covariance that is none (written by hand, e.g.): refused by keyword.
    let p = t.path().join("badcov.fits");
    let mut bad = f.clone();
    bad.covariance[0][1] = 1.0;
    save_alone(&p, "EFOSC2", &bad, "aluminium", &[], None).unwrap();
    let e = load(&p).unwrap_err().to_string();
    assert!(e.contains("TEL COV 0 1") && e.contains("correlation"), "{e}");
}
