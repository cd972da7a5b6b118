//! `instpol stokes --plot` (the paper's fig:fourier for one source): the PNG is written whole
//! or not at all, and what it draws is the solver's result. The numbers the plot draws come
//! from `src/cmd/stokes_plot/data.rs`, included here as it is compiled into the binary.

#[allow(dead_code)]
#[path = "../../src/cmd/stokes_plot/data.rs"]
mod data;

use serde_json::Value;
use std::path::{Path, PathBuf};
use std::process::{Command, Output};
use stokes::Measurement;

/// The PNG size `--help` documents.
const SIZE: (u32, u32) = (1000, 1300);

fn example(name: &str) -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../tests/data").join(name)
}

fn stokes(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_instpol")).arg("stokes").args(args).output().expect("run instpol")
}

fn names_in(dir: &Path) -> Vec<String> {
    let mut v: Vec<String> =
        std::fs::read_dir(dir).unwrap().map(|e| e.unwrap().file_name().to_string_lossy().into_owned()).collect();
    v.sort();
    v
}

/// Dual-beam counts whose F_i (eq:F) are exactly `f[i]`: f_O = I (1 + F)/2, f_E = I (1 - F)/2
/// with I = 1e6 electrons (Poisson errors), written with round-trip precision.
fn write_csv(path: &Path, hwp_deg: &[f64], f: &[f64]) -> (Vec<f64>, Vec<f64>) {
    let i0 = 1e6;
    let f_o: Vec<f64> = f.iter().map(|x| 0.5 * i0 * (1.0 + x)).collect();
    let f_e: Vec<f64> = f.iter().map(|x| 0.5 * i0 * (1.0 - x)).collect();
    let mut s = String::from("hwp_deg,f_o,f_e\n");
    for i in 0..f.len() {
        s += &format!("{:?},{:?},{:?}\n", hwp_deg[i], f_o[i], f_e[i]);
    }
    std::fs::write(path, s).unwrap();
    (f_o, f_e)
}

/// F = a + Q cos 4theta + U sin 4theta: eq:system plus a constant (the Wollaston offset of
/// eq:a0).
fn closed_form(a: f64, q: f64, u: f64, theta_deg: f64) -> f64 {
    let t = 4.0 * theta_deg.to_radians();
    a + q * t.cos() + u * t.sin()
}

#[test]
fn plot_is_a_whole_png_of_the_documented_size() {
    let dir = tempfile::tempdir().unwrap();
    let png = dir.path().join("fourier.png");
    let input = example("fors1_v_star_n16.csv");
    let o = stokes(&["--input", input.to_str().unwrap(), "--plot", png.to_str().unwrap()]);
    assert!(o.status.success(), "stderr: {}", String::from_utf8_lossy(&o.stderr));
    // The table is still printed, and nothing but the PNG is left in the folder.
    assert!(String::from_utf8_lossy(&o.stdout).contains("Harmonics"));
    assert_eq!(names_in(dir.path()), ["fourier.png"]);
    // A full decode checks the signature, every chunk's CRC and the compressed image data.
    let decoder = png::Decoder::new(std::fs::File::open(&png).unwrap());
    let mut reader = decoder.read_info().expect("PNG header");
    let mut buf = vec![0; reader.output_buffer_size()];
    let info = reader.next_frame(&mut buf).expect("PNG image data");
    assert_eq!((info.width, info.height), SIZE);
    // Something is drawn: a white canvas with curves, points and bars is far from all white.
    let pixels = &buf[..info.buffer_size()];
    let dark = pixels.chunks(info.color_type.samples()).filter(|p| p.iter().take(3).all(|&c| c < 128)).count();
    assert!(dark > 2000, "only {dark} dark pixels");
}

#[test]
fn bad_plot_path_exits_2_and_leaves_no_file() {
    let dir = tempfile::tempdir().unwrap();
    let input = example("example_n4.csv");
    // A folder that does not exist.
    let missing = dir.path().join("no-such-folder").join("f.png");
    let o = stokes(&["--input", input.to_str().unwrap(), "--plot", missing.to_str().unwrap()]);
    assert_eq!(o.status.code(), Some(2));
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(err.starts_with("error:") && err.contains("no-such-folder"), "stderr: {err}");
    assert!(o.stdout.is_empty(), "nothing is printed when the plot fails");
    assert!(!missing.exists());
    // A path that is a folder: the drawing succeeds into a temporary beside it, the rename
    // fails, and the temporary must not be left behind.
    let taken = dir.path().join("taken.png");
    std::fs::create_dir(&taken).unwrap();
    let o = stokes(&["--input", input.to_str().unwrap(), "--plot", taken.to_str().unwrap(), "--json"]);
    assert_eq!(o.status.code(), Some(2));
    let err = String::from_utf8_lossy(&o.stderr);
    // Under --json the error is the JSON object (schemas/error.schema.json): a file-system
    // failure, exit 2.
    let e: serde_json::Value = serde_json::from_str(err.trim()).unwrap_or_else(|x| panic!("{x}: {err}"));
    assert!(e["error"]["message"].as_str().unwrap().contains("taken.png"), "stderr: {err}");
    assert_eq!(e["error"]["kind"], "io", "{err}");
    assert_eq!(e["error"]["exit_code"], 2);
    assert!(o.stdout.is_empty());
    assert_eq!(names_in(dir.path()), ["taken.png"]);
    assert!(taken.is_dir() && names_in(&taken).is_empty());
}

/// The reduction the binary makes of the same counts (Poisson errors, no sigma columns).
fn reduce(hwp_deg: &[f64], f_o: Vec<f64>, f_e: Vec<f64>) -> stokes::Reduction {
    let theta = hwp_deg.iter().map(|d| d.to_radians()).collect();
    Measurement::poisson(theta, f_o, f_e).unwrap().reduce().unwrap()
}

fn json_of(csv: &Path) -> Value {
    let o = stokes(&["--input", csv.to_str().unwrap(), "--json"]);
    assert!(o.status.success(), "stderr: {}", String::from_utf8_lossy(&o.stderr));
    serde_json::from_slice(&o.stdout).unwrap()
}

fn num(v: &Value) -> f64 {
    v.as_f64().unwrap_or_else(|| panic!("not a number: {v}"))
}

/// eq:system on the optimal sets N = 4, 8, 16 with a Wollaston offset a (eq:a0): the plotted
/// curve is a + Q cos 4theta + U sin 4theta with the solver's Q, U (the CLI's JSON), passes
/// through every F_i, and the bars are the CLI's harmonic amplitudes: P at k = N/4 (a_{N/4} =
/// Q, b_{N/4} = U, eq:fourcoeff), |a| at k = 0, zero elsewhere.
#[test]
fn plot_data_is_the_solver_output_on_eq_system_input() {
    let (a, q, u) = (0.004, 0.03, -0.02);
    let dir = tempfile::tempdir().unwrap();
    for n in [4usize, 8, 16] {
        let hwp: Vec<f64> = (0..n).map(|i| 22.5 * i as f64).collect();
        let f: Vec<f64> = hwp.iter().map(|&t| closed_form(a, q, u, t)).collect();
        let csv = dir.path().join(format!("n{n}.csv"));
        let (f_o, f_e) = write_csv(&csv, &hwp, &f);
        let v = json_of(&csv);
        let d = data::fourier_plot(&reduce(&hwp, f_o, f_e));

        // The solver's numbers, as the CLI prints them, and the closed form.
        let (jq, ju) = (num(&v["q"]), num(&v["u"]));
        assert!((d.q - jq).abs() <= 1e-16 && (d.u - ju).abs() <= 1e-16, "N = {n}: plot Q, U = {}, {}", d.q, d.u);
        assert!((d.q - q).abs() < 1e-13 && (d.u - u).abs() < 1e-13, "N = {n}: Q, U = {}, {}", d.q, d.u);
        let a0 = d.a0.expect("a_0 on the optimal set");
        assert!((a0 - num(&v["a0"])).abs() <= 1e-16 && (a0 - a).abs() < 1e-13, "N = {n}: a0 = {a0}");

        // Points: the F_i at the HWP angles.
        assert_eq!(d.points.len(), n);
        for (p, (&t, &fi)) in d.points.iter().zip(hwp.iter().zip(&f)) {
            // Degrees from the solver's radians: equal to rounding.
            assert!((p.theta_deg - t).abs() < 1e-12, "{} vs {t}", p.theta_deg);
            assert!((p.f - fi).abs() < 1e-15, "N = {n}, theta = {t}: F = {} vs {fi}", p.f);
            assert!(p.sigma > 0.0 && p.sigma.is_finite());
        }
        let sigma_f: Vec<f64> = v["sigma_f"].as_array().unwrap().iter().map(num).collect();
        for (p, s) in d.points.iter().zip(&sigma_f) {
            assert!((p.sigma - s).abs() <= 1e-18, "error bars are the CLI's sigma_F");
        }

        // Curve: the closed form at every drawn point, covering [0, theta_max].
        // The last angle, 22.5 (N - 1) deg, below 180 deg: half a turn is enough.
        let tmax = if 22.5 * ((n - 1) as f64) < 180.0 { 180.0 } else { 360.0 };
        assert_eq!(d.theta_max_deg, tmax);
        assert_eq!(d.curve.first().unwrap().0, 0.0);
        assert_eq!(d.curve.last().unwrap().0, tmax);
        for &(t, y) in &d.curve {
            assert!((y - closed_form(a, q, u, t)).abs() < 1e-13, "N = {n}: curve at {t} deg = {y}");
        }
        // ... and through each F_i.
        for (&t, &fi) in hwp.iter().zip(&f) {
            let c = d.curve.iter().find(|c| c.0 == t).expect("the optimal angles are curve points");
            assert!((c.1 - fi).abs() < 1e-13);
        }

        // Bars: the CLI's harmonics.
        let four = v["fourier"].as_array().unwrap();
        assert_eq!(d.bars.len(), four.len());
        assert_eq!(d.bars.len(), n / 2 + 1);
        assert_eq!(d.k_pol, Some(n / 4));
        for (b, h) in d.bars.iter().zip(four) {
            assert_eq!(b.k as u64, h["k"].as_u64().unwrap());
            let (ha, hb) = (num(&h["a"]), num(&h["b"]));
            assert!((b.amplitude - ha.hypot(hb)).abs() <= 1e-16);
            let expected = match b.k {
                0 => a,
                k if k == n / 4 => q.hypot(u),
                _ => 0.0,
            };
            assert!((b.amplitude - expected).abs() < 1e-13, "N = {n}, k = {}: {}", b.k, b.amplitude);
            // The noise level: sigma_a alone where there is no sine part (k = 0, Nyquist),
            // else the rms of sigma_a and sigma_b.
            let (sa, sb) = (num(&h["sigma_a"]), num(&h["sigma_b"]));
            let s = if sb == 0.0 { sa } else { ((sa * sa + sb * sb) / 2.0).sqrt() };
            assert!((b.sigma - s).abs() <= 1e-15 * s, "N = {n}, k = {}", b.k);
        }
        assert!((d.p - q.hypot(u)).abs() < 1e-13);
        let chi = 0.5 * u.atan2(q).to_degrees().rem_euclid(360.0);
        assert!((d.chi_deg.unwrap() - chi).abs() < 1e-9);
    }
}

/// Uneven angles (least squares of eq:system): no harmonics and no a_0 term; the curve is
/// Q cos 4theta + U sin 4theta with the solver's Q, U, through every F_i, and the angles are
/// folded into [0, 360) for the axis.
#[test]
fn plot_data_on_an_uneven_angle_set_is_eq_system_alone() {
    let (q, u) = (-0.012, 0.045);
    let hwp = [-10.0, 5.0, 31.0, 50.0, 77.0, 100.0];
    let f: Vec<f64> = hwp.iter().map(|&t| closed_form(0.0, q, u, t)).collect();
    let dir = tempfile::tempdir().unwrap();
    let csv = dir.path().join("uneven.csv");
    let (f_o, f_e) = write_csv(&csv, &hwp, &f);
    let v = json_of(&csv);
    let d = data::fourier_plot(&reduce(&hwp, f_o, f_e));
    assert!(d.bars.is_empty() && d.a0.is_none() && d.k_pol.is_none());
    assert!(v["fourier"].as_array().unwrap().is_empty(), "the CLI has no harmonics either");
    assert!((d.q - num(&v["q"])).abs() <= 1e-16 && (d.u - num(&v["u"])).abs() <= 1e-16);
    assert!((d.q - q).abs() < 1e-13 && (d.u - u).abs() < 1e-13);
    // -10 deg is the plate at 350 deg: the axis runs to 360.
    assert!((d.points[0].theta_deg - 350.0).abs() < 1e-12);
    assert_eq!(d.theta_max_deg, 360.0);
    for &(t, y) in &d.curve {
        assert!((y - closed_form(0.0, q, u, t)).abs() < 1e-13);
    }
    for p in &d.points {
        assert!((data::model(d.q, d.u, p.theta_deg.to_radians()) - p.f).abs() < 1e-13);
    }
    let (p, _) = stokes::polarization(q, u);
    assert!((d.p - p).abs() < 1e-13);
}
