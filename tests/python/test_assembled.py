"""instpol.reduce(assembled=True) on another pipeline's trimmed, assembled frames of a chip
instrument: FORS2 shrunk to two 64 x 32 px chips, simulated as raw chip files by `instpol
simulate`, then assembled here with astropy (each chip's prescan and overscan rows averaged
and subtracted, the image rows placed in the detector frame, the chip gap NaN). The map must be
the raw files' map (`instpol reduce` on the chip files) within a twentieth of each bin's errors,
and the scene's sky; without assembled=True the frames are refused with a hint."""

import numpy as np
import pytest

import instpol
from conftest import shrunk

P, CHI = 0.02, 30.0


def tiny_fors2(dir_):
    """instruments/fors2.toml shrunk to a 64 x 68 px mosaic (as crates/cli/tests/common/raw.rs)."""
    return shrunk("fors2", [
        ("nx = 2048", "nx = 64"),
        ("ny = 2064", "ny = 68"),
        ("origin_px = [0, 1040]", "origin_px = [0, 36]"),
        ("size_px = [2048, 1024]", "size_px = [64, 32]"),
        ("throw_arcsec = 22.0", "throw_arcsec = 2.0"),
        ("strip_starts_px = [432.0, 613.5, 796.0, 975.5, 1156.5, 1338.0, 1520.5, 1701.5, 1884.0]",
         "strip_count = 3\nfirst_strip_y_px = 2"),
        ("strip_margin_px = 8.6 ", "strip_margin_px = 0 "),
        ("extraordinary_offset_sign = -1", "extraordinary_offset_sign = 1"),
        ("\nthrow_terms = [", "\n# throw_terms = ["),
    ], dir_ / "fors2_tiny.toml")


@pytest.fixture(scope="module")
def raw_and_assembled(run, tmp_path_factory):
    from astropy.io import fits

    d = tmp_path_factory.mktemp("assembled")
    inst = tiny_fors2(d)
    scene = d / "scene.toml"
    scene.write_text(
        f'instrument = "{inst}"\nfilter = "v_HIGH"\nseed = 5\n[sky]\nbrightness_e = 40000\np = {P}\n'
        f"chi_deg = {CHI}\n[effects]\nphoton_noise = true\nread_noise = true\n"
    )
    run("simulate", scene, "--out", d / "raw")
    raw = sorted((d / "raw").glob("*_CHIP*.fits"))
    assert len(raw) == 8
    out = []
    for k in range(4):
        chip1, chip2 = raw[2 * k], raw[2 * k + 1]
        assert chip1.name.endswith("_CHIP1.fits") and chip2.name.endswith("_CHIP2.fits")
        det = np.full((68, 64), np.nan, dtype=np.float32)
        for f, y0 in [(chip1, 36), (chip2, 0)]:
            with fits.open(f) as h:
                img = h[0].data.astype(np.float64)
                hdr = h[0].header
            assert img.shape == (42, 64)
            level = np.concatenate([img[:5].ravel(), img[37:].ravel()]).mean()
            det[y0:y0 + 32] = img[5:37] - level
        keep = {k_: hdr[k_] for k_ in ["HIERARCH ESO INS RETA2 POSANG", "HIERARCH ESO INS FILT1 NAME", "EXPTIME"]}
        h = fits.PrimaryHDU(det)
        for k_, v in keep.items():
            h.header[k_] = v
        p = d / f"assembled_{k}.fits"
        h.writeto(p)
        out.append(p)
    return inst, raw, out, d


def test_assembled_frames_reduce_to_the_raw_files_map(run, raw_and_assembled):
    from astropy.io import fits

    inst, raw, assembled, d = raw_and_assembled
    run("reduce", *raw, "--instrument", inst, "--bin", "8", "--out", d / "raw_map.fits")
    m = instpol.reduce(assembled, instrument=str(inst), bin=8, assembled=True)
    with fits.open(d / "raw_map.fits") as h:
        valid = h["VALID"].data.astype(bool).ravel()
        q, u = h["Q"].data.ravel(), h["U"].data.ravel()
        sq, su = h["SIGMA_Q"].data.ravel(), h["SIGMA_U"].data.ravel()
    assert np.array_equal(m.valid.ravel(), valid) and valid.sum() >= 10
    assert np.all(np.abs(m.q.ravel()[valid] - q[valid]) < 0.05 * sq[valid])
    assert np.all(np.abs(m.u.ravel()[valid] - u[valid]) < 0.05 * su[valid])
    # the scene's sky: q, u = P (cos 2 chi, sin 2 chi) within 5 sigma in every bin
    q0, u0 = P * np.cos(np.radians(2 * CHI)), P * np.sin(np.radians(2 * CHI))
    v = m.valid
    assert np.all(np.abs(m.q[v] - q0) < 5 * m.sigma_q[v]) and np.all(np.abs(m.u[v] - u0) < 5 * m.sigma_u[v])


def test_assembled_frames_without_the_flag_are_refused(raw_and_assembled):
    inst, _, assembled, _ = raw_and_assembled
    with pytest.raises(instpol.InputError, match=r"assembled detector \(64 x 68 px\).*assembled=True"):
        instpol.reduce(assembled, instrument=str(inst), bin=8)
