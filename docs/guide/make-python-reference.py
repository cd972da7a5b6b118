"""Build the Python package's reference (HTML, one page for the package with a section and an
anchor per public function, class and method) from the installed `instpol`'s docstrings, with
pdoc. Any warning is an error, and the page must hold every public name of the package with
its `>>>` examples.

    python -W error docs/guide/make-python-reference.py OUT_DIR     # then open OUT_DIR/instpol.html

(.ci/run builds it into a temporary folder; nothing generated is committed.)

The reference shows the docstrings of the module, not those of the type stubs
(`__init__.pyi`): the stubs carry the one-paragraph summaries an editor shows, and pdoc would
otherwise put them, and their `...` defaults, in place of the full docstrings (units, the
paper's equations, examples) and the real defaults. So the stubs' patching is turned off here.
"""

import re
import sys
import warnings
from pathlib import Path

warnings.simplefilter("error")

import pdoc  # noqa: E402
import pdoc.doc_pyi  # noqa: E402
import pdoc.render  # noqa: E402

import instpol  # noqa: E402

if len(sys.argv) != 2:
    sys.exit(__doc__)
out = Path(sys.argv[1])

# pdoc 14-16 patch a module's documentation from its stub through this one function.
assert hasattr(pdoc.doc_pyi, "include_typeinfo_from_stub_files"), "pdoc changed: see this script's docstring"
pdoc.doc_pyi.include_typeinfo_from_stub_files = lambda module: None

pdoc.render.configure(docformat="numpy", show_source=True, footer_text=f"instpol {instpol.__version__}")
pdoc.pdoc("instpol", output_directory=out)

page = (out / "instpol.html").read_text()
# pdoc gives a module member a <section id="name">, a class member a <div id="Class.name">.
anchors = {m.group(1): m.start() for m in re.finditer(r'<(?:section|div) id="([A-Za-z_][\w.]*)"', page)}


def own_text(name):
    """The page from `name`'s anchor to the next anchor of a public name (its own docstring)."""
    start = anchors[name]
    later = [s for k, s in anchors.items() if s > start and not k.split(".")[-1].startswith("_")]
    return page[start:min(later, default=len(page))]


# Every public function, class and method has its anchor, and its own text shows an example.
missing, without_example = [], []
for name in instpol.__all__:
    obj = getattr(instpol, name)
    if name.startswith("__"):
        continue
    names = [name]
    if isinstance(obj, type):
        names += [f"{name}.{a}" for a, m in vars(obj).items()
                  if not a.startswith("_") and (callable(m) or isinstance(m, (classmethod, staticmethod)))]
    for n in names:
        if n not in anchors:
            missing.append(n)
        elif "&gt;&gt;&gt;" not in own_text(n):
            without_example.append(n)
if missing or without_example:
    sys.exit(f"reference incomplete: no section for {missing}; no >>> example shown for {without_example}")
print(f"wrote {out / 'instpol.html'}: {len(anchors)} anchors, every public function, class and method with its examples")
