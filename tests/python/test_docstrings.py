"""The package documents itself: every public function, class, method and property has a
docstring in the module (what ``help()`` shows) and in the type stubs (what an editor shows),
and the examples in the docstrings run with the output they show (doctest)."""

import ast
import doctest
import inspect
import os
import re
from pathlib import Path

import instpol

STUB = Path(__file__).resolve().parents[2] / "crates" / "python" / "python" / "instpol" / "__init__.pyi"


def public_objects():
    """(name, object) of every public function, class, method and property of the package."""
    out = []
    for name in instpol.__all__:
        obj = getattr(instpol, name)
        if name.startswith("__") or name in ("InputError", "FileError"):
            continue
        out.append((name, obj))
        if inspect.isclass(obj):
            for attr, member in vars(obj).items():
                if attr.startswith("_"):
                    continue
                if isinstance(member, (property, classmethod, staticmethod)) or inspect.isfunction(member):
                    out.append((f"{name}.{attr}", member))
    return out


def test_every_public_object_has_a_docstring():
    objs = public_objects()
    assert len(objs) > 20, [n for n, _ in objs]
    missing = [n for n, o in objs if not (getattr(o, "__doc__", None) or "").strip()]
    assert not missing, f"no docstring: {missing}"


def test_every_stub_definition_has_a_docstring():
    tree = ast.parse(STUB.read_text())
    missing = []
    for node in ast.walk(tree):
        if isinstance(node, (ast.FunctionDef, ast.ClassDef)) and not node.name.startswith("_"):
            if ast.get_docstring(node) is None:
                missing.append(node.name)
    assert not missing, f"no docstring in __init__.pyi: {missing}"


def test_docstring_examples_run_as_shown(instpol_bin, monkeypatch):
    # run()'s example runs its plan's units with the binary, as a reader's would with
    # instpol on PATH.
    monkeypatch.setenv("INSTPOL_BIN", instpol_bin)
    r = doctest.testmod(instpol, optionflags=doctest.ELLIPSIS | doctest.NORMALIZE_WHITESPACE)
    assert r.attempted >= 100, r
    assert r.failed == 0, r


def api_objects():
    """(name, object) of every public function and class of the package (``instpol.__all__``,
    the data ``__version__``, ``__citation__`` aside) and every public method of its classes
    (properties are values, documented without examples)."""
    out = []
    for name in instpol.__all__:
        obj = getattr(instpol, name)
        if not (inspect.isfunction(obj) or inspect.isclass(obj) or inspect.isbuiltin(obj)):
            continue
        out.append((name, obj))
        if inspect.isclass(obj):
            for attr, member in vars(obj).items():
                if attr.startswith("_"):
                    continue
                if isinstance(member, (classmethod, staticmethod)):
                    member = member.__func__
                if inspect.isfunction(member):
                    out.append((f"{name}.{attr}", member))
    return out


def test_every_public_function_and_class_has_an_example():
    """The rule of the reference (docs/python-reference, built by .ci/run): every public
    function, class and method shows at least one ``>>>`` example, and doctest finds it (so it
    runs in test_docstring_examples_run_as_shown and in CI's doctest run)."""
    objs = api_objects()
    names = {n for n, _ in objs}
    # The enumeration sees the whole API: a broken walk would find nothing and pass.
    assert {"stokes", "simulate", "reduce", "Calibration", "Calibration.correct", "InputError"} <= names, names
    finder = doctest.DocTestFinder(recurse=False)
    missing = []
    for name, obj in objs:
        tests = finder.find(obj, name, module=False, globs={})
        if not any(t.examples for t in tests):
            missing.append(name)
    assert not missing, f"public API without a >>> example in its docstring: {missing}"


def test_doctests_cover_every_public_function():
    """doctest.testmod runs one test per object with examples: at least one per public object."""
    finder = doctest.DocTestFinder()
    with_examples = {t.name.removeprefix("instpol.") for t in finder.find(instpol) if t.examples}
    want = {n for n, _ in api_objects()}
    assert want <= with_examples, sorted(want - with_examples)


# The equation numbers of Patat & Romaniello 2006 as its source numbers them: the labels of the
# numbered equations in order (an eqnarray of one row holding an array is one equation; rows
# with \nonumber are none). Read from the paper's LaTeX source when it is at hand
# (INSTPOL_PAPER_TEX, else the project's shared copy), counted here, not copied.
PAPER_TEX = [Path(os.environ["INSTPOL_PAPER_TEX"])] if os.environ.get("INSTPOL_PAPER_TEX") else [
    Path(__file__).resolve().parents[2].parent / "shared" / "paper" / "patat-romaniello-2006.tex",
]


def paper_equation_numbers(tex: str):
    """label -> equation number, from LaTeX source: equation environments count one each,
    eqnarray rows (split at top-level ``\\\\``, outside nested environments) one each unless
    ``\\nonumber``; a label belongs to the number of its row, or of the environment's first
    numbered row when its own row is unnumbered (as LaTeX's eqnarray steps the counter)."""
    tex = re.sub(r"(?<!\\)%.*", "", tex)
    numbers, n = {}, 0
    for m in re.finditer(r"\\begin\{(equation|eqnarray)\}(.*?)\\end\{\1\}", tex, re.S):
        env, body = m.groups()
        if env == "equation":
            if "\\nonumber" in body:
                continue
            n += 1
            for lab in re.findall(r"\\label\{([^}]*)\}", body):
                numbers[lab] = n
            continue
        rows, depth, cur, i = [], 0, "", 0
        while i < len(body):
            if body.startswith("\\begin{", i):
                depth += 1
            elif body.startswith("\\end{", i):
                depth -= 1
            if depth == 0 and body.startswith("\\\\", i):
                rows.append(cur)
                cur, i = "", i + 2
                continue
            cur += body[i]
            i += 1
        rows.append(cur)
        first, pending = None, []
        for row in rows:
            labels = re.findall(r"\\label\{([^}]*)\}", row)
            if "\\nonumber" in row or not row.strip():
                pending += labels
                continue
            n += 1
            first = first or n
            for lab in labels + pending:
                numbers[lab] = n
            pending = []
        for lab in pending:
            numbers[lab] = first if first is not None else n + 1
    return numbers


def test_equation_numbers_in_docstrings_are_the_papers():
    """Every equation a public docstring cites is written ``Eq. N [eq:label]``, and N is the
    number the paper gives that label."""
    import sys

    tex = next((p for p in PAPER_TEX if p.is_file()), None)
    text = "\n".join(inspect.getdoc(o) or "" for _, o in api_objects()) + (instpol.__doc__ or "")
    text += STUB.read_text()
    cited = re.findall(r"Eq\.\s+(\d+)\s+\[eq:(\w+)\]", text)
    bare = re.findall(r"(?<!\[)eq:\w+", text)
    assert not bare, f"equation labels without their number (write 'Eq. N [eq:label]'): {sorted(set(bare))}"
    assert len(cited) > 20
    if tex is None:
        # ../shared is always beside the clone in CI (.ci/run sets INSTPOL_REQUIRE_DATA=1).
        assert os.environ.get("INSTPOL_REQUIRE_DATA", "0") == "0", f"the paper's source is missing: {PAPER_TEX}"
        print(f"\nSKIPPED LOUDLY: the paper's source is not at {PAPER_TEX}: equation numbers unchecked", file=sys.stderr)
        return
    numbers = paper_equation_numbers(tex.read_text())
    # The counting found the paper's equations: the first is P (eq:poldeg), the last labelled
    # one the first-order solution (eq:approx), after every other label.
    assert numbers["eq:poldeg"] == 1 and numbers["eq:approx"] == max(numbers.values()), numbers
    wrong = sorted({(f"eq:{lab}", int(num), numbers.get(f"eq:{lab}")) for num, lab in cited
                    if numbers.get(f"eq:{lab}") != int(num)})
    assert not wrong, f"(label, number written, number in the paper): {wrong}"


def test_citation_is_the_clis_and_cites_the_paper(instpol_bin):
    """instpol.__citation__ is what `instpol --version` prints after its version line (one text,
    two faces), and names the paper as CITATION.cff does (DOI, volume, first page)."""
    import subprocess

    out = subprocess.run([instpol_bin, "--version"], capture_output=True, text=True, check=True).stdout
    first, _, rest = out.partition("\n")
    assert first == f"instpol {instpol.__version__}"
    assert rest.strip() == instpol.__citation__.strip()
    cff = (STUB.parents[4] / "CITATION.cff").read_text()
    doi = re.search(r"doi: \"?([^\"\n]+)", cff).group(1)
    volume = re.search(r"volume: (\d+)", cff).group(1)
    start = re.search(r"start: (\d+)", cff).group(1)
    c = instpol.__citation__
    assert doi in c and f"PASP {volume}, {start}" in c and "@article{" in c and "Patat" in c


def test_the_guides_reference_page_lists_the_public_api():
    """docs/guide/python-reference.md's table names every public function and class, and only
    those: a function added or removed changes the page too."""
    page = (STUB.parents[4] / "docs" / "guide" / "python-reference.md").read_text()
    listed = set(re.findall(r"^\| `(\w+)` \|", page, re.M))
    public = {n for n, o in api_objects() if "." not in n}
    assert listed == public, f"missing from the page: {sorted(public - listed)}; not in the API: {sorted(listed - public)}"
