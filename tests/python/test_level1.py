"""What the CLI does with level-1 frames and a frame's WCS, the Python package does too:
catalog() gives each star's RA, Dec from the frames' celestial WCS (checked against astropy's
own TAN projection), and reduce()/catalog() refuse a master for frames the instrument declares
already corrected unless ``correct_again=True``."""

import numpy as np
import pytest

import instpol

fits = pytest.importorskip("astropy.io.fits")
wcs = pytest.importorskip("astropy.wcs")


def with_wcs(frames, dest):
    """Copies of `frames` with a gnomonic WCS about (RA, Dec) = (250.4, 36.46) deg, 0.3"/px,
    north up and east left."""
    out = []
    for f in frames:
        with fits.open(f) as h:
            hdr = h[0].header
            hdr["CTYPE1"], hdr["CTYPE2"] = "RA---TAN", "DEC--TAN"
            hdr["CRVAL1"], hdr["CRVAL2"] = 250.4, 36.46
            hdr["CRPIX1"], hdr["CRPIX2"] = 150.0, 120.0
            hdr["CD1_1"], hdr["CD1_2"], hdr["CD2_1"], hdr["CD2_2"] = -0.3 / 3600, 0.0, 0.0, 0.3 / 3600
            p = dest / f.name
            h.writeto(p)
            out.append(p)
    return out


def test_catalog_gives_ra_dec_from_the_frames_wcs(star_frames, tmp_path):
    frames, inst = star_frames
    framed = with_wcs(frames, tmp_path)
    cat = instpol.catalog([str(f) for f in framed], instrument=str(inst), as_table=False)
    assert "ra_deg" in cat and "dec_deg" in cat
    w = wcs.WCS(fits.getheader(framed[0]))
    ra, dec = w.all_pix2world(np.asarray(cat["x"]), np.asarray(cat["y"]), 0)
    np.testing.assert_allclose(cat["ra_deg"], ra, atol=1e-9)
    np.testing.assert_allclose(cat["dec_deg"], dec, atol=1e-9)
    # Frames without a WCS: no such columns.
    plain = instpol.catalog([str(f) for f in frames], instrument=str(inst), as_table=False)
    assert "ra_deg" not in plain


def test_a_master_for_frames_already_corrected_needs_correct_again(sky_frames, tmp_path):
    frames, inst = sky_frames
    level1 = tmp_path / "level1.toml"
    level1.write_text(inst.read_text() + '\n[format]\nalready_corrected = ["bias"]\n')
    # A file that is not one of the frames (the same bytes would be refused as given twice).
    with fits.open(frames[0]) as h:
        h[0].data = np.zeros_like(h[0].data)
        h.writeto(tmp_path / "bias.fits")
    bias = str(tmp_path / "bias.fits")
    for call in (lambda **k: instpol.reduce([str(f) for f in frames], str(level1), bin=10, bias=bias, **k),
                 lambda **k: instpol.catalog([str(f) for f in frames], str(level1), bias=bias, **k)):
        with pytest.raises(instpol.InputError, match="already") as e:
            call()
        assert "bias" in str(e.value)
        # Asked for: the masters are taken (whatever they then say), not refused as a second pass.
        try:
            call(correct_again=True)
        except (instpol.InputError, instpol.FileError) as again:
            assert "already" not in str(again), str(again)
