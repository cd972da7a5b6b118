//! Calibration files of several field elements (`fit::files::elements`): what is written is
//! read back in its order, a file of one element keeps format version 1, a table that does not
//! say a usable order is refused by name, and rows are corrected through the whole chain:
//! checked against a Mueller product of a stressed lens and the partial polarizer of
//! `eq:instpol` written here (each element's matrix from its formula, multiplied in the order
//! light meets them, the plate's zero angle turned last), and the first-order method against
//! `eq:approx` (the polarization the product gives unpolarized light subtracted).

use fit::correction::correct::{Measurement, Method};
use fit::correction::request::{plan_rows, Request};
use fit::files::elements::Element;
use std::path::Path;

const Z_DEG: f64 = 4.0;
const COEFFS: [f64; 3] = [0.0, 0.002, 0.003];

fn lens() -> field::StressedLens {
    field::StressedLens {
        retardance_edge: 70f64.to_radians(),
        radius_arcmin: 3.0,
        centre_arcmin: [0.4, -0.3],
        axis_offset: 10f64.to_radians(),
    }
}

fn calibration() -> fit::Calibration {
    crate::common::given::given_calibration(
        "FORS1",
        "V",
        554.0,
        Z_DEG,
        fit::Model::Radial(fit::RadialModel::new(0, COEFFS.to_vec(), [0.0, 0.0])),
        3.5,
    )
}

type M3 = [[f64; 3]; 3];

fn mul(a: &M3, b: &M3) -> M3 {
    std::array::from_fn(|i| std::array::from_fn(|j| (0..3).map(|k| a[i][k] * b[k][j]).sum()))
}

fn app(a: &M3, s: [f64; 3]) -> [f64; 3] {
    std::array::from_fn(|i| (0..3).map(|k| a[i][k] * s[k]).sum())
}

/// The (I, Q, U) block of a turn of the polarization plane by `a` (chi -> chi + a).
fn turn(a: f64) -> M3 {
    let (s, c) = (2.0 * a).sin_cos();
    [[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]]
}

/// `M_I(p, phi)` (eq:instpol): along its axis `[[1, p, 0], [p, 1, 0], [0, 0, 1 - p]]` up to a
/// factor, turned to `phi`.
fn partial_polarizer(x: f64, y: f64) -> M3 {
    let r = x.hypot(y);
    let p: f64 = COEFFS.iter().enumerate().map(|(k, c)| c * r.powi(k as i32)).sum();
    let phi = y.atan2(x);
    let along = [[1.0, p, 0.0], [p, 1.0, 0.0], [0.0, 0.0, 1.0 - p]];
    mul(&turn(phi), &mul(&along, &turn(-phi)))
}

/// A linear retarder of the lens's retardance and axis at `(x, y)`: its (I, Q, U) block (the
/// textbook form, `c = cos 2 theta`, `s = sin 2 theta`).
fn lens_block(x: f64, y: f64) -> M3 {
    let l = lens();
    let (dx, dy) = (x - l.centre_arcmin[0], y - l.centre_arcmin[1]);
    let delta = l.retardance_edge * (dx * dx + dy * dy) / (l.radius_arcmin * l.radius_arcmin);
    let (s, c) = (2.0 * (dy.atan2(dx) + l.axis_offset)).sin_cos();
    let cd = delta.cos();
    [[1.0, 0.0, 0.0], [0.0, c * c + s * s * cd, c * s * (1.0 - cd)], [0.0, c * s * (1.0 - cd), s * s + c * c * cd]]
}

fn save(dir: &Path, name: &str, order: &[Element]) -> std::path::PathBuf {
    let p = dir.join(name);
    calibration().save_with_elements(&p, order, |_, _| Ok(())).unwrap();
    p
}

#[test]
fn rows_are_corrected_through_the_elements_in_their_order() {
    let dir = tempfile::tempdir().unwrap();
    let lens_first = save(dir.path(), "a.fits", &[Element::StressedLens(lens()), Element::Model]);
    let model_first = save(dir.path(), "b.fits", &[Element::Model, Element::StressedLens(lens())]);
    let sky = [1.0, 0.02, -0.035];
    let mut order_shows = 0.0f64;
    for (path, lens_is_first) in [(&lens_first, true), (&model_first, false)] {
        let file = fit::files::calibration::load(path).unwrap();
        let exact = plan_rows(&file, &Request::new(Method::Exact, false, 0.5), 1).unwrap();
        let first = plan_rows(&file, &Request::new(Method::FirstOrder, false, 0.5), 1).unwrap();
        for (x, y) in [(0.0, 0.0), (1.5, -0.7), (-2.9, 2.2), (3.1, 3.0), (-0.4, -3.3)] {
            let (f, l) = (partial_polarizer(x, y), lens_block(x, y));
            let chain = if lens_is_first { mul(&f, &l) } else { mul(&l, &f) };
            let v = app(&mul(&turn(-Z_DEG.to_radians()), &chain), sky);
            let m = Measurement::at_plate(x, y, v[1] / v[0], v[2] / v[0], 1e-4, 1e-4, 0.0);
            let c = exact.correct(0, &m).unwrap();
            assert!((c.q0 - sky[1]).abs() < 1e-12 && (c.u0 - sky[2]).abs() < 1e-12, "({x}, {y}): {c:?}");
            // The chain's polarization of unpolarized light: the partial polarizer's, turned by
            // the lens when the lens comes after it.
            let i = app(&chain, [1.0, 0.0, 0.0]);
            assert!((c.inst.q - i[1] / i[0]).abs() < 1e-14 && (c.inst.u - i[2] / i[0]).abs() < 1e-14, "{c:?}");
            let o = first.correct(0, &m).unwrap();
            let at = app(&turn(Z_DEG.to_radians()), [1.0, m.qu.q, m.qu.u]);
            let (wq, wu) = (at[1] - i[1] / i[0], at[2] - i[2] / i[0]);
            assert!((o.q0 - wq).abs() < 1e-14 && (o.u0 - wu).abs() < 1e-14, "({x}, {y}): {o:?} vs ({wq}, {wu})");
            // The measurement's errors (no model errors here) go through the inverse: the
            // corrected variance is of the order of the measured one.
            assert!(c.var_q0 > 0.5e-8 && c.var_q0 < 2e-8, "{c:?}");
            if !lens_is_first {
                let other = mul(&f, &l);
                let w = app(&mul(&turn(-Z_DEG.to_radians()), &other), sky);
                order_shows = order_shows.max((w[1] / w[0] - m.qu.q).abs());
            }
        }
    }
    assert!(order_shows > 1e-4, "the two orders give the same measurement ({order_shows:e}): order is not tested");
}

#[test]
fn the_order_is_written_and_read_back_and_one_element_keeps_version_one() {
    let dir = tempfile::tempdir().unwrap();
    let order = [
        Element::StressedLens(lens()),
        Element::Model,
        Element::StressedLens(field::StressedLens { axis_offset: 0.5, ..lens() }),
    ];
    let p = save(dir.path(), "three.fits", &order);
    let file = fit::files::calibration::load(&p).unwrap();
    assert_eq!(file.elements.len(), 3);
    assert_eq!(file.elements[1], Element::Model);
    for (a, b) in file.elements.iter().zip(&order) {
        if let (Element::StressedLens(a), Element::StressedLens(b)) = (a, b) {
            assert!(
                (a.retardance_edge - b.retardance_edge).abs() < 1e-15 && (a.axis_offset - b.axis_offset).abs() < 1e-15
            );
            assert_eq!((a.radius_arcmin, a.centre_arcmin), (b.radius_arcmin, b.centre_arcmin));
        }
    }
    let version = |p: &Path| {
        let mut f = fitsio::FitsFile::open(p).unwrap();
        let h = f.primary_hdu().unwrap();
        h.read_key::<i64>(&mut f, "HIERARCH IP FORMAT VERSION").unwrap()
    };
    assert_eq!(version(&p), 2);
    let one = dir.path().join("one.fits");
    calibration().save(&one).unwrap();
    assert_eq!(version(&one), 1);
    // A prediction through the field model alone (validate) refuses it by name.
    let msg = file.p_phi_models_alone().unwrap_err().to_string();
    assert!(msg.contains("3 field elements") && msg.contains("three.fits"), "{msg}");
    let empty = save(dir.path(), "empty.fits", &[]);
    assert_eq!(version(&empty), 1);
    assert!(fit::files::calibration::load(&empty).unwrap().elements.is_empty());
    // An order without the model, or the model twice, is refused before writing.
    for bad in
        [vec![Element::StressedLens(lens()), Element::StressedLens(lens())], vec![Element::Model, Element::Model]]
    {
        let e = calibration().save_with_elements(&dir.path().join("bad.fits"), &bad, |_, _| Ok(())).unwrap_err();
        assert!(e.to_string().contains("the file's own model"), "{e}");
    }
}

#[test]
fn an_elements_table_without_a_usable_order_is_refused_naming_it() {
    let dir = tempfile::tempdir().unwrap();
    let edit = |name: &str, f: &dyn Fn(&mut fitsio::FitsFile)| {
        let p = save(dir.path(), name, &[Element::StressedLens(lens()), Element::Model]);
        let mut file = fitsio::FitsFile::edit(&p).unwrap();
        f(&mut file);
        drop(file);
        fit::files::calibration::load(&p).unwrap_err().to_string()
    };
    let msg = edit("place.fits", &|f| {
        let h = f.hdu("ELEMENTS").unwrap();
        h.write_col(f, "ORDER", &[2i32]).unwrap();
    });
    assert!(msg.contains("ELEMENTS row 1") && msg.contains("ORDER = 2"), "{msg}");
    let msg = edit("kind.fits", &|f| {
        let h = f.hdu("ELEMENTS").unwrap();
        h.write_col(f, "KIND", &["MIRROR".to_string()]).unwrap();
    });
    assert!(msg.contains("KIND = 'MIRROR'"), "{msg}");
    let msg = edit("radius.fits", &|f| {
        let h = f.hdu("ELEMENTS").unwrap();
        h.write_col(f, "RADIUS_ARCMIN", &[0.0f64]).unwrap();
    });
    assert!(msg.contains("positive radius"), "{msg}");
}
