"""The peer of `instpol scan` (bench/scan.sh): an astropy `fits.getheader` loop over a folder
of raw files, reading the keywords a scan needs (instrument, DPR category/type/technique,
target, filter, HWP angle, binning, exposure number, chip, MJD) into one record per file, as a
script sorting a night would. Also makes the files: `make DIR N` writes N small FORS2-like
chip files (8 x 8 px, the headers of an archive file's size) with ESO DPR keywords.

usage: python3 scan_peer.py make DIR N | scan DIR
"""

import os
import sys
import time


def card(key, value, comment=""):
    if isinstance(value, str):
        v = "'" + value.replace("'", "''").ljust(8) + "'"
    elif isinstance(value, bool):
        v = "T" if value else "F"
    else:
        v = repr(value)
    if len(key) > 8:
        text = f"HIERARCH {key} = {v}"
    else:
        text = f"{key:<8}= {v:>20}"
    if comment:
        text += f" / {comment}"
    return text[:80].ljust(80)


def make(folder, n):
    os.makedirs(folder, exist_ok=True)
    kinds = [("CALIB", "BIAS", "IMAGE")] * 2 + [("CALIB", "FLAT,SKY", "IMAGE")] * 2 + [("SCIENCE", "OBJECT", "POLARIMETRY")] * 6
    data = bytes(2880)
    for k in range(n):
        exp, chip = divmod(k, 2)
        catg, typ, tech = kinds[exp % len(kinds)]
        mjd = 58546.8 + exp * 30 / 86400
        cards = [
            card("SIMPLE", True), card("BITPIX", 16), card("NAXIS", 2), card("NAXIS1", 8), card("NAXIS2", 8),
            card("EXTEND", True), card("BZERO", 32768), card("BSCALE", 1), card("EXTNAME", f"CHIP{chip + 1}"),
            card("INSTRUME", "FORS2"), card("OBJECT", f"field {exp // 16}"), card("MJD-OBS", mjd),
            card("RA", 150.0 + exp // 16), card("DEC", -30.0), card("EXPTIME", 30.0),
            card("ESO DPR CATG", catg), card("ESO DPR TYPE", typ), card("ESO DPR TECH", tech),
            card("ESO OBS TARG NAME", f"T{exp // 16}"), card("ESO INS FILT1 NAME", "v_HIGH"),
            card("ESO INS RETA2 POSANG", 22.5 * (exp % 4)), card("ESO DET EXP NO", exp + 1),
            card("ESO DET WIN1 BINX", 2), card("ESO DET WIN1 BINY", 2),
            card("ESO DET OUT1 PRSCX", 0), card("ESO DET OUT1 OVSCX", 0),
            card("ESO DET OUT1 PRSCY", 0), card("ESO DET OUT1 OVSCY", 0),
            card("ESO DET OUT1 CONAD", 1.25), card("ESO DET OUT1 RON", 3.0),
        ]
        # An archive header carries a few hundred more keywords (telescope, ambient, ...).
        cards += [card(f"ESO TEL AMBI K{i}", float(i), "filler as an archive header has") for i in range(150)]
        cards.append("END".ljust(80))
        head = "".join(cards).encode()
        head += b" " * (-len(head) % 2880)
        stamp = f"{exp:06d}"
        with open(os.path.join(folder, f"FORS2.2019-03-04T{stamp}_CHIP{chip + 1}.fits"), "wb") as f:
            f.write(head + data)


def scan(folder):
    from astropy.io import fits

    keys = ["INSTRUME", "HIERARCH ESO DPR CATG", "HIERARCH ESO DPR TYPE", "HIERARCH ESO DPR TECH",
            "HIERARCH ESO OBS TARG NAME", "HIERARCH ESO INS FILT1 NAME", "HIERARCH ESO INS RETA2 POSANG",
            "HIERARCH ESO DET WIN1 BINX", "HIERARCH ESO DET WIN1 BINY", "HIERARCH ESO DET EXP NO", "EXTNAME",
            "MJD-OBS", "RA", "DEC", "EXPTIME"]
    t0 = time.perf_counter()
    files = sorted(os.path.join(folder, f) for f in os.listdir(folder) if f.endswith(".fits"))
    records = []
    for p in files:
        h = fits.getheader(p)
        records.append({k: h.get(k) for k in keys})
    return len(records), time.perf_counter() - t0


if __name__ == "__main__":
    if sys.argv[1] == "make":
        make(sys.argv[2], int(sys.argv[3]))
    else:
        n, s = scan(sys.argv[2])
        print(f'{{"files": {n}, "seconds": {s:.4f}}}')
