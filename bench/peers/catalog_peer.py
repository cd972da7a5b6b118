#!/usr/bin/env python3
"""Peer for `instpol catalog` (issue 13's speed target): the same steps with photutils and
astropy, written for this benchmark (not copied from any pipeline).

  make DIR      write a scene of ~500 stars in the FORS1 strips and simulate 16 frames with
                instpol (2048 x 2048, 16 HWP angles) into DIR
  run DIR       detect on the first frame (DAOStarFinder, 5 sigma), pair o/e by the FORS1 throw
                (110 px along y), re-centre every star in every frame (centroid_com), exact
                circular apertures and sigma-clipped annulus backgrounds per beam, F_i, Q, U
                per star; prints JSON with the time and the star count
"""
import json, sys, time, glob, os, subprocess
import numpy as np

FWHM, R, RIN, ROUT, THROW = 4.0, 6.0, 9.0, 14.0, 110.0


def make(d, instpol):
    os.makedirs(d, exist_ok=True)
    rng = np.random.default_rng(1)
    lines = ['instrument = "fors1"', 'filter = "V"', 'seed = 3',
             'hwp_angles_deg = [' + ", ".join(str(22.5 * i) for i in range(16)) + ']',
             '[output]', 'bitpix = -32', '[sky]', 'brightness_e = 300', 'p = 0.01',
             '[effects]', 'photon_noise = true', 'read_noise = true']
    n = 0
    for k in range(9):
        y0 = 34 + 220 * k + 55
        for i in range(56):
            x = 30 + 35.5 * i + rng.uniform(-3, 3)
            y = y0 + rng.uniform(-15, 15)
            lines += ['[[stars]]', f'x = {x:.2f}', f'y = {y:.2f}', 'coords = "pixel"',
                      f'flux_e = {10 ** rng.uniform(4.3, 5.5):.1f}', f'p = {rng.uniform(0, 0.05):.4f}',
                      f'chi_deg = {rng.uniform(0, 180):.1f}', 'fwhm_arcsec = 0.8']
            n += 1
    open(os.path.join(d, "scene.toml"), "w").write("\n".join(lines) + "\n")
    subprocess.run([instpol, "simulate", os.path.join(d, "scene.toml"), "--out", d], check=True,
                   stdout=subprocess.DEVNULL)
    print(json.dumps({"stars": n}))


def run(d):
    from astropy.io import fits
    from astropy.stats import sigma_clipped_stats
    from photutils.detection import DAOStarFinder
    from photutils.centroids import centroid_com, centroid_sources
    from photutils.aperture import CircularAperture, CircularAnnulus, aperture_photometry, ApertureStats
    t0 = time.perf_counter()
    files = sorted(glob.glob(os.path.join(d, "frame_*.fits")))
    frames, theta = [], []
    for f in files:
        with fits.open(f) as h:
            frames.append(h[0].data.astype(float))
            theta.append(np.radians(float(h[0].header["HIERARCH ESO INS RETA2 POSANG"])))
    theta = np.array(theta)
    img = frames[0]
    mean, med, std = sigma_clipped_stats(img[img > 0], sigma=3.0)
    src = DAOStarFinder(fwhm=FWHM, threshold=5.0 * std)(img - med)
    x, y = np.array(src["xcentroid"]), np.array(src["ycentroid"])
    # o/e pairs: a source THROW px above another (FORS1: e image at +throw along y).
    pairs = []
    for i in range(len(x)):
        d2 = (x - x[i]) ** 2 + (y - (y[i] + THROW)) ** 2
        j = int(np.argmin(d2))
        if d2[j] < 1.5 ** 2:
            pairs.append((i, j))
    po = np.array([(x[i], y[i]) for i, _ in pairs])
    pe = np.array([(x[j], y[j]) for _, j in pairs])
    fo = np.zeros((len(frames), len(pairs)))
    fe = np.zeros_like(fo)
    for k, fr in enumerate(frames):
        for pos, out in ((po, fo), (pe, fe)):
            cx, cy = centroid_sources(fr, pos[:, 0], pos[:, 1], box_size=11, centroid_func=centroid_com)
            c = np.column_stack([cx, cy])
            ap = CircularAperture(c, r=R)
            an = CircularAnnulus(c, r_in=RIN, r_out=ROUT)
            bkg = ApertureStats(fr, an).median
            phot = aperture_photometry(fr, ap, method="exact")
            out[k] = np.array(phot["aperture_sum"]) - bkg * ap.area
    F = (fo - fe) / (fo + fe)
    N = len(theta)
    q = 2.0 / N * (F * np.cos(4 * theta)[:, None]).sum(axis=0)
    u = 2.0 / N * (F * np.sin(4 * theta)[:, None]).sum(axis=0)
    dt = time.perf_counter() - t0
    print(json.dumps({"total_s": dt, "stars": len(pairs), "median_p": float(np.median(np.hypot(q, u)))}))


if __name__ == "__main__":
    if sys.argv[1] == "make":
        make(sys.argv[2], sys.argv[3] if len(sys.argv) > 3 else "target/release/instpol")
    else:
        run(sys.argv[2])
