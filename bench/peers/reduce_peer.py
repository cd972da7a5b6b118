#!/usr/bin/env python3
"""Straightforward numpy + astropy peer of `instpol reduce` (issue 8 benchmark).

make DIR   write 16 FORS1-like frames (2048 x 2048 float32, HWP angles i * 22.5 deg, V filter,
           ESO HIERARCH keywords) of a 2 % polarized sky with Poisson-like noise.
calibrate DIR  reduce, then the sky-field solution per bin (eq:approx: p = hypot(q1 - q0,
           u1 - u0) for the known sky 2 % at 30 deg) and a least-squares cubic p(r) = c1 r +
           c2 r^2 + c3 r^3 (r in arcmin from the centre, numpy lstsq). Prints JSON timings.
reduce DIR read the 16 frames (astropy.io.fits), per pixel of the mask strips F_i = (o - e)/(o + e)
           (o rows of each strip, e rows one throw above), Q = 2/N sum F_i cos 4 theta_i,
           U = 2/N sum F_i sin 4 theta_i, then 30 x 30 px bins with
           astropy.stats.sigma_clipped_stats (3 sigma) on Q and U. Prints JSON timings.
"""
import json
import sys
import time
from pathlib import Path

import numpy as np
from astropy.io import fits
from astropy.stats import sigma_clipped_stats

NX = NY = 2048
THROW = 110          # 22 arcsec at 0.2 arcsec/px
FIRST = 34
STRIPS = 9
BIN = 30
N = 16


def make(d: Path):
    d.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(1)
    y = np.arange(NY)[:, None]
    in_o = np.zeros((NY, 1), bool)
    in_e = np.zeros((NY, 1), bool)
    for k in range(STRIPS):
        o0 = FIRST + 2 * k * THROW
        in_o |= (y >= o0) & (y < o0 + THROW)
        in_e |= (y >= o0 + THROW) & (y < o0 + 2 * THROW)
    for i in range(N):
        th = np.deg2rad(22.5 * i)
        m = 0.02 * np.cos(4 * th - 2 * np.deg2rad(30.0))
        sky = np.zeros((NY, NX))  # the masked strips dark, as the mask makes them
        sky = np.where(in_o, 2000.0 * (1 + m), sky)
        sky = np.where(in_e, 2000.0 * (1 - m), sky)
        data = (sky + rng.normal(0, 45.0, sky.shape)).astype(np.float32)
        h = fits.Header()
        h["HIERARCH ESO INS RETA2 POSANG"] = 22.5 * i
        h["HIERARCH ESO INS FILT1 NAME"] = "V"
        h["EXPTIME"] = 10.0
        fits.PrimaryHDU(data, h).writeto(d / f"frame_{i:02d}.fits", overwrite=True)


def reduce(d: Path, quiet=False):
    t0 = time.perf_counter()
    files = sorted(d.glob("frame_*.fits"))
    frames, theta = [], []
    for f in files:
        with fits.open(f, memmap=False) as h:
            frames.append(h[0].data.astype(np.float64))
            theta.append(np.deg2rad(h[0].header["HIERARCH ESO INS RETA2 POSANG"]))
    t_read = time.perf_counter() - t0
    theta = np.array(theta)
    n = len(theta)
    q = np.zeros((STRIPS * THROW, NX))
    u = np.zeros_like(q)
    rows = np.concatenate([np.arange(FIRST + 2 * k * THROW, FIRST + (2 * k + 1) * THROW) for k in range(STRIPS)])
    for fr, th in zip(frames, theta):
        o = fr[rows]
        e = fr[rows + THROW]
        f = (o - e) / (o + e)
        q += 2.0 / n * f * np.cos(4 * th)
        u += 2.0 / n * f * np.sin(4 * th)
    t_pix = time.perf_counter() - t0 - t_read
    # Bins of 30 x 30 detector pixels over the strip pixels (bins group by detector y).
    qb, ub, xc, yc = [], [], [], []
    ydet = rows
    for y0 in range(0, NY, BIN):
        sel = (ydet >= y0) & (ydet < y0 + BIN)
        if not sel.any():
            continue
        for x0 in range(0, NX, BIN):
            blk_q = q[sel, x0:x0 + BIN]
            blk_u = u[sel, x0:x0 + BIN]
            qb.append(sigma_clipped_stats(blk_q, sigma=3.0)[0])
            ub.append(sigma_clipped_stats(blk_u, sigma=3.0)[0])
            xc.append(x0 + 0.5 * min(BIN, NX - x0) - 0.5)
            yc.append(ydet[sel].mean())
    t_total = time.perf_counter() - t0
    if quiet:
        return t0, np.array(qb), np.array(ub), np.array(xc), np.array(yc)
    print(json.dumps({"read_s": t_read, "pixels_s": t_pix, "bins_s": t_total - t_read - t_pix,
                      "total_s": t_total, "bins": len(qb), "median_q": float(np.median(qb)),
                      "median_u": float(np.median(ub))}))


def calibrate(d: Path):
    t0, qb, ub, xc, yc = reduce(d, quiet=True)
    q0, u0 = 0.02 * np.cos(np.deg2rad(60.0)), 0.02 * np.sin(np.deg2rad(60.0))
    p = np.hypot(qb - q0, ub - u0)
    scale = 0.2 / 60.0
    r = np.hypot((xc - 1023.5) * scale, (yc - 1023.5) * scale)
    a = np.stack([r, r**2, r**3], axis=1)
    c, *_ = np.linalg.lstsq(a, p, rcond=None)
    print(json.dumps({"total_s": time.perf_counter() - t0, "bins": int(len(p)), "coefficients": c.tolist()}))


if __name__ == "__main__":
    cmd, d = sys.argv[1], Path(sys.argv[2])
    {"make": make, "reduce": reduce, "calibrate": calibrate}[cmd](d)
