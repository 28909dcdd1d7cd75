"""Gains files shipped with jaxatt (:mod:`jaxatt.fitting.gainsfile` format), package data.

* ``robust_broad_all.json``: :mod:`jaxatt.observers.robust_ahrs` tuned on all 20 BROAD trials of the shared subset:
  the gains of ``jaxatt.filter("robust", ...)`` (the registry entry's ``shipped``).
* ``robust_broad_fold1.json`` / ``robust_broad_fold2.json``: tuned on fold 1 / fold 2 of the 2-fold cross-validation
  stratified by group (:func:`jaxatt.data.broad.stratified_folds`), for out-of-fold numbers.
* ``batista-ges-growing.json``, ``batista-so3.json``, ``nlio-case1.json``: gains tuned on simulated seeds of those
  studies (``jaxatt evaluate --experiment E --gains FILE`` reads them).
* ``batista-ges-gradient.json``: batista-ges tuned by gradients alone on the variance-free loss (no runs; Adam then
  L-BFGS from the paper's gains; research/varfree_tune.py).
* ``batista-so3-gradient.json``: batista-so3 tuned by gradients alone on the variance-free loss (no runs; L-BFGS
  from the paper's gains, then L-BFGS restarted with a fresh memory; research/varfree_tune.py --study batista-so3).
* ``nlio-case1-gradient.json``: the NLIO-FG gains of nlio-case1 tuned by gradients alone on the variance-free loss
  (L-BFGS from the paper's gains, no runs; research/nlio_varfree.py compares it held out).

Derived from the BROAD dataset (D. Laidig, M. Caruso, A. Cereatti, T. Seel, "BROAD - A Benchmark for Robust
Inertial Orientation Estimation", Data 6(7), 2021, doi:10.3390/data6070072, CC BY 4.0).
"""

from __future__ import annotations

import json
from importlib import resources
from typing import List

__all__ = ["available", "path", "load", "load_params"]


def available() -> List[str]:
    """Names of the shipped gains files."""
    return sorted(p.name for p in resources.files(__name__).iterdir() if p.name.endswith(".json"))


def path(name: str):
    """A path-like (importlib.resources Traversable) to the shipped gains file ``name``."""
    from ...fitting.gainsfile import shipped_path

    return shipped_path(name)


def load(name: str = "robust_broad_all.json") -> dict:
    """The whole JSON of a shipped gains file."""
    with path(name).open("r") as f:
        return json.load(f)


def load_params(which: str = "all", dtype=None):
    """Params of the robust AHRS with shipped gains: ``which`` = "all" (tuned on all 20 BROAD trials), "fold1" or
    "fold2" (one fold of the 2-fold cross-validation), or a file name."""
    from ...fitting import gainsfile

    name = which if which.endswith(".json") else f"robust_broad_{which}.json"
    return gainsfile.load_shipped(name, "robust", dtype=dtype)
