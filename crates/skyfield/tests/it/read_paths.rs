//! The reduction reads frames two ways: `reduce_files` decodes rows straight from the files
//! (big-endian f32, f64, i16 and unsigned-16 pixels) and sends everything else (scaled data)
//! through CFITSIO; `read_frames` + `FrameSet` + `reduce_set` has CFITSIO read every frame
//! whole into f64. Both must give the same map, bit for bit: each stored type, repeated
//! exposures at one angle (summed in the order given), masked pixels, and a scaled frame whose
//! BZERO only CFITSIO applies.

use instrument::Instrument;
use skyfield::calib::ReadOptions;
use skyfield::fits::{write_frame, Bitpix, KeyValue};
use skyfield::reduce::{read_frames, reduce_files, reduce_set, DiskFrames, FrameSet, FrameSource, ReduceConfig};
use std::path::{Path, PathBuf};

use crate::common;

fn tiny() -> Instrument {
    common::tiny_with_bias(180.0)
}

fn keys(inst: &Instrument, hwp: f64, extra: &[(&str, f64)]) -> Vec<(String, KeyValue, String)> {
    common::keys(inst, hwp, "V_BESS", extra)
}

/// Deterministic noise in [-0.5, 0.5) (a hash of the pixel and frame).
fn noise(i: usize, frame: usize) -> f64 {
    let mut h = (i as u64 ^ ((frame as u64) << 32)).wrapping_mul(0x9E37_79B9_7F4A_7C15);
    h ^= h >> 29;
    h = h.wrapping_mul(0xBF58_476D_1CE4_E5B9);
    h ^= h >> 32;
    (h >> 11) as f64 / (1u64 << 53) as f64 - 0.5
}

/// A sky of `Q/I = 0.012`, `U/I = -0.007` (eq:F) with noise of a few tens of ADU, integer
/// valued (so that the unsigned 16-bit frames hold it exactly), a bright star, a NaN and a
/// saturated pixel.
fn image(inst: &Instrument, hwp_deg: f64, frame: usize) -> Vec<f64> {
    let g = skyfield::BeamGeometry::new(inst);
    let d = &inst.detector;
    let t = 4.0 * hwp_deg.to_radians();
    let f = 0.012 * t.cos() - 0.007 * t.sin();
    let mut v: Vec<f64> = (0..g.nx * g.ny).map(|i| (d.bias_adu + 40.0 * noise(i, frame)).round()).collect();
    for (x, y) in g.sky_pixels() {
        let (o, e) = g.beams_of_sky(x, y).unwrap();
        let star = if (x as f64 - 30.0).hypot(y as f64 - 12.0) < 2.5 { 20000.0 } else { 0.0 };
        v[o] = (d.bias_adu + (3000.0 + star) * (1.0 + f) + 60.0 * noise(o, frame + 99)).round();
        v[e] = (d.bias_adu + (3000.0 + star) * (1.0 - f) + 60.0 * noise(e, frame + 199)).round();
    }
    let sky: Vec<(usize, usize)> = g.sky_pixels().collect();
    let (x, y) = sky[sky.len() / 5 + frame % 3];
    v[g.beams_of_sky(x, y).unwrap().0] = f64::NAN;
    let (x, y) = sky[sky.len() / 2];
    v[g.beams_of_sky(x, y).unwrap().1] = d.saturation_adu + 10.0;
    v
}

fn write_set(dir: &Path, inst: &Instrument, bitpix: Bitpix) -> Vec<PathBuf> {
    // N = 8, with a second exposure at 22.5 deg.
    let angles = [0.0, 22.5, 45.0, 67.5, 90.0, 112.5, 135.0, 157.5, 22.5];
    angles
        .iter()
        .enumerate()
        .map(|(k, &a)| {
            let p = dir.join(format!("f{k}.fits"));
            let mut img = image(inst, a, k);
            if bitpix == Bitpix::U16 {
                // NaN cannot be stored in integers.
                img.iter_mut().filter(|v| v.is_nan()).for_each(|v| *v = 0.0);
            }
            write_frame(&p, 64, 64, &img, bitpix, &keys(inst, a, &[])).unwrap();
            p
        })
        .collect()
}

fn assert_same_map(a: &skyfield::StokesMap, b: &skyfield::StokesMap, what: &str) {
    assert_eq!(a.valid, b.valid, "{what}: valid bins");
    let cols = |m: &skyfield::StokesMap| {
        [
            m.q.clone(),
            m.u.clone(),
            m.sigma_q.clone(),
            m.sigma_u.clone(),
            m.cov_qu.clone(),
            m.sigma_q_phot.clone(),
            m.sigma_u_phot.clone(),
            m.intensity.clone(),
        ]
    };
    for (c, (x, y)) in cols(a).iter().zip(cols(b).iter()).enumerate() {
        for k in (0..x.len()).filter(|&k| a.valid[k]) {
            assert_eq!(x[k].to_bits(), y[k].to_bits(), "{what}: column {c}, bin {k}: {} vs {}", x[k], y[k]);
        }
    }
    assert_eq!(a.n_pixels, b.n_pixels, "{what}: kept pixels");
}

#[test]
fn rows_from_files_equal_whole_frames_for_every_stored_type() {
    let inst = tiny();
    let cfg = ReduceConfig { bin_px: 4, ..Default::default() };
    for bitpix in [Bitpix::F32, Bitpix::F64, Bitpix::U16] {
        let dir = tempfile::tempdir().unwrap();
        let paths = write_set(dir.path(), &inst, bitpix);
        let fast = reduce_files(&paths, &inst, &cfg, &|| {}).unwrap();
        let set = FrameSet::from_frames(read_frames(&paths, &inst, &|| {}).unwrap(), &inst, true).unwrap();
        let whole = reduce_set(&set, &inst, &cfg).unwrap();
        assert!(fast.map.n_valid() >= 20, "{bitpix:?}: {} valid bins", fast.map.n_valid());
        assert_same_map(&fast.map, &whole.map, &format!("{bitpix:?}"));
        // The masked pixels are reported, naming the frames.
        let w: Vec<String> = fast.warnings.iter().map(|w| w.to_string()).collect();
        assert!(w.iter().any(|w| w.contains("f0.fits") && w.contains("1 saturated")), "{bitpix:?}: {w:?}");
        if bitpix != Bitpix::U16 {
            assert!(w.iter().any(|w| w.contains("f1.fits") && w.contains("1 NaN")), "{bitpix:?}: {w:?}");
        }
        // The frame reader the catalog streams with (`DiskFrames`, rows decoded and counted in
        // one pass) counts the same pixels and gives each angle the whole frame's values.
        let disk = DiskFrames::open(&paths, &inst, &ReadOptions::default(), true).unwrap();
        for i in 0..disk.angles_deg().len() {
            let want = set.data[i].clone();
            let mut got = Vec::new();
            disk.with_frame_rows(i, &mut |rows| got = rows.to_vec()).unwrap();
            assert!(
                got.len() == want.len() && got.iter().zip(&want).all(|(a, b)| a.to_bits() == b.to_bits()),
                "{bitpix:?}: angle {i}: streamed rows differ from the frame"
            );
        }
        let w: Vec<String> = disk.bad_pixel_warnings().unwrap().iter().map(|w| w.to_string()).collect();
        assert!(w.iter().any(|w| w.contains("f0.fits") && w.contains("1 saturated")), "{bitpix:?}: {w:?}");
        if bitpix != Bitpix::U16 {
            assert!(w.iter().any(|w| w.contains("f1.fits") && w.contains("1 NaN")), "{bitpix:?}: {w:?}");
        }
    }
}

/// A frame with BZERO (scaled data) goes through CFITSIO, which applies it: a row reader that
/// ignored the keyword would see every value 250 ADU low and give another map.
#[test]
fn scaled_frame_goes_through_cfitsio() {
    let inst = tiny();
    let cfg = ReduceConfig { bin_px: 4, ..Default::default() };
    let dir = tempfile::tempdir().unwrap();
    let paths = write_set(dir.path(), &inst, Bitpix::F32);
    // Rewrite frame 3 as f32 values 250 ADU low with BZERO = 250.
    let a = 67.5;
    let img: Vec<f64> = image(&inst, a, 3).iter().map(|v| v - 250.0).collect();
    write_frame(&paths[3], 64, 64, &img, Bitpix::F32, &keys(&inst, a, &[("BZERO", 250.0)])).unwrap();
    let fast = reduce_files(&paths, &inst, &cfg, &|| {}).unwrap();
    let set = FrameSet::from_frames(read_frames(&paths, &inst, &|| {}).unwrap(), &inst, true).unwrap();
    let whole = reduce_set(&set, &inst, &cfg).unwrap();
    assert_same_map(&fast.map, &whole.map, "BZERO frame");
    // And the unscaled set gives the same Q, U to rounding (the frame's values are those).
    let plain =
        reduce_files(&write_set(tempfile::tempdir().unwrap().path(), &inst, Bitpix::F32), &inst, &cfg, &|| {}).unwrap();
    for k in (0..plain.map.q.len()).filter(|&k| plain.map.valid[k]) {
        assert!((plain.map.q[k] - fast.map.q[k]).abs() < 1e-9, "bin {k}");
    }
}

/// A frame cut short inside its image is refused by the row reader, naming the file.
#[test]
fn truncated_frame_is_named_by_the_row_reader() {
    let inst = tiny();
    let dir = tempfile::tempdir().unwrap();
    let paths = write_set(dir.path(), &inst, Bitpix::F32);
    let bytes = std::fs::read(&paths[5]).unwrap();
    std::fs::write(&paths[5], &bytes[..2880 + 64 * 64 * 2]).unwrap();
    let e = reduce_files(&paths, &inst, &ReduceConfig::default(), &|| {}).unwrap_err().to_string();
    assert!(e.contains("f5.fits") && e.contains("truncated"), "{e}");
}
