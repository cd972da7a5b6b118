"""Write the astropy-made tables that `crates/skyfield/tests/it/tables.rs` reads.

Run from this folder with astropy installed:  python3 make_tables.py
The same small catalog in ECSV, VOTable (TABLEDATA), FITS and CSV, with units, a NaN, a
negative zero, an integer column, and text with a blank, a comma and a quote.
"""
import numpy as np
from astropy.table import Table
import astropy.units as u

t = Table()
t["id"] = np.array([1, 2, 3], dtype=np.int64)
t["x"] = np.array([10.5, 2047.25, -0.0]) * u.pix
t["q"] = np.array([0.0123, -1e-17, np.nan])
t["q"].description = "Q/I, dimensionless fraction"
t["chi_deg"] = np.array([179.99, 0.0, 90.0]) * u.deg
t["note"] = ["ok", "near, edge", 'said "hi"']
t.meta["comment"] = "made by make_tables.py"

t.write("astropy.ecsv", overwrite=True)
t.write("astropy.vot", format="votable", overwrite=True)
t.write("astropy.fits", overwrite=True)
t.write("astropy.csv", overwrite=True)
