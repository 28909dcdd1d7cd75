"""Compare two numbers files written by numbers_v01.py / numbers_v02.py: the largest relative difference per entry."""

import json
import sys

import numpy as np


def flat(x, prefix=""):
    if isinstance(x, dict):
        for k, v in x.items():
            yield from flat(v, f"{prefix}/{k}")
    else:
        try:
            yield prefix, np.asarray(x, float)
        except (TypeError, ValueError):
            pass


a = dict(flat(json.load(open(sys.argv[1]))))
b = dict(flat(json.load(open(sys.argv[2]))))
tol = float(sys.argv[3]) if len(sys.argv) > 3 else 1e-9
worst = []
for k in sorted(a):
    if k not in b:
        print(f"missing in new: {k}")
        continue
    x, y = a[k], b[k]
    if x.shape != y.shape:
        print(f"shape {k}: {x.shape} vs {y.shape}")
        continue
    both_nan = np.isnan(x) & np.isnan(y)
    d = np.where(both_nan, 0.0, np.abs(x - y) / np.maximum(np.abs(x), 1e-300))
    d = np.where(both_nan | ((x == 0) & (y == 0)), 0.0, d)
    m = float(np.max(d)) if d.size else 0.0
    worst.append((m, k))
for m, k in sorted(worst, reverse=True)[:25]:
    print(f"{m:10.3g}  {k}" + ("   <-- MOVED" if m > tol else ""))
print(f"{sum(m > tol for m, _ in worst)} of {len(worst)} entries differ by more than {tol:g} (relative)")
