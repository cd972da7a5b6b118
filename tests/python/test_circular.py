"""instpol.catalog through a quarter-wave plate against `instpol catalog --json` on the same
simulated frames (instruments/calcite_qwp.toml, a star of V/I = 1 %), and against the V/I the
frames were simulated with; instpol.reduce through a quarter-wave plate on a strip instrument
against `instpol reduce` (its V map read with astropy) and the sky's V/I."""

from pathlib import Path

import numpy as np
import pytest

import instpol
from conftest import key, same, shrunk

ROOT = Path(__file__).resolve().parents[2]


def test_catalog_carries_v_as_the_cli(run, run_json, tmp_path):
    inst = ROOT / "instruments" / "calcite_qwp.toml"
    scene = tmp_path / "qwp.toml"
    scene.write_text(
        f'instrument = "{inst}"\nfilter = "V"\nhwp_angles_deg = [-45, 45, 135, 225]\nseed = 4\n'
        '[output]\nbitpix = -32\n[[stars]]\nx = 200\ny = 300\ncoords = "pixel"\nflux_e = 2e6\n'
        'v = 0.01\nfwhm_arcsec = 0.9\n[effects]\nphoton_noise = true\n'
    )
    run("simulate", scene, "--out", tmp_path / "f")
    frames = sorted(str(p) for p in (tmp_path / "f").glob("*.fits"))
    args = ("--hwp-angles", "-45,45,135,225", "--fwhm", "4.2", "--aperture", "9", "--annulus", "14,24")
    j = run_json("catalog", *frames, "--instrument", inst, *args)
    c = instpol.catalog(frames, instrument=str(inst), hwp_angles=[-45, 45, 135, 225], fwhm=4.2, aperture=9,
                        annulus=(14, 24), as_table=False)
    assert c["qwp_zero_angle_deg"] == key(j, "qwp_zero_angle_deg") == 0.0
    rows = key(j, "rows")
    assert len(rows) == 1 and c["v"][0] == rows[0]["v"] and c["sigma_v"][0] == rows[0]["sigma_v"]
    assert np.isnan(c["q"][0]) and rows[0]["q"] is None
    # V/I = 1 % within 4 sigma; sigma_v = 1/(2 SNR) for 4 positions of 2e6 e- (1/sqrt(2e6)/2).
    assert abs(c["v"][0] - 0.01) < 4 * c["sigma_v"][0]
    assert abs(c["sigma_v"][0] / (0.5 / np.sqrt(2e6)) - 1) < 0.1
    t = instpol.catalog(frames, instrument=str(inst), hwp_angles=[-45, 45, 135, 225], fwhm=4.2, aperture=9,
                        annulus=(14, 24))
    if hasattr(t, "meta"):
        assert t.meta["qwp_zero_angle_deg"] == 0.0 and t["v"][0] == c["v"][0]


def test_reduce_gives_the_cli_v_map(run, cal_v, tmp_path):
    """A tiny FORS1 with a quarter-wave plate, a sky of V/I = 2 % (with 3 % linear
    polarization) at -45 and 45 deg with photon noise: instpol.reduce gives a CircularMap equal
    to the CLI's V map file bit for bit (astropy), its bins within errors of 2 % (numpy pulls);
    Calibration.correct_map refuses the V map, saying what it is."""
    from astropy.io import fits

    inst = shrunk("fors1", [
        ("nx = 2048", "nx = 128"), ("ny = 2048", "ny = 128"), ("throw_arcsec = 22.0", "throw_arcsec = 8.0"),
        ("strip_count = 9", "strip_count = 1"), ("first_strip_y_px = 34", "first_strip_y_px = 20"),
        ("[polarimetry]\n", '[polarimetry]\nplate = "quarter_wave"\n'),
    ], tmp_path / "tiny_qwp.toml")
    scene = tmp_path / "sky.toml"
    scene.write_text(
        f'instrument = "{inst}"\nfilter = "V"\nhwp_angles_deg = [-45, 45]\nseed = 8\n[output]\nbitpix = -32\n'
        '[sky]\nbrightness_e = 4000\np = 0.03\nchi_deg = 20\nv = 0.02\n[effects]\nphoton_noise = true\n'
    )
    run("simulate", scene, "--out", tmp_path / "f")
    frames = sorted(str(p) for p in (tmp_path / "f").glob("*.fits"))
    cli = tmp_path / "cli.fits"
    run("reduce", *frames, "--instrument", inst, "--bin", "8", "--out", cli)
    m = instpol.reduce(frames, instrument=str(inst), bin=8, output=tmp_path / "py.fits")
    assert isinstance(m, instpol.CircularMap)
    assert m.header["stokes"] == "V" and m.header["plate_angles_deg"] == [-45.0, 45.0]
    with fits.open(cli) as h:
        assert h[0].header["STOKES"] == "V" and "Q" not in h
        for ext, attr in [("V", "v"), ("SIGMA_V", "sigma_v"), ("SIGV_PHOT", "sigma_v_phot"), ("INTENSITY", "intensity")]:
            assert same(np.asarray(h[ext].data, dtype=float), getattr(m, attr)), ext
    ok = m.valid
    pulls = (m.v[ok] - 0.02) / m.sigma_v[ok]
    assert ok.sum() == 16 * 5 and np.all(np.abs(pulls) < 4.5)
    assert 0.75 < np.sqrt(np.mean(pulls ** 2)) < 1.25
    with pytest.raises(instpol.InputError, match="STOKES = 'V'"):
        instpol.Calibration.load(cal_v).correct_map(cli, tmp_path / "corr.fits")
