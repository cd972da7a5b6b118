//! Shared pieces of the cargo-fuzz targets (issue 8): a scratch folder per fuzzing process
//! (loaders that read from a path get the input written there), a 64 x 64 px instrument that
//! keeps frames and plans small, and the seed mode that writes the generated FITS seeds
//! (too big to keep in git; fuzz/run.sh makes them).

use std::path::{Path, PathBuf};
use std::sync::OnceLock;

/// A 64 x 64 px instrument with FORS1's keywords and broad-band filters (4 arcsec/px, so the
/// field is 4.27 arcmin across and the repo's scenes fit).
pub const MINI: &str = r#"name = "MINI"
[detector]
nx = 64
ny = 64
pixel_scale_arcsec = 4.0
gain_e_per_adu = 1.25
read_noise_e = 5.0
saturation_adu = 65535.0
[field]
width_arcmin = 4.27
height_arcmin = 4.27
[polarimetry]
throw_arcsec = 24.0
strip_axis = "y"
strip_count = 4
first_strip_y_px = 4
extraordinary_offset_sign = 1
hwp_angle_keyword = "HIERARCH ESO INS RETA2 POSANG"
filter_keyword = "HIERARCH ESO INS FILT1 NAME"
exptime_keyword = "EXPTIME"
[[filters]]
name = "B"
lambda_eff_nm = 429.0
[[filters]]
name = "V"
aliases = ["V_BESS"]
lambda_eff_nm = 554.0
[[filters]]
name = "I"
lambda_eff_nm = 768.0
"#;

/// This process's scratch folder (under `$TMPDIR`; run.sh points that at a folder it removes).
pub fn scratch() -> &'static Path {
    static DIR: OnceLock<PathBuf> = OnceLock::new();
    DIR.get_or_init(|| {
        let d = std::env::temp_dir().join(format!("instpol-fuzz-{}", std::process::id()));
        std::fs::create_dir_all(&d).expect("cannot create the fuzz scratch folder");
        std::fs::write(d.join("mini.toml"), MINI).expect("cannot write mini.toml");
        d
    })
}

/// Write one input to `scratch()/name` and return its path.
pub fn write_input(name: &str, data: &[u8]) -> PathBuf {
    let p = scratch().join(name);
    std::fs::write(&p, data).expect("cannot write the fuzz input");
    p
}

/// The 64 x 64 instrument, loaded once.
pub fn mini() -> &'static instrument::Instrument {
    static INST: OnceLock<instrument::Instrument> = OnceLock::new();
    INST.get_or_init(|| {
        instrument::Instrument::from_toml_str(MINI, &scratch().join("mini.toml")).expect("MINI is a valid instrument")
    })
}

/// Seed mode: when `INSTPOL_FUZZ_SEEDS=<dir>` is set, `write` fills `<dir>` with this target's
/// generated seeds and the process exits before fuzzing (`cargo fuzz run <t> -- -runs=0`).
pub fn seed_mode(write: impl FnOnce(&Path)) {
    if let Some(dir) = std::env::var_os("INSTPOL_FUZZ_SEEDS") {
        let dir = PathBuf::from(dir);
        std::fs::create_dir_all(&dir).expect("cannot create the seed folder");
        write(&dir);
        std::process::exit(0);
    }
}

/// 64 x 64 frames of `MINI` at the four optimal HWP angles, in the stored types the reader
/// distinguishes (unsigned 16-bit, f32, f64).
pub fn write_frame_seeds(dir: &Path) {
    use skyfield::fits::{write_frame, Bitpix, KeyValue};
    let types = [Bitpix::U16, Bitpix::F32, Bitpix::F64, Bitpix::U16];
    for (i, (a, bp)) in [0.0, 22.5, 45.0, 67.5].iter().zip(types).enumerate() {
        let keys = vec![
            ("HIERARCH ESO INS RETA2 POSANG".to_string(), KeyValue::F64(*a), String::new()),
            ("HIERARCH ESO INS FILT1 NAME".to_string(), KeyValue::Str("V".into()), String::new()),
            ("EXPTIME".to_string(), KeyValue::F64(300.0), String::new()),
        ];
        let data: Vec<f64> =
            (0..64 * 64).map(|k| 1000.0 + (k % 7) as f64 + if k == 100 { f64::NAN } else { 0.0 }).collect();
        write_frame(&dir.join(format!("frame{i}.fits")), 64, 64, &data, bp, &keys).expect("writing a seed frame");
    }
}

/// Small calibrations (radial, radial + residual, map; a few bins, a coarse grid, two input
/// names) made from the full-size ones that `instpol demo --no-frames` writes into
/// `INSTPOL_FUZZ_DEMO`, so that libFuzzer's mutations land on headers and tables rather than
/// on 700 kB of image data.
pub fn write_calibration_seeds(dir: &Path) {
    let demo = PathBuf::from(std::env::var_os("INSTPOL_FUZZ_DEMO").expect("set INSTPOL_FUZZ_DEMO to a demo folder"));
    let shrink = |mut c: fit::Calibration, step_bins: usize| {
        let r = c.region;
        let step = ((r.x_max - r.x_min).max(r.y_max - r.y_min) / 5.0).max(0.1);
        c.grid = Some(c.gridded(step));
        c.bins = c.bins.iter().step_by(step_bins.max(1)).cloned().collect();
        c.provenance.inputs = vec!["frame_0.fits".into(), "frame_22.5_long_name.fits".into()];
        c
    };
    for name in ["cal_V", "cal_B"] {
        let c = fit::Calibration::load(&demo.join(format!("{name}.fits"))).expect("demo calibration");
        let k = (c.bins.len() / 40).max(1);
        let small = shrink(c, k);
        small.save(&dir.join(format!("{name}.fits"))).expect("writing a seed calibration");
        if name == "cal_V" {
            let mut m = small.clone();
            let g = m.grid.clone().expect("grid");
            m.model = fit::Model::Map(g);
            m.bins.truncate(3);
            m.provenance.inputs.clear();
            m.save(&dir.join("map_V.fits")).expect("writing a seed map calibration");
        }
    }
}

/// The files the scene seeds name, in the scratch folder: the 64 x 64 instrument, a ray-trace
/// field file, and 8 x 8 Q/U maps (also used as an extended-source image).
pub fn scene_files() {
    use skyfield::fits::{write_frame, Bitpix};
    let d = scratch();
    std::fs::write(d.join("field.json"), include_str!("../seeds/field_file/fors1_V.json")).expect("field.json");
    let q: Vec<f64> = (0..64).map(|k| 0.001 * (k % 8) as f64).collect();
    let u: Vec<f64> = (0..64).map(|k| if k == 9 { f64::NAN } else { -0.0005 * (k / 8) as f64 }).collect();
    write_frame(&d.join("q.fits"), 8, 8, &q, Bitpix::F64, &[]).expect("q.fits");
    write_frame(&d.join("u.fits"), 8, 8, &u, Bitpix::F64, &[]).expect("u.fits");
}

/// Seeds of the Q/U map readers: an 8 x 8 2-D map (f64), a 64 x 64 image (f32), and `(2, 8, 8)` cubes (value plane,
/// error plane) in f32 and f64, as the FORS2 maps that `import-map` reads.
pub fn write_map_seeds(dir: &Path) {
    use fitsio::images::{ImageDescription, ImageType};
    let q: Vec<f64> = (0..64).map(|k| if k == 9 { f64::NAN } else { 0.001 * (k % 8) as f64 }).collect();
    skyfield::fits::write_frame(&dir.join("map2d.fits"), 8, 8, &q, skyfield::fits::Bitpix::F64, &[])
        .expect("writing map2d.fits");
    let img: Vec<f64> = (0..64 * 64).map(|k| 100.0 + (k % 64) as f64).collect();
    skyfield::fits::write_frame(&dir.join("image64.fits"), 64, 64, &img, skyfield::fits::Bitpix::F32, &[])
        .expect("writing image64.fits");
    for (name, ty) in [("cube64.fits", ImageType::Double), ("cube32.fits", ImageType::Float)] {
        let p = dir.join(name);
        let _ = std::fs::remove_file(&p);
        let desc = ImageDescription { data_type: ty, dimensions: &[2, 8, 8] };
        let mut f = fitsio::FitsFile::create(&p).with_custom_primary(&desc).open().expect("creating a seed cube");
        let hdu = f.primary_hdu().expect("primary HDU");
        let mut v = q.clone();
        v.extend((0..64).map(|k| 1e-4 + 1e-6 * k as f64));
        hdu.write_image(&mut f, &v).expect("writing a seed cube");
    }
}
