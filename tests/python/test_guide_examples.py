"""Every Python example of the README and the guide (docs/**/*.md) runs against the installed
package. A file's blocks run in order in one fresh folder holding links to the repository's
instruments/ and tests/: its ```toml file=NAME blocks are written to NAME, its ```console
commands are run (their output is checked by crates/cli/tests/it/doc_examples.rs; here they only
make the inputs the Python blocks read), and its ```python blocks are executed in one namespace,
as a reader pasting them into one session would."""

import os
import re
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
FENCE = re.compile(r"^( *)```(.*)$")


def blocks(text):
    """(info, text) of every fenced block, the fence's indentation removed."""
    out, info, indent, lines = [], None, 0, []
    for line in text.splitlines():
        m = FENCE.match(line)
        if info is None:
            if m and m.group(2).strip():
                info, indent, lines = m.group(2).strip(), len(m.group(1)), []
            elif m:
                info, indent, lines = "", len(m.group(1)), []
        elif m and not m.group(2).strip():
            out.append((info, "\n".join(lines) + "\n"))
            info = None
        else:
            lines.append(line[min(indent, len(line) - len(line.lstrip(" "))):])
    return out


def documentation_files():
    files = [ROOT / "README.md"] + sorted((ROOT / "docs").rglob("*.md"))
    return [f for f in files if any(i == "python" for i, _ in blocks(f.read_text()))]


def test_the_block_reader_reads_indented_blocks_and_their_info():
    b = blocks("x\n   ```console\n   $ instpol a\n   ```\n```python\nprint(1)\n```\n")
    assert b == [("console", "$ instpol a\n"), ("python", "print(1)\n")]


def test_some_documentation_has_python_examples():
    names = [f.name for f in documentation_files()]
    assert "README.md" in names and "correcting.md" in names, names


@pytest.mark.parametrize("md", documentation_files(), ids=lambda p: str(p.relative_to(ROOT)))
def test_python_examples_run(md, instpol_bin, tmp_path, monkeypatch):
    for sub in ("instruments", "tests"):
        (tmp_path / sub).symlink_to(ROOT / sub)
    monkeypatch.chdir(tmp_path)
    env = dict(os.environ, PATH=f"{Path(instpol_bin).parent}{os.pathsep}{os.environ.get('PATH', '')}")
    namespace = {"__name__": "__guide__"}
    ran = 0
    for info, body in blocks(md.read_text()):
        name = next((w[5:] for w in info.split() if w.startswith("file=")), None)
        if name:
            (tmp_path / name).write_text(body)
        elif info == "console":
            for line in body.splitlines():
                if line.startswith("$ "):
                    cmd = line[2:]
                    r = subprocess.run(cmd, shell=True, cwd=tmp_path, env=env, capture_output=True, text=True)
                    assert r.returncode == 0, f"{md.name}: `{cmd}` exited {r.returncode}: {r.stderr}"
        elif info == "python":
            exec(compile(body, f"{md.name} (python block {ran + 1})", "exec"), namespace)
            ran += 1
    assert ran > 0
