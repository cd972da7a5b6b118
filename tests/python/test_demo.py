"""instpol.demo against `instpol demo --json`: the same library call, so the same report to the
last bit (paths aside: each run writes into its own folder; the CLI alone draws plots and adds
its provenance), and the calibration files it writes read back as the report says."""

import pytest

import instpol
from conftest import same


def normalized(v, out):
    """The report with the output folder named OUT, the CLI's plots and provenance left out."""
    if isinstance(v, dict):
        return {k: normalized(x, out) for k, x in v.items() if k not in ("plot_outputs", "provenance")}
    if isinstance(v, list):
        return [normalized(x, out) for x in v]
    if isinstance(v, str):
        return v.replace(str(out), "OUT")
    return v


def assert_same_report(py, cli):
    """Equal dicts, floats compared bit for bit (NaN equal to NaN)."""
    assert type(py) is type(cli), (py, cli)
    if isinstance(py, dict):
        assert sorted(py) == sorted(cli)
        for k in py:
            assert_same_report(py[k], cli[k])
    elif isinstance(py, list):
        assert len(py) == len(cli)
        for a, b in zip(py, cli):
            assert_same_report(a, b)
    elif isinstance(py, float):
        assert same(py, cli), (py, cli)
    else:
        assert py == cli


@pytest.mark.parametrize("frames", [False, True])
def test_demo_matches_cli(run_json, tmp_path, frames):
    a, b = tmp_path / "py", tmp_path / "cli"
    py = instpol.demo(a, frames=frames, seed=7)
    args = ["demo", "--out", b, "--seed", "7"] + ([] if frames else ["--no-frames"])
    cli = run_json(*args)
    assert py["through_frames"] is frames and len(py["filters"]) == 3
    assert all(f["plot_outputs"] == [] for f in py["filters"])
    assert all(len(f["plot_outputs"]) > 0 for f in cli["filters"])
    assert_same_report(normalized(py, a), normalized(cli, b))
    # The calibration files are written where the report says, and load.
    for f in py["filters"]:
        cal = instpol.Calibration.load(f["output"])
        assert cal.filter == f["filter"]
    assert not (a / "frames_V").exists() and not (a / "standard_V").exists()


def test_demo_bad_folder_is_a_file_error(tmp_path):
    f = tmp_path / "file"
    f.write_text("not a folder")
    with pytest.raises(instpol.FileError, match="cannot create"):
        instpol.demo(f / "out", frames=False)
