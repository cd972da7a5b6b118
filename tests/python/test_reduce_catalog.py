"""instpol.reduce and instpol.catalog against `instpol reduce` / `instpol catalog` on the same
simulated frames (the map's FITS extensions read with astropy, the catalog's JSON rows), and
against the polarization the frames were simulated with."""

import os
import numpy as np
import pytest

import instpol
from conftest import key, num, same

MAP_EXT = {"Q": "q", "U": "u", "SIGMA_Q": "sigma_q", "SIGMA_U": "sigma_u", "COV_QU": "cov_qu",
           "SIGQ_PHOT": "sigma_q_phot", "SIGU_PHOT": "sigma_u_phot", "P": "p", "CHI": "chi_deg",
           "INTENSITY": "intensity", "INT_SNR": "intensity_snr", "COVERAGE": "n_pixels", "VALID": "valid"}


def test_reduce_is_the_cli_map(run_json, sky_frames, tmp_path):
    from astropy.io import fits

    frames, inst = sky_frames
    out = tmp_path / "map.fits"
    j = run_json("reduce", *frames, "--instrument", inst, "--bin", "10", "--out", out)
    m = instpol.reduce(frames, instrument=inst, bin=10, output=tmp_path / "py.fits")
    assert m.header["bin_px"] == 10 and m.header["hwp_angles_deg"] == [0.0, 22.5, 45.0, 67.5]
    assert m.header["filter"] == key(j, "filter") and m.warnings == key(j, "warnings")
    with fits.open(out) as h, fits.open(tmp_path / "py.fits") as hp:
        for ext, name in MAP_EXT.items():
            a = getattr(m, name)
            assert same(a, h[ext].data), ext
            assert same(hp[ext].data, h[ext].data), ext
    v = m.valid
    assert v.sum() == key(j, "n_valid_bins") and v.size == key(j, "n_bins")
    assert np.median(m.p[v]) == pytest.approx(key(j, "median_p"), rel=1e-15)
    assert np.median(m.sigma_q[v]) == pytest.approx(key(j, "median_sigma_q"), rel=1e-15)
    # the simulated sky: p = 0.0645 at 68.4 deg, no noise in Q/U of a uniform sky beyond rounding
    q0 = 0.0645 * np.cos(2 * np.radians(68.4))
    assert np.max(np.abs(m.q[v] - q0)) < 1e-10
    assert np.max(np.abs(m.chi_deg[v] - 68.4)) < 1e-7
    # bin centres step by bin * scale (the last, partial bin excepted)
    assert np.allclose(np.diff(m.x_arcmin[:, :-1], axis=1), 10 * m.header["pixel_scale_arcsec"] / 60)
    # FORS1's V filter states no zero angle: the map records 0, which its q, u lack.
    assert m.header["hwp_zero_angle_deg"] == 0.0
    with fits.open(out) as h:
        assert h[0].header["HWPZERO"] == 0.0


def test_reduce_records_the_filters_zero_angle(sky_frames, tmp_path):
    """An instrument file whose filter has an HWP zero angle: the map records it (HWPZERO, as
    astropy reads it, and the header dict), while its q, u stay at the plate (the same as
    without it: the zero angle is not applied by the reduction)."""
    from astropy.io import fits

    frames, inst = sky_frames
    v = 'lambda_eff_nm = 554.0\n'
    text = inst.read_text()
    assert v in text
    z_inst = tmp_path / "zero.toml"
    z_inst.write_text(text.replace(v, v + "hwp_chi_offset_deg = 1.8\n", 1))
    m = instpol.reduce(frames, instrument=z_inst, bin=10, output=tmp_path / "z.fits")
    plain = instpol.reduce(frames, instrument=inst, bin=10)
    assert m.header["hwp_zero_angle_deg"] == 1.8
    with fits.open(tmp_path / "z.fits") as h:
        assert h[0].header["HWPZERO"] == 1.8
    assert same(m.q, plain.q) and same(m.u, plain.u)


def test_reduce_errors(sky_frames, tmp_path):
    frames, inst = sky_frames
    with pytest.raises(instpol.InputError, match="bin 0: a bin side in pixels must be between 1"):
        instpol.reduce(frames, instrument=inst, bin=0)
    with pytest.raises(instpol.InputError, match="incomplete HWP angle set"):
        instpol.reduce(frames[:3], instrument=inst, bin=10)
    with pytest.raises(instpol.InputError, match="unknown instrument 'nosuch'"):
        instpol.reduce(frames, instrument="nosuch")
    with pytest.raises(OSError):
        instpol.reduce([tmp_path / "missing.fits"] + frames[1:], instrument=inst, bin=10)


def test_catalog_is_the_cli_catalog(run_json, star_frames):
    frames, inst = star_frames
    args = dict(fwhm=4.7, aperture=9.0, annulus=(14.0, 24.0))
    j = run_json("catalog", *frames, "--instrument", inst, "--fwhm", "4.7", "--aperture", "9", "--annulus", "14,24")
    c = instpol.catalog(frames, instrument=inst, **args)
    rows = j["rows"]
    assert len(rows) == len(c["x"]) == 3
    for k in ["x", "y", "x_e", "y_e", "x_arcmin", "y_arcmin", "fwhm_px", "flux_e", "q", "u", "sigma_q", "sigma_u",
              "cov_qu", "p", "sigma_p", "chi_deg", "sigma_chi_deg", "a0", "kappa", "chi2_mod",
              "sigma_q_scatter", "sigma_u_scatter"]:
        assert same(c[k], [num(r[k]) for r in rows]), k
    assert same(c["f"], [num(r["f"]) for r in rows])
    assert list(c["id"]) == [r["id"] for r in rows] and list(c["flags"]) == [r["flags"] for r in rows]
    assert c["hwp_deg"] == j["hwp_deg"] and c["n_sources"] == j["n_sources"]
    shift = j["unpaired_shift_px"]
    assert c["unpaired_shift_px"] == (None if shift is None else tuple(shift))
    # the 5.7 % standard at (150, 200) px, chi = 136 deg, comes back within 4 sigma
    i = int(np.argmin(np.hypot(c["x"] - 150, c["y"] - 200)))
    assert abs(c["p"][i] - 0.0572) < 4 * c["sigma_p"][i]
    assert abs((c["chi_deg"][i] - 136.0 + 90) % 180 - 90) < 4 * c["sigma_chi_deg"][i]


def test_catalog_errors(star_frames):
    frames, inst = star_frames
    with pytest.raises(instpol.InputError, match="aperture 0 px: expected a radius between 0 and 1000 px"):
        instpol.catalog(frames, instrument=inst, aperture=0.0)
    with pytest.raises(instpol.InputError, match="annulus"):
        instpol.catalog(frames, instrument=inst, annulus=(12.0,))
    with pytest.raises(instpol.InputError, match="pair-tol 0 px: expected a distance between 0 and 20 px"):
        instpol.catalog(frames, instrument=inst, pair_tol=0.0)


def test_reduce_refuses_to_write_over_an_input(sky_frames, tmp_path):
    import shutil

    frames, inst = sky_frames
    copies = [shutil.copy(f, tmp_path / f.name) for f in frames]
    before = [open(f, "rb").read() for f in copies]
    with pytest.raises(instpol.InputError, match="refusing to write over an input"):
        instpol.reduce(copies, instrument=inst, bin=10, output=copies[2])
    # A hard link to a frame is the same file under another name: refused as the CLI refuses
    # it (the package compared resolved paths and took it; both faces now ask the library).
    link = tmp_path / "link.fits"
    os.link(copies[1], link)
    with pytest.raises(instpol.InputError, match="refusing to write over an input"):
        instpol.reduce(copies, instrument=inst, bin=10, output=link)
    assert [open(f, "rb").read() for f in copies] == before


def test_a_frame_under_two_names_is_refused_naming_both(sky_frames, star_frames, tmp_path):
    """A frame given again under another name (the same path, a copy, a symlink) would be summed
    with itself: reduce and catalog refuse it, naming both names."""
    for fixture, call in ((sky_frames, lambda f, i: instpol.reduce(f, instrument=i, bin=10)),
                          (star_frames, lambda f, i: instpol.catalog(f, instrument=i))):
        frames, inst = fixture
        first = str(frames[0])
        copy, sym = tmp_path / "copy.fits", tmp_path / "sym.fits"
        copy.write_bytes(open(first, "rb").read())
        if not sym.exists():
            os.symlink(first, sym)
        for again in (first, str(copy), str(sym)):
            with pytest.raises(instpol.InputError, match="given once") as e:
                call(list(frames) + [again], inst)
            assert first in str(e.value) and again in str(e.value)
        copy.unlink()
        sym.unlink()


def test_a_map_says_what_it_is(run_json, sky_frames, tmp_path):
    """reduce()'s map carries its product as the CLI's reduce --json and the map's header do:
    the plate, the instrument file's BLAKE3 (checked with Python's blake3) and the inputs'."""
    blake3 = pytest.importorskip("blake3")
    frames, inst = sky_frames
    out = tmp_path / "m.fits"
    m = instpol.reduce([str(f) for f in frames], instrument=str(inst), bin=10, output=out)
    assert m.product is not None
    assert m.product["plate"] == "half_wave"
    assert m.product["instrument_hash"] == "blake3:" + blake3.blake3(inst.read_bytes()).hexdigest()
    j = run_json("reduce", *frames, "--instrument", inst, "--bin", "10", "--out", tmp_path / "cli.fits")
    assert j["product"]["instrument_hash"] == m.product["instrument_hash"]
    assert j["product"]["plate"] == m.product["plate"]
    want = ["blake3:" + blake3.blake3(f.read_bytes()).hexdigest() for f in list(frames) + [inst]]
    assert j["product"]["inputs"] == want
