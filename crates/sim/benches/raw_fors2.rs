//! Raw FORS2 frames against the time merely to read them: 16 exposures of
//! two chip files each (2048 x 1034 u16 with prescan and overscan rows, ESO keywords; written
//! by `sim::raw` from a uniformly polarized sky), reduced with a master bias, a master flat and
//! the overscan correction (`reduce_files_with`), against CFITSIO reading the same 32 files as
//! stored (u16), one after the other. Same files, same page cache (every file read once before
//! timing; the timings alternate: read, reduce, binary, read, ...), `REPS` repetitions (default
//! 7), wall and CPU time of each; the ratios are taken per repetition (each reduction against
//! the read just before it) and their median is reported, with the medians of the times.
//! With `INSTPOL_BIN` set to an `instpol` binary, `instpol reduce` on the same files
//! (`--instrument fors2 --bias --flat`, map written to the temporary folder) is timed in the
//! same loop: wall time, and CPU time of the child process. The binary also hashes every input
//! for its provenance record (BLAKE3, `skyfield::provenance`), a second pass over every byte
//! that the read does not make: its bound is against the read plus that hash, each file hashed
//! in turn on one core as `provenance::hash_file` does (`read_hash_wall_s`; the ratio
//! `binary_ratio_read_hash`), with the ratio against the read alone reported beside it. Prints
//! one JSON line. Frames are made in `BENCH_RAW_DIR` (kept) or a temporary folder.
//!
//! `cargo bench -p instpol-sim --bench raw_fors2`

use fitsio::FitsFile;
use instrument::Instrument;
use sim::raw::{write_raw_exposure, RawChip, RawExposure};
use skyfield::beams::BeamGeometry;
use skyfield::calib::ReadOptions;
use skyfield::reduce::{reduce_files_with, ReduceConfig};
use std::path::{Path, PathBuf};
use std::time::Instant;

/// User + system CPU seconds of this process so far, and of its waited-for children
/// (Linux `/proc/self/stat`: utime, stime, cutime, cstime).
fn cpu_times() -> (f64, f64) {
    let s = std::fs::read_to_string("/proc/self/stat").unwrap_or_default();
    let f: Vec<&str> = s.rsplit(')').next().unwrap_or("").split_whitespace().collect();
    let tick = 100.0; // USER_HZ on Linux
    let t = |i: usize| f.get(i).and_then(|x| x.parse::<f64>().ok()).unwrap_or(0.0);
    ((t(11) + t(12)) / tick, (t(13) + t(14)) / tick)
}

/// CPU seconds of this process's threads so far, to the nanosecond (the sum over
/// `/proc/self/task/*/schedstat`; rayon's threads live as long as the process), falling back to
/// the 10 ms ticks of `/proc/self/stat`.
fn cpu_s() -> f64 {
    let Ok(tasks) = std::fs::read_dir("/proc/self/task") else { return cpu_times().0 };
    let ns: u64 = tasks
        .flatten()
        .filter_map(|t| std::fs::read_to_string(t.path().join("schedstat")).ok())
        .filter_map(|s| s.split_whitespace().next().and_then(|x| x.parse::<u64>().ok()))
        .sum();
    if ns == 0 {
        cpu_times().0
    } else {
        ns as f64 * 1e-9
    }
}

/// The one median (mean of the two middles), of a vector of times.
fn median_of(mut v: Vec<f64>) -> f64 {
    stokes::stats::robust::median(&mut v, stokes::stats::robust::Middle::Mean)
}

fn timed<T>(f: impl FnOnce() -> T) -> (f64, f64, T) {
    let (c0, t0) = (cpu_s(), Instant::now());
    let v = f();
    (t0.elapsed().as_secs_f64(), cpu_s() - c0, v)
}

const CHIPS: [RawChip; 2] = [
    RawChip { bias_adu: 200.0, gain_e_per_adu: 1.25, read_noise_e: 3.0, scan: [0, 0, 5, 5] },
    RawChip { bias_adu: 212.0, gain_e_per_adu: 1.40, read_noise_e: 3.5, scan: [0, 0, 5, 5] },
];

fn make(dir: &Path, inst: &Instrument) -> (Vec<PathBuf>, PathBuf, PathBuf) {
    let (nx, ny) = (inst.detector.nx, inst.detector.ny);
    let g = BeamGeometry::new(inst);
    let flat: Vec<f64> = (0..nx * ny).map(|p| 1.0 + 0.05 * ((p % nx) as f64 / 40.0).sin()).collect();
    // Frames kept in BENCH_RAW_DIR from another beam layout (an older instrument file) would be
    // timed as if current: made again when the layout they were made with differs.
    let stamp = dir.join("layout.txt");
    let layout = format!("{:?} {:?}\n", inst.strips(), inst.polarimetry.throw_terms);
    let current = std::fs::read_to_string(&stamp).ok().as_deref() == Some(layout.as_str());
    let mut science = Vec::new();
    for k in 0..16 {
        let a = (k % 4) as f64 * 22.5;
        let stem = format!("sci{k:02}");
        if !current || !dir.join(format!("{stem}_CHIP2.fits")).exists() {
            let t = 4.0 * a.to_radians();
            let f = 0.02 * t.cos() - 0.01 * t.sin();
            let mut e = vec![0.0; nx * ny];
            for (x, y) in g.sky_pixels() {
                let (o, ee) = g.beams_of_sky(x, y).unwrap();
                e[o] = 2000.0 * (1.0 + f);
                e[ee] = 2000.0 * (1.0 - f);
            }
            let x = RawExposure {
                electrons: &e,
                hwp_deg: Some(a),
                filter: "v_HIGH".into(),
                exptime_s: 10.0,
                exposure_no: k,
                binning: None,
            };
            write_raw_exposure(inst, &x, Some(&flat), None, &CHIPS, true, k as u64, dir, &stem).unwrap();
        }
        science.push(dir.join(format!("{stem}_CHIP1.fits")));
        science.push(dir.join(format!("{stem}_CHIP2.fits")));
    }
    let (bias, flatp) = (dir.join("BIAS.fits"), dir.join("FLAT.fits"));
    if !current || !flatp.exists() {
        let zero = vec![0.0; nx * ny];
        let lamp = vec![20000.0; nx * ny];
        let mut b = Vec::new();
        let mut fl = Vec::new();
        for k in 0..3 {
            let x = RawExposure {
                electrons: &zero,
                hwp_deg: Some(0.0),
                filter: "v_HIGH".into(),
                exptime_s: 0.0,
                exposure_no: 100 + k,
                binning: None,
            };
            b.extend(
                write_raw_exposure(inst, &x, None, None, &CHIPS, false, 100 + k as u64, dir, &format!("bias{k}"))
                    .unwrap(),
            );
            let x = RawExposure {
                electrons: &lamp,
                hwp_deg: Some(0.0),
                filter: "v_HIGH".into(),
                exptime_s: 1.0,
                exposure_no: 200 + k,
                binning: None,
            };
            fl.extend(
                write_raw_exposure(inst, &x, Some(&flat), None, &CHIPS, true, 200 + k as u64, dir, &format!("flat{k}"))
                    .unwrap(),
            );
        }
        skyfield::calib::master_bias(&b, inst, 3.0).unwrap().write(&bias, inst).unwrap();
        skyfield::calib::master_flat(&fl, inst, Some(&bias), 3.0).unwrap().write(&flatp, inst).unwrap();
    }
    std::fs::write(&stamp, &layout).unwrap();
    (science, bias, flatp)
}

fn main() {
    let reps: usize = std::env::var("REPS").ok().and_then(|s| s.parse().ok()).unwrap_or(7);
    let tmp = tempfile::tempdir().unwrap();
    let dir = std::env::var("BENCH_RAW_DIR").map(PathBuf::from).unwrap_or_else(|_| tmp.path().to_path_buf());
    std::fs::create_dir_all(&dir).unwrap();
    let inst = Instrument::load("fors2").unwrap();
    let (paths, bias, flat) = make(&dir, &inst);
    let read_all = || {
        let mut n = 0usize;
        for p in &paths {
            let mut f = FitsFile::open(p).unwrap();
            let h = f.primary_hdu().unwrap();
            let v: Vec<u16> = h.read_image(&mut f).unwrap();
            n += v.len();
        }
        n
    };
    // The binary's inputs, as its provenance record hashes them.
    let hashed: Vec<PathBuf> = paths.iter().cloned().chain([bias.clone(), flat.clone()]).collect();
    let hash_all = || hashed.iter().map(|p| skyfield::provenance::hash_file(p).unwrap().len()).sum::<usize>();
    read_all(); // page cache warm for every timing
    hash_all();
    let opts = ReadOptions { bias: Some(bias.clone()), flat: Some(flat.clone()), ..Default::default() };
    let cfg = ReduceConfig::default();
    // `PROFILE_REDUCE=N`: only the library's reduction, N times (for a profiler), no timings.
    if let Some(n) = std::env::var("PROFILE_REDUCE").ok().and_then(|s| s.parse::<usize>().ok()) {
        for _ in 0..n {
            reduce_files_with(&paths, &inst, &cfg, &opts, &|| {}).unwrap();
        }
        return;
    }
    let bin = std::env::var("INSTPOL_BIN").ok().filter(|b| !b.is_empty());
    let map_out = tmp.path().join("raw_map.fits");
    let run_bin = |b: &str| -> (f64, f64) {
        let c0 = cpu_times().1;
        let t0 = Instant::now();
        let st = std::process::Command::new(b)
            .arg("reduce")
            .args(&paths)
            .args(["--instrument", "fors2", "--bias"])
            .arg(&bias)
            .arg("--flat")
            .arg(&flat)
            .arg("--out")
            .arg(&map_out)
            .stdout(std::process::Stdio::null())
            .stderr(std::process::Stdio::null())
            .status()
            .unwrap();
        let w = t0.elapsed().as_secs_f64();
        assert!(st.success(), "{b} reduce failed");
        (w, cpu_times().1 - c0)
    };
    let (mut rw, mut rc, mut dw, mut dc, mut bw, mut bc) = (vec![], vec![], vec![], vec![], vec![], vec![]);
    let mut hw = vec![];
    let (mut npix, mut bins) = (0, 0);
    for _ in 0..reps {
        let (w, c, n) = timed(read_all);
        rw.push(w);
        rc.push(c);
        npix = n;
        let (w, c, b) = timed(|| {
            reduce_files_with(&paths, &inst, &cfg, &opts, &|| {}).unwrap().map.valid.iter().filter(|v| **v).count()
        });
        dw.push(w);
        dc.push(c);
        bins = b;
        if let Some(b) = &bin {
            let (w, _, _) = timed(hash_all);
            hw.push(w);
            let (w, c) = run_bin(b);
            bw.push(w);
            bc.push(c);
        }
    }
    let ratios = |a: &[f64], r: &[f64]| median_of(a.iter().zip(r).map(|(x, y)| x / y.max(1e-9)).collect());
    let mut json = format!(
        "{{\"files\": {}, \"pixels\": {npix}, \"reps\": {reps}, \"cfitsio_read_wall_s\": {:.4}, \"cfitsio_read_cpu_s\": {:.4}, \"reduce_raw_wall_s\": {:.4}, \"reduce_raw_cpu_s\": {:.4}, \"ratio_wall\": {:.3}, \"ratio_cpu\": {:.3}, \"best_ratio_wall\": {:.3}",
        paths.len(),
        median_of(rw.clone()),
        median_of(rc.clone()),
        median_of(dw.clone()),
        median_of(dc.clone()),
        ratios(&dw, &rw),
        ratios(&dc, &rc),
        dw.iter().cloned().fold(f64::INFINITY, f64::min) / rw.iter().cloned().fold(f64::INFINITY, f64::min),
    );
    if !bw.is_empty() {
        json += &format!(
            ", \"binary_wall_s\": {:.4}, \"binary_cpu_s\": {:.4}, \"binary_ratio_wall\": {:.3}, \"binary_ratio_cpu\": {:.3}, \"hash_wall_s\": {:.4}, \"read_hash_wall_s\": {:.4}, \"binary_ratio_read_hash\": {:.3}",
            median_of(bw.clone()),
            median_of(bc.clone()),
            ratios(&bw, &rw),
            ratios(&bc, &rc),
            median_of(hw.clone()),
            median_of(rw.iter().zip(&hw).map(|(r, h)| r + h).collect()),
            ratios(&bw, &rw.iter().zip(&hw).map(|(r, h)| r + h).collect::<Vec<_>>()),
        );
    }
    json += &format!(", \"valid_bins\": {bins}, \"threads\": {}}}", rayon::current_num_threads());
    println!("{json}");
}
