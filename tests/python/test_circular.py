"""instpol.catalog through a quarter-wave plate against `instpol catalog --json` on the same
simulated frames (instruments/calcite_qwp.toml, a star of V/I = 1 %), and against the V/I the
frames were simulated with."""

from pathlib import Path

import numpy as np

import instpol
from conftest import key

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
