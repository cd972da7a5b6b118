"""Write the tiny FITS files of crates/skyfield/tests/it/formats.rs with astropy, and what astropy
reads from them (expected.json), so the Rust reader is checked against an independent one.

Run from this folder:  python3 make_formats.py   (astropy >= 6, numpy). The files are committed;
the tests do not need astropy.
"""
import gzip
import json
import shutil

import numpy as np
from astropy.io import fits

NX, NY = 12, 20
HWP = "HIERARCH ESO INS RETA2 POSANG"
FILT = "HIERARCH ESO INS FILT1 NAME"
rng = np.random.default_rng(12)


def keys(h, hwp=22.5):
    h[HWP] = hwp
    h[FILT] = "V_BESS"
    h["EXPTIME"] = 30.0


def values(kind):
    """Pixel values covering each type's range, including its extremes."""
    if kind == "u8":
        v = rng.integers(0, 256, (NY, NX)).astype(np.uint8); v[0, 0] = 0; v[0, 1] = 255
    elif kind == "i8":
        v = rng.integers(-128, 128, (NY, NX)).astype(np.int8); v[0, 0] = -128; v[0, 1] = 127
    elif kind == "i16":
        v = rng.integers(-32768, 32768, (NY, NX)).astype(np.int16); v[0, 0] = -32768
    elif kind == "u16":
        v = rng.integers(0, 65536, (NY, NX)).astype(np.uint16); v[0, 0] = 65535
    elif kind == "i32":
        v = rng.integers(-2**31, 2**31, (NY, NX)).astype(np.int32)
    elif kind == "u32":
        v = rng.integers(0, 2**32, (NY, NX)).astype(np.uint32); v[0, 0] = 2**32 - 1
    elif kind == "i64":
        v = rng.integers(-2**40, 2**40, (NY, NX)).astype(np.int64)
    elif kind == "f32":
        v = (rng.normal(1000, 300, (NY, NX))).astype(np.float32); v[1, 1] = np.nan
    elif kind == "f64":
        v = rng.normal(1000, 300, (NY, NX)); v[2, 2] = np.nan
    return v


expected = []


def record(name, spec, hdu_index):
    """What astropy reads from `name` at `hdu_index`: scaled values, BLANK pixels as NaN."""
    with fits.open(name, do_not_scale_image_data=True) as f:
        raw = f[hdu_index].data.copy()
        blank = f[hdu_index].header.get("BLANK")
    with fits.open(name) as f:
        data = np.asarray(f[hdu_index].data, dtype=np.float64)
    if blank is not None:
        data[raw == blank] = np.nan
    expected.append({
        "file": spec,
        "nx": data.shape[1],
        "ny": data.shape[0],
        "values": [None if np.isnan(x) else float(x) for x in data.ravel()],
    })


# Every BITPIX with its unsigned/signed conventions, in the primary HDU.
for kind in ["u8", "i8", "i16", "u16", "i32", "u32", "i64", "f32", "f64"]:
    h = fits.PrimaryHDU(values(kind))
    keys(h.header)
    h.writeto(f"prim_{kind}.fits", overwrite=True)
    record(f"prim_{kind}.fits", f"prim_{kind}.fits", 0)

# BSCALE/BZERO scaling of 16-bit integers (not the unsigned convention).
v = rng.integers(-3000, 3000, (NY, NX)).astype(np.int16)
h = fits.PrimaryHDU(v)
h.header["BSCALE"] = 0.5
h.header["BZERO"] = 100.0
keys(h.header)
h.writeto("prim_scaled.fits", overwrite=True)
record("prim_scaled.fits", "prim_scaled.fits", 0)

# BLANK: flagged pixels are no data.
v = rng.integers(100, 5000, (NY, NX)).astype(np.int16)
v[3, 4] = v[7, 7] = v[19, 11] = -32768
h = fits.PrimaryHDU(v)
h.header["BLANK"] = -32768
keys(h.header)
h.writeto("prim_blank.fits", overwrite=True)
record("prim_blank.fits", "prim_blank.fits", 0)

# Header-only primary + the image in extension 1 (found automatically; keywords in the primary).
p = fits.PrimaryHDU()
keys(p.header)
img = fits.ImageHDU(values("f32"), name="SCI")
fits.HDUList([p, img]).writeto("ext1.fits", overwrite=True)
record("ext1.fits", "ext1.fits", 1)

# A table in extension 1 and two images: chosen by [2], by [CHIP1], ...
p = fits.PrimaryHDU()
keys(p.header)
tab = fits.BinTableHDU.from_columns([fits.Column(name="A", format="E", array=np.arange(5, dtype=np.float32))], name="TAB")
c1 = fits.ImageHDU(values("u16"), name="CHIP1")
c2 = fits.ImageHDU(values("i16"), name="CHIP2")
fits.HDUList([p, tab, c1, c2]).writeto("mef.fits", overwrite=True)
record("mef.fits", "mef.fits[2]", 2)
record("mef.fits", "mef.fits[CHIP2]", 3)

# A file whose own name has brackets.
shutil.copy("prim_f32.fits", "odd[1].fits")
record("odd[1].fits", "odd[1].fits", 0)

# gzip of a whole file.
with open("prim_u16.fits", "rb") as src, gzip.open("gz_u16.fits.gz", "wb") as dst:
    dst.write(src.read())
record("gz_u16.fits.gz", "gz_u16.fits.gz", 0)

# fpack-style tile compression (RICE, lossless for integers; image in extension 1).
p = fits.PrimaryHDU()
keys(p.header)
comp = fits.CompImageHDU(values("u16"), compression_type="RICE_1")
fits.HDUList([p, comp]).writeto("rice_u16.fits.fz", overwrite=True)
record("rice_u16.fits.fz", "rice_u16.fits.fz", 1)
comp = fits.CompImageHDU(values("i32"), compression_type="GZIP_2")
fits.HDUList([p, comp]).writeto("gzip2_i32.fits.fz", overwrite=True)
record("gzip2_i32.fits.fz", "gzip2_i32.fits.fz", 1)

with open("expected.json", "w") as f:
    json.dump(expected, f, indent=0)
print(f"{len(expected)} cases")
