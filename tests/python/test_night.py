"""instpol.scan and instpol.run against `instpol scan --json` and `instpol run`: the same
library calls, so the same plan (less the CLI's provenance) and the same products; a plan
edited in Python runs what is left of it; bad plans are InputError."""

import json
import os
from pathlib import Path

import numpy as np
import pytest

import instpol

ROOT = Path(__file__).resolve().parents[2]
INST = ROOT / "instruments" / "tiny_fors2.toml"


def simulate(run, tmp, name, angles, start_mjd, first_exp, dpr, target, sky=None, stars=()):
    t = f'instrument = "{INST}"\nfilter = "v_HIGH"\nhwp_angles_deg = {list(angles)}\nexposure_s = 10\nseed = {first_exp}\n'
    if sky:
        t += f"[sky]\nbrightness_e = {sky}\n"
    for x, y, f in stars:
        t += f'[[stars]]\nx = {x}\ny = {y}\ncoords = "pixel"\nflux_e = {f}\np = 0.02\nchi_deg = 30\nfwhm_arcsec = 2.5\n'
    t += f"[output]\narchive = {{ start_mjd = {start_mjd}, cadence_s = 60 }}\nfirst_exposure_no = {first_exp}\n"
    t += "[output.keywords]\n"
    for k, v in zip(["CATG", "TYPE", "TECH"], dpr):
        t += f'"HIERARCH ESO DPR {k}" = "{v}"\n'
    t += f'"HIERARCH ESO OBS TARG NAME" = "{target}"\nRA = 10.0\nDEC = -20.0\n'
    t += "[effects]\nphoton_noise = true\nread_noise = true\n"
    scene = tmp / f"{name}.toml"
    scene.write_text(t)
    run("simulate", scene, "--out", tmp / "raw" / name)


@pytest.fixture(scope="module")
def night(run, tmp_path_factory):
    tmp = tmp_path_factory.mktemp("night")
    simulate(run, tmp, "bias", [0, 22.5, 45, 67.5, 90], 58546.80, 1, ["CALIB", "BIAS", "IMAGE"], "BIAS")
    simulate(run, tmp, "flat", [0, 22.5, 45, 67.5], 58546.81, 11, ["CALIB", "FLAT,SKY", "IMAGE"], "FLAT", sky=20000)
    simulate(
        run, tmp, "target", [0, 22.5, 45, 67.5], 58546.90, 21, ["SCIENCE", "OBJECT", "POLARIMETRY"], "NGC 1",
        sky=400, stars=[(40, 33.5, 2e5), (110, 130.5, 3e5)],
    )
    return tmp


def test_scan_is_the_cli_plan(night, run):
    cli_plan = night / "cli.json"
    _, out, _ = run("scan", night / "raw", "--instrument", INST, "--out", cli_plan, "--products", night / "products",
                    "--fwhm", "3", "--aperture", "4", "--bin", "8", "--json")
    cli = json.loads(out)
    del cli["provenance"]
    py = instpol.scan(night / "raw", str(INST), night / "products", fwhm=3, aperture=4, bin=8, out=night / "py.json")
    assert py == cli
    assert json.loads((night / "py.json").read_text()) == json.loads(cli_plan.read_text())
    kinds = sorted(u["kind"] for u in py["units"])
    assert kinds == ["catalog", "master-bias", "master-flat", "reduce"]
    assert {f["role"] for f in py["files"]} == {"bias", "flat", "polarimetry"}


def test_run_makes_the_cli_products_and_skips_them_after(night, run, instpol_bin):
    products = night / "products"
    plan = instpol.scan(night / "raw", str(INST), products, fwhm=3, aperture=4, bin=8)
    # An edited plan: the catalog left out; it is not run.
    edited = dict(plan, units=[u for u in plan["units"] if u["kind"] != "catalog"])
    report = instpol.run(edited, jobs=2, instpol_bin=instpol_bin)
    assert sorted(o["status"] for o in report["outcomes"]) == ["done"] * 3
    assert not any(p.parent.name == "catalogs" for p in products.rglob("*"))
    # The same plan from the CLI's file, whole: the three are up to date, the catalog runs.
    plan_file = night / "plan.toml"
    run("scan", night / "raw", "--instrument", INST, "--out", plan_file, "--products", products,
        "--fwhm", "3", "--aperture", "4", "--bin", "8")
    report = instpol.run(plan_file, instpol_bin=instpol_bin)
    status = {o["id"]: o["status"] for o in report["outcomes"]}
    assert sorted(status.values()) == ["done", "up_to_date", "up_to_date", "up_to_date"], status
    assert [k for k, s in status.items() if s == "done"][0].startswith("catalog-")
    # The CLI finds everything done.
    _, out, _ = run("run", plan_file, "--json")
    assert {o["status"] for o in json.loads(out)["outcomes"]} == {"up_to_date"}
    dry = instpol.run(plan, dry_run=True, units=[plan["units"][0]["id"]], instpol_bin=instpol_bin)
    assert [o["status"] for o in dry["outcomes"]] == ["up_to_date"]


def test_bad_plans_are_input_errors(night, instpol_bin, tmp_path):
    plan = instpol.scan(night / "raw", str(INST), tmp_path / "p", fwhm=3, aperture=4, bin=8)
    cyc = json.loads(json.dumps(plan))
    cyc["units"][0]["after"] = [cyc["units"][-1]["id"]]
    with pytest.raises(instpol.InputError, match="cycle"):
        instpol.run(cyc, instpol_bin=instpol_bin)
    bad = json.loads(json.dumps(plan))
    bad["units"][0]["kind"] = "transmogrify"
    with pytest.raises(instpol.InputError, match="unknown kind 'transmogrify'"):
        instpol.run(bad, instpol_bin=instpol_bin)
    with pytest.raises(instpol.InputError, match="no such unit"):
        instpol.run(plan, units=["nothing"], instpol_bin=instpol_bin)
    with pytest.raises(instpol.InputError, match="sky"):
        instpol.scan(night / "raw", str(INST), tmp_path / "p", sky={"X": 3})
    # The library checks a sky field whichever face gives it: a negative P is refused.
    with pytest.raises(instpol.InputError, match=r"sky field X: P -1 %"):
        instpol.scan(night / "raw", str(INST), tmp_path / "p", sky={"X": (-1.0, 30.0)})
    with pytest.raises(instpol.InputError, match="no FITS file"):
        os.makedirs(tmp_path / "empty")
        instpol.scan(tmp_path / "empty", str(INST), tmp_path / "p")
    with pytest.raises(instpol.FileError):
        instpol.run(tmp_path / "none.toml", instpol_bin=instpol_bin)
    assert not (tmp_path / "p").exists()


def test_sky_fields_from_a_table_are_the_dict(night, tmp_path):
    table = tmp_path / "skies.csv"
    table.write_text("target,p_percent,chi_deg\nNGC 1,1.74,-53.8\n")
    args = (night / "raw", str(INST), tmp_path / "p")
    kw = dict(fwhm=3, aperture=4, bin=8)
    by_dict = instpol.scan(*args, sky={"NGC 1": (1.74, -53.8)}, **kw)
    by_table = instpol.scan(*args, sky=table, **kw)
    assert by_table["units"] == by_dict["units"]
    assert any(u["kind"] == "calibrate" for u in by_table["units"])


def _numbers(path):
    """Every number a product holds, by extension or column: a FITS file's HDUs' data, a
    table's columns (astropy reads both, a reader of its own)."""
    from astropy.io import fits
    from astropy.table import Table

    if path.suffix == ".fits":
        with fits.open(path) as h:
            return {i: None if hdu.data is None else hdu.data.copy() for i, hdu in enumerate(h)}
    t = Table.read(path, format="ascii.ecsv")
    return {c: np.array(t[c]) for c in t.colnames}


def test_run_makes_the_cli_products_in_process_without_the_binary(night, run, tmp_path, monkeypatch):
    """instpol.run with no instpol binary anywhere (INSTPOL_BIN unset, PATH stripped of every
    folder holding one): the units run in process through the library calls the CLI's
    commands make, and every product's numbers are those `instpol run` made from the same
    plan; a unit whose command the in-process runner does not know whole fails saying that it
    needs the binary."""
    import shutil

    monkeypatch.delenv("INSTPOL_BIN", raising=False)
    path = [d for d in os.environ.get("PATH", "").split(os.pathsep) if not (Path(d) / "instpol").exists()]
    monkeypatch.setenv("PATH", os.pathsep.join(path))
    assert shutil.which("instpol") is None
    py_plan = instpol.scan(night / "raw", str(INST), tmp_path / "py", fwhm=3, aperture=4, bin=8)
    report = instpol.run(py_plan, jobs=2)
    assert sorted(o["status"] for o in report["outcomes"]) == ["done"] * 4, report
    assert [o["status"] for o in instpol.run(py_plan)["outcomes"]] == ["up_to_date"] * 4
    # The CLI's run of the same plan, in its own products folder (the binary by its full path).
    cli_plan = tmp_path / "cli.toml"
    run("scan", night / "raw", "--instrument", INST, "--out", cli_plan, "--products", tmp_path / "cli",
        "--fwhm", "3", "--aperture", "4", "--bin", "8")
    run("run", cli_plan)
    outputs = [Path(o) for u in py_plan["units"] for o in u["outputs"]]
    assert len(outputs) == 4
    for py_out in outputs:
        cli_out = tmp_path / "cli" / py_out.relative_to(tmp_path / "py")
        a, b = _numbers(py_out), _numbers(cli_out)
        assert a.keys() == b.keys(), py_out.name
        for k in a:
            if a[k] is None or b[k] is None:
                assert a[k] is None and b[k] is None, (py_out.name, k)
            elif a[k].dtype.kind in "fc":
                assert np.array_equal(a[k], b[k], equal_nan=True), (py_out.name, k)
            else:
                assert np.array_equal(a[k], b[k]), (py_out.name, k)
    # An option the in-process runner does not read: the unit needs the binary, and says so.
    edited = json.loads(json.dumps(py_plan))
    edited["records"] = str(tmp_path / "edited-records")
    for u in edited["units"]:
        u["outputs"] = [o.replace(str(tmp_path / "py"), str(tmp_path / "edited")) for o in u["outputs"]]
        u["inputs"] = [i.replace(str(tmp_path / "py"), str(tmp_path / "edited")) for i in u["inputs"]]
        u["command"] = [c.replace(str(tmp_path / "py"), str(tmp_path / "edited")) for c in u["command"]]
        if u["kind"] == "reduce":
            u["command"].append("--allow-incomplete")
    status = {o["kind"]: (o["status"], o.get("reason", "")) for o in instpol.run(edited)["outcomes"]}
    assert status["reduce"][0] == "failed" and "runs only through the instpol binary" in status["reduce"][1], status
    assert status["master-bias"][0] == "done" and status["catalog"][0] == "done"
