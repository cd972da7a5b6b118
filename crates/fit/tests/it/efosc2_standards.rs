//! Real data: the EFOSC2 unpolarized standards of 2018 (../shared/data/efosc2-standards/,
//! Wiersema et al. 2018's method and group) fitted with the Wiersema-type model of
//! `fit::telescope`, against a reference computed here by a separate implementation: its own
//! file reading and interpolation of the aluminium table, a Jones-matrix chain
//! `Rot(offset) Rot(-pa) M3 Rot(-pa)` on unpolarized light (two incoherent orthogonal
//! fields), a Nelder-Mead minimization of chi^2 and errors from its numerical Hessian.

use crate::common;
use common::jones::{mul, rot, C, J};
use fit::telescope::{fit_band, fit_joint, read_observations, FitOptions, ModelKind};
use fit::ErrorScaling;
use mueller::mirror::MetalTable;
use std::path::{Path, PathBuf};

fn data_dir() -> Option<PathBuf> {
    crate::common::shared_data::shared_data("efosc2-standards", &[], "the EFOSC2 real-data tests")
}

const BANDS: [(&str, &str); 5] = [("U", "pu"), ("B", "pb"), ("V", "pv"), ("R", "pr"), ("i", "pi")];

/// (pa_deg, q, sq, u, su, wavelength) rows, read here with no help from instpol.
fn rows(path: &PathBuf) -> Vec<[f64; 6]> {
    std::fs::read_to_string(path)
        .unwrap()
        .lines()
        .filter(|l| !l.trim().is_empty())
        .map(|l| {
            let f: Vec<f64> = l.split(',').skip(1).map(|x| x.trim().parse().unwrap()).collect();
            [f[0], f[1], f[2], f[3], f[4], f[5]]
        })
        .collect()
}

/// n, k of the shared Rakic table, linear interpolation between the bracketing rows.
fn rakic(dir: &Path, w: f64) -> C {
    let t: Vec<[f64; 3]> = std::fs::read_to_string(dir.join("METALS_Aluminium_Rakic.txt"))
        .unwrap()
        .lines()
        .skip(1)
        .map(|l| {
            let f: Vec<f64> = l.split(',').map(|x| x.trim().parse().unwrap()).collect();
            [f[0], f[1], f[2]]
        })
        .collect();
    // The table runs from long to short wavelengths: find the pair that brackets w.
    for p in t.windows(2) {
        let (a, b) = (p[0], p[1]);
        let (lo, hi) = if a[0] < b[0] { (a, b) } else { (b, a) };
        if lo[0] <= w && w <= hi[0] && hi[0] > lo[0] {
            let s = (w - lo[0]) / (hi[0] - lo[0]);
            return C::new(lo[1] + s * (hi[1] - lo[1]), lo[2] + s * (hi[2] - lo[2]));
        }
    }
    panic!("{w} outside the table")
}

/// Reference model: q, u of an unpolarized star (x and y fields added incoherently).
fn ref_qu(n: C, f: f64, offset_deg: f64, pa_deg: f64) -> (f64, f64) {
    let nn = n * f;
    let i = std::f64::consts::FRAC_PI_4;
    let w = (nn * nn - C::new(i.sin().powi(2), 0.0)).sqrt();
    let rs = (C::new(i.cos(), 0.0) - w) / (C::new(i.cos(), 0.0) + w);
    let rp = (nn * nn * i.cos() - w) / (nn * nn * i.cos() + w);
    // M3 with s along x (their Stokes frame of the mirror), p along y.
    let m3: J = [[rs, C::new(0.0, 0.0)], [C::new(0.0, 0.0), rp]];
    let (o, p) = (offset_deg.to_radians(), pa_deg.to_radians());
    let j = mul(&rot(o), &mul(&rot(-p), &mul(&m3, &rot(-p))));
    let (mut ii, mut qq, mut uu) = (0.0, 0.0, 0.0);
    for e in [[C::new(1.0, 0.0), C::new(0.0, 0.0)], [C::new(0.0, 0.0), C::new(1.0, 0.0)]] {
        let ex = j[0][0] * e[0] + j[0][1] * e[1];
        let ey = j[1][0] * e[0] + j[1][1] * e[1];
        ii += ex.norm_sqr() + ey.norm_sqr();
        qq += ex.norm_sqr() - ey.norm_sqr();
        uu += 2.0 * (ex.conj() * ey).re;
    }
    (qq / ii, uu / ii)
}

fn chi2(d: &[[f64; 6]], n: C, x: &[f64; 2]) -> f64 {
    d.iter()
        .map(|r| {
            let (q, u) = ref_qu(n, x[0], x[1], r[0]);
            ((q - r[1]) / r[2]).powi(2) + ((u - r[3]) / r[4]).powi(2)
        })
        .sum()
}

/// Plain Nelder-Mead in 2-D (reflection, expansion, contraction, shrink).
fn nelder_mead(f: &dyn Fn(&[f64; 2]) -> f64, start: [f64; 2], scale: [f64; 2]) -> [f64; 2] {
    let mut s = [start, [start[0] + scale[0], start[1]], [start[0], start[1] + scale[1]]];
    let mut v = s.map(|x| f(&x));
    for _ in 0..4000 {
        let mut idx = [0, 1, 2];
        idx.sort_by(|&a, &b| v[a].total_cmp(&v[b]));
        s = idx.map(|i| s[i]);
        v = idx.map(|i| v[i]);
        if (v[2] - v[0]).abs() < 1e-13 * (1.0 + v[0].abs()) {
            break;
        }
        let c = [(s[0][0] + s[1][0]) / 2.0, (s[0][1] + s[1][1]) / 2.0];
        let at = |t: f64| [c[0] + t * (s[2][0] - c[0]), c[1] + t * (s[2][1] - c[1])];
        let r = at(-1.0);
        let fr = f(&r);
        if fr < v[0] {
            let e = at(-2.0);
            let fe = f(&e);
            if fe < fr {
                s[2] = e;
                v[2] = fe;
            } else {
                s[2] = r;
                v[2] = fr;
            }
        } else if fr < v[1] {
            s[2] = r;
            v[2] = fr;
        } else {
            let k = at(0.5);
            let fk = f(&k);
            if fk < v[2] {
                s[2] = k;
                v[2] = fk;
            } else {
                for i in 1..3 {
                    s[i] = [(s[0][0] + s[i][0]) / 2.0, (s[0][1] + s[i][1]) / 2.0];
                    v[i] = f(&s[i]);
                }
            }
        }
    }
    s[0]
}

/// Reference fit: best of Nelder-Mead runs from a grid; errors from the Hessian of chi^2
/// (cov = 2 H^-1), unscaled (the emcee likelihood of the published method).
fn reference(d: &[[f64; 6]], n: C) -> ([f64; 2], [f64; 2], f64) {
    let f = |x: &[f64; 2]| if x[0] <= 0.0 { f64::INFINITY } else { chi2(d, n, x) };
    let mut best = ([1.0, 0.0], f64::INFINITY);
    for f0 in [0.5, 1.0, 1.5, 2.0] {
        for o0 in (0..6).map(|k| -90.0 + 30.0 * k as f64) {
            let x = nelder_mead(&f, [f0, o0], [0.1, 10.0]);
            let c = f(&x);
            if c < best.1 {
                best = (x, c);
            }
        }
    }
    let x = best.0;
    let h = [1e-4, 1e-3];
    let mut hess = [[0.0; 2]; 2];
    for i in 0..2 {
        for j in 0..2 {
            let e = |si: f64, sj: f64| {
                let mut y = x;
                y[i] += si * h[i];
                y[j] += sj * h[j];
                f(&y)
            };
            hess[i][j] = (e(1.0, 1.0) - e(1.0, -1.0) - e(-1.0, 1.0) + e(-1.0, -1.0)) / (4.0 * h[i] * h[j]);
        }
    }
    let det = hess[0][0] * hess[1][1] - hess[0][1] * hess[1][0];
    let cov = [2.0 * hess[1][1] / det, 2.0 * hess[0][0] / det];
    let off = (x[1] + 90.0).rem_euclid(180.0) - 90.0;
    ([x[0], off], [cov[0].sqrt(), cov[1].sqrt()], best.1)
}

#[test]
fn wiersema_model_reproduces_an_independent_fit_band_by_band() {
    let Some(dir) = data_dir() else { return };
    let table = MetalTable::read(&dir.join("METALS_Aluminium_Rakic.txt")).unwrap();
    let abs = FitOptions { clip: None, error_scaling: ErrorScaling::Absolute, ..Default::default() };
    eprintln!("band  factor (ours | ref)          offset deg (ours | ref)       chi2/dof  rms_q%  rms_u%");
    for (band, stem) in BANDS {
        let path = dir.join(format!("{stem}_standards.txt"));
        let d = rows(&path);
        let n = rakic(&dir, d[0][5]);
        let (x, e, c2) = reference(&d, n);
        let obs = read_observations(&path).unwrap();
        let f = fit_band(ModelKind::Wiersema, &obs, &table, &abs).unwrap();
        let (fa, off) = (f.param("factor").unwrap(), f.param("offset").unwrap());
        let off_deg = off.value.to_degrees();
        eprintln!(
            "{band:4}  {:.4}+-{:.4} | {:.4}+-{:.4}   {:7.2}+-{:.2} | {:7.2}+-{:.2}   {:6.2}  {:.3}  {:.3}",
            fa.value,
            fa.sigma,
            x[0],
            e[0],
            off_deg,
            off.sigma.to_degrees(),
            x[1],
            e[1],
            f.chi2_reduced,
            100.0 * f.rms_q,
            100.0 * f.rms_u
        );
        assert!((f.chi2 - c2).abs() < 1e-6 * c2.max(1.0), "{band}: chi2 {} vs {c2}", f.chi2);
        assert!((fa.value - x[0]).abs() < 0.02 * e[0], "{band}: factor {} vs {}", fa.value, x[0]);
        let doff = ((off_deg - x[1] + 90.0).rem_euclid(180.0)) - 90.0;
        assert!(doff.abs() < 0.02 * e[1], "{band}: offset {off_deg} vs {}", x[1]);
        assert!((fa.sigma / e[0] - 1.0).abs() < 0.02, "{band}: sigma factor {} vs {}", fa.sigma, e[0]);
        assert!(
            (off.sigma.to_degrees() / e[1] - 1.0).abs() < 0.02,
            "{band}: sigma offset {} vs {}",
            off.sigma.to_degrees(),
            e[1]
        );
    }
}

#[test]
fn efosc2_report_physical_and_joint_fits() {
    let Some(dir) = data_dir() else { return };
    let table = MetalTable::read(&dir.join("METALS_Aluminium_Rakic.txt")).unwrap();
    let opts = FitOptions::default();
    let mut all = Vec::new();
    eprintln!("band model     params                                         chi2/dof  rms_q%  rms_u%  flagged");
    for (band, stem) in BANDS {
        let mut obs = read_observations(&dir.join(format!("{stem}_standards.txt"))).unwrap();
        for o in &mut obs {
            o.band = band.to_string();
        }
        for model in [ModelKind::Wiersema, ModelKind::Oxide] {
            let f = fit_band(model, &obs, &table, &opts).unwrap();
            let ps: Vec<String> = f
                .params
                .iter()
                .map(|p| {
                    if p.name == "offset" {
                        format!("offset={:.2}+-{:.2}deg", p.value.to_degrees(), p.sigma.to_degrees())
                    } else if p.name == "q0" || p.name == "u0" {
                        format!("{}={:.3}+-{:.3}%", p.name, 100.0 * p.value, 100.0 * p.sigma)
                    } else {
                        format!("{}={:.3}+-{:.3}", p.name, p.value, p.sigma)
                    }
                })
                .collect();
            let flagged: Vec<&str> = f.points.iter().filter(|p| p.flagged).map(|p| p.obs.star.as_str()).collect();
            eprintln!(
                "{band:4} {:9} {:60} {:6.2}  {:.3}  {:.3}  {:?}",
                model.name(),
                ps.join(" "),
                f.chi2_reduced,
                100.0 * f.rms_q,
                100.0 * f.rms_u,
                flagged
            );
            assert!(f.chi2_reduced.is_finite());
        }
        all.extend(obs);
    }
    for model in [ModelKind::Wiersema, ModelKind::Oxide] {
        let j = fit_joint(model, &all, &table, &opts, true).unwrap();
        let p0 = &j.params[0];
        let flagged: Vec<String> =
            j.points.iter().filter(|p| p.flagged).map(|p| format!("{}@{}", p.obs.star, p.obs.band)).collect();
        eprintln!(
            "joint {}: {} = {:.3} +- {:.3}, chi2/dof = {:.2} ({} dof), rms q {:.3}%, u {:.3}%, flagged {:?}",
            model.name(),
            p0.name,
            p0.value,
            p0.sigma,
            j.chi2_reduced,
            j.dof,
            100.0 * j.rms_q,
            100.0 * j.rms_u,
            flagged
        );
    }
}

#[test]
fn efosc2_standards_corrected_leave_one_out_are_unpolarized() {
    // Each star's measurement corrected with the Wiersema model fitted to the other stars of
    // its band: the published standards are unpolarized (P < 0.1%), so the corrected (q, u)
    // must be zero within the errors (measurement errors scaled by sqrt(max(1, chi2_red)) of
    // the fit, plus the model's covariance), while uncorrected they show the M3's 3-5 %.
    let Some(dir) = data_dir() else { return };
    let table = MetalTable::read(&dir.join("METALS_Aluminium_Rakic.txt")).unwrap();
    let (mut n, mut within, mut raw_p, mut cor_p) = (0, 0, Vec::new(), Vec::new());
    for (_, stem) in BANDS {
        let obs = read_observations(&dir.join(format!("{stem}_standards.txt"))).unwrap();
        for k in 0..obs.len() {
            let rest: Vec<_> = obs.iter().enumerate().filter(|(i, _)| *i != k).map(|(_, o)| o.clone()).collect();
            let f = fit_band(ModelKind::Wiersema, &rest, &table, &FitOptions::default()).unwrap();
            let o = &obs[k];
            let s = f.chi2_reduced.max(1.0).sqrt();
            let [q, sq, u, su] =
                f.correct(&o.band, o.qu.q, o.qu.sigma_q() * s, o.qu.u, o.qu.sigma_u() * s, o.parallactic).unwrap();
            let z2 = (q / sq).powi(2) + (u / su).powi(2);
            n += 1;
            // 2-dof chi^2 below 11.83: 3 sigma.
            if z2 < 11.83 {
                within += 1;
            }
            raw_p.push(o.qu.q.hypot(o.qu.u));
            cor_p.push(q.hypot(u));
        }
    }
    raw_p.sort_by(f64::total_cmp);
    cor_p.sort_by(f64::total_cmp);
    let (mr, mc) = (raw_p[raw_p.len() / 2], cor_p[cor_p.len() / 2]);
    eprintln!(
        "leave-one-out: {within} of {n} corrected within 3 sigma of P = 0; median P raw {:.2}% corrected {:.3}%",
        100.0 * mr,
        100.0 * mc
    );
    assert!(mr > 0.025 && mc < 0.003, "median P raw {mr}, corrected {mc}");
    assert!(within as f64 >= 0.85 * n as f64, "{within} of {n}");
}
