//! Bad frames: each a clear error naming the file (or keyword, or angle), or a documented
//! warning; never a panic.

use instrument::Instrument;
use skyfield::fits::{write_frame, Bitpix, KeyValue};
use skyfield::reduce::{reduce_files, ReduceConfig};
use skyfield::Error;
use std::path::{Path, PathBuf};

use crate::common;

fn tiny() -> Instrument {
    common::tiny_with_bias(0.0)
}

fn keys(inst: &Instrument, hwp: f64, filter: &str) -> Vec<(String, KeyValue, String)> {
    common::keys(inst, hwp, filter, &[])
}

/// A frame of an unpolarized-in-o/e-balance sky with `Q/I = 0.01` modulation (eq:ord).
fn image(inst: &Instrument, hwp_deg: f64) -> Vec<f64> {
    let g = skyfield::BeamGeometry::new(inst);
    let mut v = vec![0.0; g.nx * g.ny];
    let m = 0.01 * (4.0 * hwp_deg.to_radians()).cos();
    for (x, y) in g.sky_pixels() {
        let (o, e) = g.beams_of_sky(x, y).unwrap();
        v[o] = 4000.0 * (1.0 + m);
        v[e] = 4000.0 * (1.0 - m);
    }
    v
}

fn good_set(dir: &Path, inst: &Instrument) -> Vec<PathBuf> {
    [0.0, 22.5, 45.0, 67.5]
        .iter()
        .enumerate()
        .map(|(k, &a)| {
            let p = dir.join(format!("f{k}.fits"));
            write_frame(&p, 64, 64, &image(inst, a), Bitpix::F64, &keys(inst, a, "V_BESS")).unwrap();
            p
        })
        .collect()
}

fn reduce(paths: &[PathBuf], inst: &Instrument) -> Result<skyfield::reduce::Reduced, Error> {
    reduce_files(paths, inst, &ReduceConfig { bin_px: 4, ..Default::default() }, &|| {})
}

#[test]
fn good_set_gives_q() {
    let dir = tempfile::tempdir().unwrap();
    let inst = tiny();
    let r = reduce(&good_set(dir.path(), &inst), &inst).unwrap();
    for (k, _, _) in r.map.valid_bins() {
        assert!((r.map.q[k] - 0.01).abs() < 1e-12 && r.map.u[k].abs() < 1e-12);
    }
}

#[test]
fn truncated_file_is_named() {
    let dir = tempfile::tempdir().unwrap();
    let inst = tiny();
    let p = good_set(dir.path(), &inst);
    let b = std::fs::read(&p[2]).unwrap();
    std::fs::write(&p[2], &b[..b.len() / 2]).unwrap();
    let e = reduce(&p, &inst).unwrap_err().to_string();
    assert!(e.contains("f2.fits"), "{e}");
}

/// Every FITS image type is a frame: an 8-bit image reads to its values (it was
/// refused as "BITPIX 8" before).
#[test]
fn byte_frames_are_read() {
    let dir = tempfile::tempdir().unwrap();
    let inst = tiny();
    let bad = dir.path().join("byte.fits");
    {
        use fitsio::images::{ImageDescription, ImageType};
        let d = ImageDescription { data_type: ImageType::UnsignedByte, dimensions: &[64, 64] };
        let mut f = fitsio::FitsFile::create(&bad).with_custom_primary(&d).open().unwrap();
        let h = f.primary_hdu().unwrap();
        let v: Vec<u8> = (0..64 * 64).map(|i| (i % 251) as u8).collect();
        h.write_image(&mut f, &v).unwrap();
        h.write_key(&mut f, &inst.polarimetry.hwp_angle_keyword, 0.0f64).unwrap();
        h.write_key(&mut f, &inst.polarimetry.filter_keyword, "V_BESS").unwrap();
    }
    let fr = skyfield::io::read_frame(&bad, &inst).unwrap();
    assert_eq!(fr.bitpix, 8);
    for (i, v) in fr.data.iter().enumerate() {
        assert_eq!(*v, (i % 251) as f64);
    }
}

#[test]
fn nan_filled_frame_is_an_error_and_some_nans_a_warning() {
    let dir = tempfile::tempdir().unwrap();
    let inst = tiny();
    let p = good_set(dir.path(), &inst);
    write_frame(&p[1], 64, 64, &vec![f64::NAN; 64 * 64], Bitpix::F64, &keys(&inst, 22.5, "V_BESS")).unwrap();
    let e = reduce(&p, &inst).unwrap_err().to_string();
    assert!(e.contains("f1.fits") && e.contains("NaN"), "{e}");
    let mut img = image(&inst, 22.5);
    for v in img.iter_mut().step_by(7) {
        *v = f64::NAN;
    }
    write_frame(&p[1], 64, 64, &img, Bitpix::F64, &keys(&inst, 22.5, "V_BESS")).unwrap();
    let r = reduce(&p, &inst).unwrap();
    assert!(
        r.warnings.iter().any(|w| w.message.contains("NaN") && w.to_string().contains("f1.fits")),
        "{:?}",
        r.warnings
    );
    for (k, _, _) in r.map.valid_bins() {
        assert!((r.map.q[k] - 0.01).abs() < 1e-12);
    }
}

#[test]
fn saturated_pixels_are_masked_with_a_warning() {
    let dir = tempfile::tempdir().unwrap();
    let inst = tiny();
    let p = good_set(dir.path(), &inst);
    let mut img = image(&inst, 45.0);
    for v in img.iter_mut().skip(3).step_by(11) {
        if *v > 0.0 {
            *v = 70000.0;
        }
    }
    write_frame(&p[2], 64, 64, &img, Bitpix::F64, &keys(&inst, 45.0, "V_BESS")).unwrap();
    let r = reduce(&p, &inst).unwrap();
    assert!(r.warnings.iter().any(|w| w.message.contains("saturated")), "{:?}", r.warnings);
    for (k, _, _) in r.map.valid_bins() {
        assert!((r.map.q[k] - 0.01).abs() < 1e-12, "saturated pixels leaked into bin {k}");
    }
}

#[test]
fn missing_keyword_mixed_filters_missing_angle() {
    let dir = tempfile::tempdir().unwrap();
    let inst = tiny();
    let p = good_set(dir.path(), &inst);
    // Missing keyword.
    let mut k = keys(&inst, 45.0, "V_BESS");
    k.remove(0);
    write_frame(&p[2], 64, 64, &image(&inst, 45.0), Bitpix::F64, &k).unwrap();
    let e = reduce(&p, &inst).unwrap_err().to_string();
    assert!(e.contains("HIERARCH ESO INS RETA2 POSANG") && e.contains("f2.fits"), "{e}");
    // Mixed filters.
    write_frame(&p[2], 64, 64, &image(&inst, 45.0), Bitpix::F64, &keys(&inst, 45.0, "R_BESS")).unwrap();
    let e = reduce(&p, &inst).unwrap_err();
    assert!(matches!(e, Error::MixedFilters { .. }), "{e}");
    let e = e.to_string();
    assert!(e.contains("R: ") && e.contains("V: ") && e.contains("f2.fits"), "{e}");
    // Missing angle: only 3 of the N = 4 set.
    let e = reduce(&[p[0].clone(), p[1].clone(), p[3].clone()], &inst).unwrap_err().to_string();
    assert!(e.contains("missing [45 deg]"), "{e}");
    // No frames at all.
    assert!(matches!(reduce(&[], &inst), Err(Error::NoFrames)));
}

/// An instrument that names a fallback HWP keyword (FORS2: `RETA2 POSANG`, else `RETA2 ROT`):
/// a frame with only the fallback reads its angle from it (the same map as the good set), the
/// primary wins when both are there, and a frame with neither is refused naming both.
#[test]
fn hwp_angle_from_the_fallback_keyword() {
    let dir = tempfile::tempdir().unwrap();
    let mut inst = tiny();
    let alt = "HIERARCH ESO INS RETA2 ROT".to_string();
    inst.polarimetry.hwp_angle_fallback_keywords = vec![alt.clone()];
    let p = good_set(dir.path(), &inst);
    let bits = |m: &skyfield::StokesMap| m.q.iter().chain(&m.u).map(|v| v.to_bits()).collect::<Vec<_>>();
    let good = reduce(&p, &inst).unwrap();
    // Frame 2 (45 deg) with the angle under the fallback name only.
    let mut k = keys(&inst, 45.0, "V_BESS");
    k[0].0 = alt.clone();
    write_frame(&p[2], 64, 64, &image(&inst, 45.0), Bitpix::F64, &k).unwrap();
    let r = reduce(&p, &inst).unwrap();
    assert_eq!(r.map.hwp_angles_deg, good.map.hwp_angles_deg);
    assert_eq!(bits(&r.map), bits(&good.map));
    // Both present: the primary's 45 deg is used (the fallback's 10 deg would make a set of
    // angles without 45 and be refused).
    let mut k = keys(&inst, 45.0, "V_BESS");
    k.push((alt.clone(), KeyValue::F64(10.0), String::new()));
    write_frame(&p[2], 64, 64, &image(&inst, 45.0), Bitpix::F64, &k).unwrap();
    assert_eq!(bits(&reduce(&p, &inst).unwrap().map), bits(&good.map));
    // Neither: the error names both keywords and the file.
    let mut k = keys(&inst, 45.0, "V_BESS");
    k.remove(0);
    write_frame(&p[2], 64, 64, &image(&inst, 45.0), Bitpix::F64, &k).unwrap();
    let e = reduce(&p, &inst).unwrap_err().to_string();
    assert!(
        e.contains("'HIERARCH ESO INS RETA2 POSANG' or 'HIERARCH ESO INS RETA2 ROT'") && e.contains("f2.fits"),
        "{e}"
    );
}

/// Frames with no flux above the bias (already bias-subtracted, or the instrument's bias_adu
/// wrong): the error names those frames and the likely cause instead of "no valid bins".
#[test]
fn frames_without_flux_are_named() {
    let dir = tempfile::tempdir().unwrap();
    let inst = tiny();
    let p = good_set(dir.path(), &inst);
    write_frame(&p[0], 64, 64, &vec![0.0; 64 * 64], Bitpix::F32, &keys(&inst, 0.0, "V_BESS")).unwrap();
    write_frame(&p[2], 64, 64, &vec![-50.0; 64 * 64], Bitpix::F32, &keys(&inst, 45.0, "V_BESS")).unwrap();
    let e = reduce(&p, &inst).unwrap_err();
    assert!(matches!(e, Error::NoFlux { .. }), "{e}");
    let e = e.to_string();
    assert!(e.contains("f0.fits") && e.contains("f2.fits") && !e.contains("f1.fits") && e.contains("bias"), "{e}");
    eprintln!("{e}");
}
