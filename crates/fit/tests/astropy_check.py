#!/usr/bin/env python3
"""Open an instpol calibration file with astropy alone and check what it says.

Usage: python3 astropy_check.py CAL.fits [CAL2.fits ...]

Not part of `cargo test` (needs `pip install astropy numpy`). Checks: the primary header's
HIERARCH IP keywords (format version, model, coefficients), the four image extensions and
their linear WCS, the BINS table, and that the radial polynomial evaluated here from the header
reproduces the MODEL_Q / MODEL_U columns the Rust writer computed.
"""
import sys

import numpy as np
from astropy.io import fits
from astropy.table import Table
from astropy.wcs import WCS


def check(path):
    with fits.open(path) as h:
        h.info()
        hd = h[0].header
        ver = hd["HIERARCH IP FORMAT VERSION"]
        model = hd["HIERARCH IP MODEL"]
        print(f"format {ver}, model {model}, instrument {hd['HIERARCH IP INSTRUMENT']}, "
              f"filter {hd['HIERARCH IP FILTER']}, lambda {hd.get('HIERARCH IP LAMBDA NM')} nm")
        for name in ("QMAP", "UMAP", "QERR", "UERR"):
            assert h[name].data.ndim == 2, name
        q = h["QMAP"]
        w = WCS(q.header)
        ny, nx = q.data.shape
        x0, y0 = w.pixel_to_world_values(0, 0)
        x1, _ = w.pixel_to_world_values(nx - 1, 0)
        print(f"QMAP {nx} x {ny}, x from {x0:.3f} to {x1:.3f} arcmin, y from {y0:.3f}")
        bins = Table(h["BINS"].data)
        print(f"BINS: {len(bins)} rows, columns {bins.colnames}")
        if model.startswith("RADIAL"):
            first = hd["HIERARCH IP RADIAL FIRST POWER"]
            deg = hd["HIERARCH IP RADIAL DEGREE"]
            c = [hd[f"HIERARCH IP RADIAL C{k}"] for k in range(first, deg + 1)]
            cx, cy = hd["HIERARCH IP CENTRE X"], hd["HIERARCH IP CENTRE Y"]
            dx, dy = bins["X_ARCMIN"] - cx, bins["Y_ARCMIN"] - cy
            r = np.hypot(dx, dy)
            p = sum(ck * r ** (first + i) for i, ck in enumerate(c))
            a = np.arctan2(dy, dx)
            mq, mu = p * np.cos(2 * a), p * np.sin(2 * a)
            err = max(np.max(np.abs(mq - bins["MODEL_Q"])), np.max(np.abs(mu - bins["MODEL_U"])))
            print(f"coefficients (%): {[round(100 * x, 5) for x in c]}, centre ({cx:.4f}, {cy:.4f}) arcmin; "
                  f"max |model here - MODEL_Q/U| = {err:.2e}")
            assert err < 1e-12, err
            # The image is the model on the grid (plus the residual map when present).
            if model == "RADIAL":
                j, i = ny // 2, nx // 3
                xx, yy = w.pixel_to_world_values(i, j)
                rr = np.hypot(xx - cx, yy - cy)
                pp = sum(ck * rr ** (first + k) for k, ck in enumerate(c))
                aa = np.arctan2(yy - cy, xx - cx)
                assert abs(pp * np.cos(2 * aa) - q.data[j, i]) < 1e-12
        print(f"{path}: OK")


if __name__ == "__main__":
    for p in sys.argv[1:]:
        check(p)
