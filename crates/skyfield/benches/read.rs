//! Frame reading against frame reduction: how long CFITSIO needs merely to
//! read a set of frames, and how long the whole reduction (`reduce_files`: read, check, F_i,
//! Q/U per pixel, 30 px sigma-clipped bins) takes on the same files. The target is a
//! reduction within 2x of the read time.
//!
//! A plain timing harness (no criterion: one run is seconds of work on 16 x 2048^2 frames),
//! best of `REPS` (default 3). Frames: `BENCH_FRAMES=DIR` (FITS files `*.fits`, FORS1 layout;
//! `bench/run.sh` makes them with `bench/peers/reduce_peer.py make`). Prints one JSON line.
//!
//! `BENCH_FRAMES=/tmp/frames cargo bench -p instpol-skyfield --bench read`

use fitsio::FitsFile;
use skyfield::reduce::{read_frames, reduce_files, ReduceConfig};
use std::path::PathBuf;
use std::time::Instant;

fn best<T>(reps: usize, mut f: impl FnMut() -> T) -> (f64, T) {
    let mut best = f64::INFINITY;
    let mut last = None;
    for _ in 0..reps {
        let t = Instant::now();
        let v = f();
        best = best.min(t.elapsed().as_secs_f64());
        last = Some(v);
    }
    (best, last.unwrap())
}

fn main() {
    let Ok(dir) = std::env::var("BENCH_FRAMES") else {
        eprintln!("read bench skipped: set BENCH_FRAMES to a folder of frames (bench/run.sh does)");
        return;
    };
    let reps: usize = std::env::var("REPS").ok().and_then(|s| s.parse().ok()).unwrap_or(3);
    let mut paths: Vec<PathBuf> = std::fs::read_dir(&dir)
        .expect("BENCH_FRAMES folder")
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.extension().is_some_and(|x| x == "fits"))
        .collect();
    paths.sort();
    let inst = instrument::Instrument::load("fors1").unwrap();
    // 1. CFITSIO alone: open and read every image as stored (f32), one file after the other.
    let (t_raw, npix) = best(reps, || {
        let mut n = 0usize;
        for p in &paths {
            let mut f = FitsFile::open(p).unwrap();
            let h = f.primary_hdu().unwrap();
            let v: Vec<f32> = h.read_image(&mut f).unwrap();
            n += v.len();
        }
        n
    });
    // 2. What the reduction reads with: skyfield's reader (parallel over files, checks, f64).
    let (t_read, _) = best(reps, || read_frames(&paths, &inst, &|| {}).unwrap().len());
    // 3. The whole reduction from the files.
    let cfg = ReduceConfig::default();
    let (t_reduce, bins) =
        best(reps, || reduce_files(&paths, &inst, &cfg, &|| {}).unwrap().map.valid.iter().filter(|v| **v).count());
    println!(
        "{{\"frames\": {}, \"pixels\": {npix}, \"cfitsio_read_s\": {t_raw:.4}, \"read_frames_s\": {t_read:.4}, \"reduce_files_s\": {t_reduce:.4}, \"valid_bins\": {bins}, \"threads\": {}}}",
        paths.len(),
        rayon::current_num_threads()
    );
}
