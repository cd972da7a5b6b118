"""The package as an astropy user writes it: frames given as HDUList, CCDData or (array,
header) give the numbers the same frames give as files, bit for bit; a catalog is an astropy
Table whose columns carry their units and equal the dict's (as_table=False), and code written
for the dict reads it unchanged; errors name the frame's place in the list, not a temporary
file."""

import numpy as np
import pytest

import instpol

fits = pytest.importorskip("astropy.io.fits")
u = pytest.importorskip("astropy.units")
nddata = pytest.importorskip("astropy.nddata")

from conftest import same  # noqa: E402


def objects(paths, kind):
    out = []
    for p in paths:
        with fits.open(p) as h:
            data, header = h[0].data.astype(float), h[0].header.copy()
        if kind == "hdulist":
            out.append(fits.HDUList([fits.PrimaryHDU(data=data, header=header)]))
        elif kind == "ccddata":
            out.append(nddata.CCDData(data, unit="adu", header=header))
        else:
            out.append((data, header))
    return out


@pytest.mark.parametrize("kind", ["hdulist", "ccddata", "pair"])
def test_frames_in_memory_are_the_files(star_frames, sky_frames, kind):
    frames, inst = star_frames
    by_file = instpol.catalog(frames, str(inst))
    by_object = instpol.catalog(objects(frames, kind), str(inst))
    for k in ("x", "y", "q", "u", "sigma_q", "sigma_u", "p", "chi_deg"):
        assert same(by_file[k], by_object[k]), k
    sky, sky_inst = sky_frames
    m1 = instpol.reduce(sky, str(sky_inst), bin=16)
    m2 = instpol.reduce(objects(sky, kind), str(sky_inst), bin=16)
    assert same(m1.q, m2.q) and same(m1.u, m2.u)


def test_a_catalog_is_a_table_with_units_and_the_dicts_numbers(star_frames):
    from astropy.table import QTable, Table

    frames, inst = star_frames
    d = instpol.catalog(frames, str(inst), as_table=False)
    t = instpol.catalog(frames, str(inst))
    assert isinstance(d, dict) and isinstance(t, Table) and isinstance(t, instpol.CatalogTable)
    assert len(t) == len(d["id"])
    assert t["x"].unit == u.pix and t["chi_deg"].unit == u.deg and t["x_arcmin"].unit == u.arcmin
    assert t["flux_e"].unit == u.electron and t["q"].unit is None
    # The values are the dict's, bit for bit; every column of the dict is a column or meta.
    for k, v in d.items():
        if k in t.colnames:
            if np.asarray(v).dtype.kind == "f":
                assert same(t[k], v), k
        else:
            assert t.meta[k] == v and t[k] == v, k
    # As quantities, and code written for the dict: arithmetic on plain arrays, meta by key.
    q = QTable(t)
    assert same(q["chi_deg"].to_value(u.deg), d["chi_deg"]) and q["x"].unit == u.pix
    i = int(np.argmin(np.hypot(t["x"] - 150, t["y"] - 200)))
    assert i == int(np.argmin(np.hypot(d["x"] - 150, d["y"] - 200)))
    assert t["filter"] == d["filter"] and list(t["hwp_deg"]) == list(d["hwp_deg"])
    ok = t["flags"] == 0
    assert same(t["q"][ok], d["q"][d["flags"] == 0])


def test_a_bad_frame_object_is_named_by_its_place(star_frames):
    frames, inst = star_frames
    objs = objects(frames, "hdulist")
    with pytest.raises(instpol.InputError, match=r"frames\[1\]: a dict"):
        instpol.catalog([objs[0], {"not": "a frame"}] + objs[2:], str(inst))
    # A frame whose header lacks the HWP angle: the error names frames[2], no temporary path.
    bare = objs[:2] + [fits.HDUList([fits.PrimaryHDU(data=objs[2][0].data)])] + objs[3:]
    with pytest.raises(instpol.InputError) as e:
        instpol.catalog(bare, str(inst))
    assert "frames[2] (HDUList)" in str(e.value) and "instpol-frames-" not in str(e.value), str(e.value)
