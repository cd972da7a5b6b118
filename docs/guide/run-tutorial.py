"""Execute the tutorial notebook (docs/guide/tutorial.ipynb) against the installed `instpol`,
as a reader running every cell in order would, and fail on any cell's error. The notebook is
kept in the repository without outputs (its figures and numbers are made by the run, not
stored beside the code that makes them); the executed copy, with its figures, is written to
OUT when given.

    python docs/guide/run-tutorial.py [OUT.ipynb]
"""

import sys
import time
from pathlib import Path

import nbclient
import nbformat

NOTEBOOK = Path(__file__).with_name("tutorial.ipynb")

nb = nbformat.read(NOTEBOOK, as_version=4)
nbformat.validate(nb)
stored = [i for i, c in enumerate(nb.cells) if c.cell_type == "code" and (c.outputs or c.execution_count)]
if stored:
    sys.exit(f"{NOTEBOOK}: cells {stored} keep outputs: clear them (jupyter nbconvert --clear-output --inplace)")

start = time.time()
nbclient.NotebookClient(nb, timeout=600, kernel_name="python3", resources={"metadata": {"path": str(NOTEBOOK.parent)}}).execute()
errors = [o for c in nb.cells if c.cell_type == "code" for o in c.outputs if o.output_type == "error"]
if errors:
    sys.exit(f"{NOTEBOOK}: {errors[0].ename}: {errors[0].evalue}")
figures = sum(1 for c in nb.cells if c.cell_type == "code" for o in c.outputs if "image/png" in o.get("data", {}))
if figures < 3:
    sys.exit(f"{NOTEBOOK}: {figures} figures drawn, expected 3")
if len(sys.argv) > 1:
    nbformat.write(nb, sys.argv[1])
print(f"{NOTEBOOK.name}: {len(nb.cells)} cells ran in {time.time() - start:.0f} s, {figures} figures")
