"""astropy reads every output of every command without a warning (issue 15, Must show).

Runs the `instpol` binary (env INSTPOL_BIN, default target/release/instpol) to make the outputs
of every command that writes files -- demo, simulate, master-bias, master-flat, reduce,
calibrate, fit, import-map, catalog (all four table formats), correct (catalogs in every format
and a Stokes map) -- then opens each with astropy with every warning turned into an error:
`fits.open(...).verify('exception')`, `CCDData.read(file, hdu=k)` on every image HDU,
`Table.read(file, hdu=k)` on every table HDU, `astropy.wcs.WCS` on every image header (primary
and alternate WCSs), `Table.read` on the text tables; units must parse; every JSON summary carries
the run's provenance. fitsverify, when installed, must report 0 errors and 0 warnings
(tests/python/fitsverify.sh runs it the same way by hand).
"""

import json
import os
import shutil
import subprocess
import warnings
from pathlib import Path

import numpy as np
import pytest
from astropy import units as u
from astropy.io import fits
from astropy.nddata import CCDData
from astropy.table import Table
from astropy.wcs import WCS

ROOT = Path(__file__).resolve().parents[2]
BIN = Path(os.environ.get("INSTPOL_BIN", ROOT / "target" / "release" / "instpol"))
DATA = ROOT.parent / "shared" / "data" / "fors2-instpol"
if not DATA.is_dir():
    DATA = Path("/work/shared/data/fors2-instpol")


# A FORS1-like celestial WCS: 0.2"/px, rotated by 30 deg, reference pixel off centre.
_C, _S = np.cos(np.radians(30.0)), np.sin(np.radians(30.0))
_D = 0.2 / 3600.0
CELESTIAL = {"CTYPE1": "RA---TAN", "CTYPE2": "DEC--TAN", "CRPIX1": 1000.5, "CRPIX2": 1040.25,
             "CRVAL1": 150.1, "CRVAL2": -30.2, "CD1_1": -_D * _C, "CD1_2": _D * _S, "CD2_1": _D * _S,
             "CD2_2": _D * _C, "RADESYS": "ICRS"}


def run(*args, json_out=False):
    cmd = [str(BIN), *map(str, args)] + (["--json"] if json_out else [])
    p = subprocess.run(cmd, capture_output=True, text=True, timeout=600)
    assert p.returncode == 0, f"{' '.join(cmd)}\nexit {p.returncode}\n{p.stderr}"
    if json_out:
        out = json.loads(p.stdout)
        assert "provenance" in out, f"{args[0]} --json has no provenance"
        prov = out["provenance"]
        assert prov["program"] == "instpol" and prov["version"] and prov["date_utc"]
        assert prov["command_line"].split()[1] == args[0]
        return out
    return p.stdout


@pytest.fixture(scope="session")
def outputs(tmp_path_factory):
    """Every output file of every command, made once."""
    if not BIN.is_file():
        pytest.fail(f"instpol binary not found at {BIN}: build it (cargo build --release) or set INSTPOL_BIN")
    d = tmp_path_factory.mktemp("outputs")
    # demo (no frames: the fast path; its calibration files and tables).
    run("demo", "--no-frames", "--out", d / "demo", json_out=True)
    cal_v = next(p for p in (d / "demo").glob("*.fits") if "V" in p.name)
    # simulate: the maskless example polarimeter with two stars; FORS1 with strips.
    inst = ROOT / "instruments"
    # The example calcite instrument with the HWP angle read from the headers the simulator writes.
    calcite = d / "calcite.toml"
    calcite.write_text((inst / "calcite.toml").read_text().replace('hwp_angle_keyword = ""',
                                                                   'hwp_angle_keyword = "HWPANG"'))
    scene = d / "stars.toml"
    scene.write_text((inst / "scenes" / "calcite_stars.toml").read_text().replace(
        'instrument = "calcite"', f'instrument = "{calcite}"'))
    run("simulate", scene, "--out", d / "stars", json_out=True)
    stars = sorted((d / "stars").glob("*.fits"))
    run("simulate", inst / "scenes" / "empty_V.toml", "--out", d / "empty", json_out=True)
    empty = sorted((d / "empty").glob("*.fits"))
    # masters: any frames combine (the format is what is checked here).
    run("master-bias", *stars[:3], "--instrument", calcite, "--out", d / "bias.fits")
    run("master-flat", *stars[:3], "--instrument", calcite, "--out", d / "flat.fits")
    # The same frames with a celestial WCS (rotated TAN), as real frames have one.
    (d / "wcs").mkdir()
    for f in empty:
        with fits.open(f) as h:
            hdr = h[0].header
            hdr.update(CELESTIAL)
            h.writeto(d / "wcs" / f.name)
    run("reduce", *sorted((d / "wcs").glob("*.fits")), "--instrument", "fors1", "--bin", "64", "--out",
        d / "map_wcs.fits", json_out=True)
    # reduce, calibrate, fit on the FORS1 empty field.
    run("reduce", *empty, "--instrument", "fors1", "--bin", "64", "--out", d / "map.fits", json_out=True)
    run("calibrate", "--map", d / "map.fits", "--sky-p", "0", "--sky-chi", "0", "--out", d / "cal.fits",
        json_out=True)
    run("fit", d / "cal.fits", "--out", d / "refit.fits", json_out=True)
    # import-map: the real FORS2 maps.
    if DATA.is_dir():
        run("import-map", "--q", DATA / "I_BESS_inlaQ_bin10.fits", "--u", DATA / "I_BESS_inlaU_bin10.fits",
            "--pixel-scale", "0.25", "--bin", "10", "--filter", "I_BESS", "--instrument", "FORS2",
            "--out", d / "fors2_I.fits", json_out=True)
    else:
        print(f"WARNING: {DATA} missing: import-map of the real FORS2 maps not checked")
    # catalog in every table format.
    for ext in ["csv", "fits", "ecsv", "vot"]:
        run("catalog", *stars, "--instrument", calcite, "--fwhm", "4.7", "--aperture", "9", "--annulus", "14,24",
            "--out", d / f"cat.{ext}", json_out=True)
    # correct: each catalog format into each other one; a Stokes map. The catalogs are the
    # calcite's and the calibration FORS1's: the formats are tested here, so the mismatch the
    # catalogs' keywords show is allowed on purpose.
    for src, dst in [("ecsv", "vot"), ("vot", "fits"), ("fits", "fits"), ("csv", "ecsv"), ("fits", "csv")]:
        run("correct", "--cal", cal_v, "--in", d / f"cat.{src}", "--out", d / f"cor_{src}.{dst}", "--coords",
            "pixel", "--allow-extrapolation", "--allow-mismatch", json_out=True)
    run("correct", "--cal", d / "cal.fits", "--in", d / "map.fits", "--out", d / "map_cor.fits", json_out=True)
    return d


def fits_files(d):
    return sorted(p for p in d.rglob("*") if p.suffix.lower() in (".fits", ".fit", ".fts"))


def test_every_fits_output_opens_without_warnings(outputs):
    files = fits_files(outputs)
    assert len(files) >= 15, files
    bad = []
    for f in files:
        try:
            check_fits_file(f)
        except Exception as e:  # noqa: BLE001 -- every file's problem is reported, named
            bad.append(f"{f.relative_to(outputs)}: {type(e).__name__}: {e}")
    assert not bad, "\n".join(bad)


def check_fits_file(f):
    if True:
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            with fits.open(f) as h:
                h.verify("exception")
                assert h[0].header.get("PROGRAM") == "instpol", f"{f}: no provenance"
                assert any("blake3:" in str(c) for c in h[0].header.get("HISTORY", [])) or f.parent.name in (
                    "demo", "stars", "empty"), f"{f}: no input hashes in HISTORY"
                for k, hdu in enumerate(h):
                    if isinstance(hdu, (fits.BinTableHDU, fits.TableHDU)):
                        t = Table.read(f, hdu=k)
                        for c in t.columns.values():
                            if c.unit is not None:
                                u.Unit(c.unit)
                    elif hdu.data is not None and hdu.data.ndim >= 2:
                        c = CCDData.read(f, hdu=k)
                        assert c.unit is not None
                        if "BUNIT" in hdu.header:
                            assert hdu.header["BUNIT"] != "fraction"
                        for key in [" ", *[a for a in "ABCDEFGHIJKLMNOPQRSTUVWXYZ" if f"WCSNAME{a}" in hdu.header]]:
                            WCS(hdu.header, key=key)


def test_stokes_map_units_and_wcs(outputs):
    m = outputs / "map.fits"
    with fits.open(m) as h:
        g = h[0].header
        b, ox, oy = g["BINSIZE"], g["BINORGX"], g["BINORGY"]
        q = h["Q"].header
        assert q["BUNIT"] == "" and "dimensionless" in q.comments["BUNIT"]
        assert h["CHI"].header["BUNIT"] == "deg"
        assert u.Unit(h["INTENSITY"].header["BUNIT"]) == u.electron / u.pix
        w = WCS(q)
        # Bin (i, j) covers 0-based pixels [o + b i, o + b (i + 1)); its centre, 1-based, is
        # o + b (i + 1/2) + 1/2.
        for i, j in [(0, 0), (3, 5)]:
            x, y = w.wcs_pix2world([[i + 1, j + 1]], 1)[0]
            assert x == pytest.approx(ox + b * (i + 0.5) + 0.5) and y == pytest.approx(oy + b * (j + 0.5) + 0.5)
        wa = WCS(q, key="A")
        scale = g["PIXSCALE"] / 60.0
        cx, cy = (g["DETNX"] - 1) / 2.0, (g["DETNY"] - 1) / 2.0
        x, y = wa.wcs_pix2world([[1, 1]], 1)[0]
        assert x == pytest.approx((ox + b / 2 - 0.5 - cx) * scale) and y == pytest.approx((oy + b / 2 - 0.5 - cy) * scale)


def test_calibration_file_units(outputs):
    with fits.open(outputs / "cal.fits") as h:
        for name in ["QMAP", "UMAP", "QERR", "UERR"]:
            assert h[name].header["BUNIT"] == ""
            assert CCDData.read(outputs / "cal.fits", hdu=name).unit == u.dimensionless_unscaled
        t = Table.read(outputs / "cal.fits", hdu="BINS")
        assert t["X_ARCMIN"].unit == u.arcmin and t["PHI_DEG"].unit == u.deg and t["Q"].unit is None


def test_catalog_tables_in_every_format_agree(outputs):
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        ref = Table.read(outputs / "cat.fits")
        assert ref["x"].unit == u.pix and ref["chi_deg"].unit == u.deg and ref["flux_e"].unit == u.ct
        # What the catalog is, as keywords every reader sees (astropy reads the CSV's
        # `# KEY = value` lines as comments: comment="#").
        assert ref.meta["FILTER"] and ref.meta["INSTRUME"] and ref.meta["PLATE"] == "half_wave"
        for ext, fmt in [("csv", "ascii.csv"), ("ecsv", "ascii.ecsv"), ("vot", "votable")]:
            kw = {"comment": "#"} if ext == "csv" else {}
            t = Table.read(outputs / f"cat.{ext}", format=fmt, **kw)
            assert t.colnames == ref.colnames, ext
            if ext == "csv":
                assert f"FILTER = {ref.meta['FILTER']}" in t.meta["comments"], t.meta
            if ext == "ecsv":
                assert t.meta["FILTER"] == ref.meta["FILTER"] and t.meta["INSTRUME"] == ref.meta["INSTRUME"]
            for c in ["x", "q", "sigma_q", "chi_deg"]:
                a, b = np.asarray(t[c], float), np.asarray(ref[c], float)
                assert np.array_equal(a, b, equal_nan=True), (ext, c)
            if ext != "csv":
                assert t["x"].unit == u.pix and t["chi_deg"].unit == u.deg, ext


def test_corrected_catalogs_read_and_agree(outputs):
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        tabs = {}
        for src, dst, fmt in [("ecsv", "vot", "votable"), ("vot", "fits", "fits"), ("fits", "fits", "fits"),
                              ("csv", "ecsv", "ascii.ecsv"), ("fits", "csv", "ascii.csv")]:
            kw = {"comment": "#"} if dst == "csv" else {}
            t = Table.read(outputs / f"cor_{src}.{dst}", format=fmt, **kw)
            assert "q0" in t.colnames and "chi0_deg" in t.colnames, (src, dst)
            tabs[(src, dst)] = t
        ref = tabs[("fits", "fits")]
        for k, t in tabs.items():
            for c in ["q0", "u0", "sigma_q0", "p0"]:
                assert np.allclose(np.asarray(t[c], float), np.asarray(ref[c], float), rtol=0, atol=0,
                                   equal_nan=True), (k, c)


def test_fitsverify_clean(outputs):
    fv = shutil.which("fitsverify")
    if fv is None:
        print("WARNING: fitsverify is not installed (apt-get install fitsverify): FITS standard check skipped")
        pytest.skip("fitsverify not installed")
    for f in fits_files(outputs):
        p = subprocess.run([fv, "-q", str(f)], capture_output=True, text=True)
        assert "verification OK" in p.stdout + p.stderr, f"{f}: {p.stdout}{p.stderr}"


def test_celestial_wcs_carried_through_the_binning(outputs):
    """Each bin centre of the reduced map has, by the map's WCS, the sky position the frames'
    WCS gives its detector pixel (astropy evaluates both)."""
    frame = WCS(fits.Header(CELESTIAL))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with fits.open(outputs / "map_wcs.fits") as h:
            g = h[0].header
            b, ox, oy = g["BINSIZE"], g["BINORGX"], g["BINORGY"]
            for name in ["Q", "P", "VALID"]:
                w = WCS(h[name].header)
                assert w.has_celestial
                for i, j in [(0, 0), (7, 3), (g["NBINX"] - 1, g["NBINY"] - 1)]:
                    sky_map = w.pixel_to_world(i, j)  # 0-based map pixel = bin (i, j)
                    sky_det = frame.pixel_to_world(ox + b * (i + 0.5) - 0.5, oy + b * (j + 0.5) - 0.5)
                    assert sky_map.separation(sky_det).arcsec < 1e-6, (name, i, j)
                det = WCS(h[name].header, key="D")
                x, y = det.wcs_pix2world([[1, 1]], 1)[0]
                assert (x, y) == pytest.approx((ox + b / 2 + 0.5, oy + b / 2 + 0.5))
    # Correcting the map keeps its celestial WCS.
    d = outputs
    run("correct", "--cal", d / "cal.fits", "--in", d / "map_wcs.fits", "--out", d / "map_wcs_cor.fits")
    with fits.open(d / "map_wcs_cor.fits") as h:
        assert WCS(h["Q"].header).has_celestial
