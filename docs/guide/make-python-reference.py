"""Build the Python package's reference (HTML) from the installed `instpol`'s docstrings:

- one page per public function and class, `OUT_DIR/instpol.NAME.html`: its signature and its
  docstring (units, the paper's equations, `>>>` examples), and for a class every public
  method and property with its own signature and docstring, each under an anchor
  (`instpol.Calibration.html#Calibration.correct`);
- an index, `OUT_DIR/index.html`, linking each page with the first line of its docstring;
- pdoc's page of the whole module, `OUT_DIR/instpol.html`, everything on one page, cross-linked.

Any warning is an error, and every page must exist and show the `>>>` examples of its object
and of each of its methods (the examples themselves run in tests/python/test_docstrings.py).

    python -W error docs/guide/make-python-reference.py OUT_DIR     # then open OUT_DIR/index.html

(.ci/run builds it into a temporary folder; nothing generated is committed.)

The reference shows the docstrings of the module, not those of the type stubs
(`__init__.pyi`): the stubs carry the one-paragraph summaries an editor shows, and pdoc would
otherwise put them, and their `...` defaults, in place of the full docstrings (units, the
paper's equations, examples) and the real defaults. So the stubs' patching is turned off here
for pdoc's page, and the per-name pages are rendered from the module's own objects.
"""

import html
import sys
import warnings
from pathlib import Path

warnings.simplefilter("error")

import pdoc  # noqa: E402
import pdoc.doc  # noqa: E402
import pdoc.doc_pyi  # noqa: E402
import pdoc.docstrings  # noqa: E402
import pdoc.render  # noqa: E402
import pdoc.render_helpers  # noqa: E402

import instpol  # noqa: E402

if len(sys.argv) != 2:
    sys.exit(__doc__)
out = Path(sys.argv[1])
out.mkdir(parents=True, exist_ok=True)

# pdoc 14-16 patch a module's documentation from its stub through this one function.
assert hasattr(pdoc.doc_pyi, "include_typeinfo_from_stub_files"), "pdoc changed: see this script's docstring"
pdoc.doc_pyi.include_typeinfo_from_stub_files = lambda module: None

FORMAT = "numpy"
pdoc.render.configure(docformat=FORMAT, show_source=True, footer_text=f"instpol {instpol.__version__}")
pdoc.pdoc("instpol", output_directory=out)

STYLE = """body { font-family: sans-serif; max-width: 60em; margin: 2em auto; padding: 0 1em; line-height: 1.45; }
pre, code { font-family: monospace; background: #f4f4f4; }
pre { padding: 0.6em; overflow-x: auto; }
.signature { font-size: 1.05em; border-left: 3px solid #0072B2; }
nav { margin-bottom: 1.5em; } section { margin-top: 2em; } table { border-collapse: collapse; }
td, th { padding: 0.2em 0.8em; border-bottom: 1px solid #ddd; text-align: left; vertical-align: top; }"""


def page(title, body):
    """A whole HTML page."""
    return (f'<!doctype html>\n<html lang="en">\n<head>\n<meta charset="utf-8">\n<title>{html.escape(title)}</title>\n'
            f"<style>\n{STYLE}\n</style>\n</head>\n<body>\n{body}\n"
            f"<footer><p>instpol {html.escape(instpol.__version__)}</p></footer>\n</body>\n</html>\n")


def docstring_html(d):
    """A documented object's docstring as HTML (pdoc's own conversion of numpy docstrings)."""
    md = pdoc.docstrings.convert(d.docstring, FORMAT, d.source_file)
    return pdoc.render_helpers.to_html(md)


def signature(d, name):
    """`name(args)` of a function or class, `name` of anything else."""
    sig = getattr(d, "signature", None)
    return f"{name}{sig}" if sig is not None else name


def kind(d):
    if isinstance(d, pdoc.doc.Class):
        return "class"
    if isinstance(d, pdoc.doc.Function):
        return "function"
    return "variable"


def summary(d):
    """The first paragraph of a docstring as inline HTML (its markup converted as pdoc does)."""
    first = d.docstring.strip().split("\n\n")[0]
    text = pdoc.render_helpers.to_html(pdoc.docstrings.convert(first, FORMAT, d.source_file)).strip()
    return text.removeprefix("<p>").removesuffix("</p>")


def member_section(cls, m):
    """A method's or property's section of its class's page, under the anchor `Class.name`."""
    anchor = f"{cls}.{m.name}"
    return (f'<section id="{html.escape(anchor)}">\n<h2>{html.escape(anchor)}</h2>\n'
            f'<pre class="signature">{html.escape(signature(m, m.name))}</pre>\n{docstring_html(m)}\n</section>')


module = pdoc.doc.Module(instpol)
names = [n for n in instpol.__all__ if not n.startswith("__")]
rows, missing, without_example = [], [], []
for name in names:
    d = module.get(name)
    if d is None:
        missing.append(name)
        continue
    sections = [f'<pre class="signature">{html.escape(signature(d, name))}</pre>\n{docstring_html(d)}']
    shown = {name: sections[0]}
    if isinstance(d, pdoc.doc.Class):
        public = [m for m in d.own_members if not m.name.startswith("_") and isinstance(m, pdoc.doc.Function)]
        public += [m for m in d.own_members if not m.name.startswith("_") and isinstance(m, pdoc.doc.Variable)
                   and m.docstring]
        if public:
            sections.append("<h2>Members</h2>\n<ul>\n" + "".join(
                f'<li><a href="#{html.escape(name)}.{html.escape(m.name)}"><code>{html.escape(m.name)}</code></a></li>\n'
                for m in public) + "</ul>")
        for m in public:
            section = member_section(name, m)
            sections.append(section)
            if isinstance(m, pdoc.doc.Function):
                shown[f"{name}.{m.name}"] = section
    nav = ('<nav><a href="index.html">instpol reference</a> · '
           f'<a href="instpol.html#{html.escape(name)}">on the one-page reference</a></nav>')
    body = f"{nav}\n<h1><code>instpol.{html.escape(name)}</code> ({kind(d)})</h1>\n" + "\n".join(sections)
    (out / f"instpol.{name}.html").write_text(page(f"instpol.{name}", body), encoding="utf-8")
    without_example += [n for n, text in shown.items() if "&gt;&gt;&gt;" not in text]
    rows.append(f'<tr><td><a href="instpol.{html.escape(name)}.html"><code>{html.escape(name)}</code></a></td>'
                f"<td>{kind(d)}</td><td>{summary(d)}</td></tr>")

intro = f"<p>{summary(module)}</p>" if module.docstring else ""
index = ("<h1>The <code>instpol</code> Python reference</h1>\n"
         f"<p>instpol {html.escape(instpol.__version__)}: a page for each public function and class "
         '(<a href="instpol.html">everything on one page</a>).</p>\n'
         f"{intro}\n<table>\n<tr><th>name</th><th>kind</th><th>what it does</th></tr>\n" + "\n".join(rows) + "\n</table>")
(out / "index.html").write_text(page("instpol reference", index), encoding="utf-8")

if missing or without_example:
    sys.exit(f"reference incomplete: no page for {missing}; no >>> example shown for {without_example}")
print(f"wrote {out / 'index.html'} and {len(rows)} pages, one per public function and class, "
      "every one with its examples, and the one-page reference instpol.html")
