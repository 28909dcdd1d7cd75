"""Gains files shipped with jaxatt (JSON, written by :func:`jaxatt.broad_tune.broad_tune`).

* ``robust_broad_all.json``: :mod:`jaxatt.observers.robust_ahrs` tuned on all 20 BROAD trials of the shared
  subset - the default gains of the robust AHRS.
* ``robust_broad_fold1.json`` / ``robust_broad_fold2.json``: tuned on fold 1 / fold 2 of the 2-fold
  cross-validation stratified by group (:func:`jaxatt.broad_tune.stratified_folds`), for out-of-fold numbers.

Derived from the BROAD dataset (D. Laidig, M. Caruso, A. Cereatti, T. Seel, "BROAD - A Benchmark for Robust
Inertial Orientation Estimation", Data 6(7), 2021, doi:10.3390/data6070072, CC BY 4.0).

Packaging: the JSON files are package data of ``jaxatt.data.gains`` (pyproject: ``[tool.setuptools.package-data]
"jaxatt.data.gains" = ["*.json"]``).
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
    p = resources.files(__name__) / name
    if not p.is_file():
        raise FileNotFoundError(f"no shipped gains file {name!r}; available: {available()}")
    return p


def load(name: str = "robust_broad_all.json") -> dict:
    """The whole JSON of a shipped gains file (keys: observer, gains, tuned, train_trials, history, ...)."""
    with path(name).open("r") as f:
        return json.load(f)


def load_params(which: str = "all", dtype=None):
    """Params of the robust AHRS with shipped tuned gains: ``which`` = "all" (tuned on all 20 BROAD trials),
    "fold1" or "fold2" (tuned on one fold of the 2-fold cross-validation), or a file name."""
    from ...observers import robust_ahrs

    name = which if which.endswith(".json") else f"robust_broad_{which}.json"
    d = load(name)
    if d.get("observer") != "robust":
        raise ValueError(f"{name} holds gains of {d.get('observer')!r}, not 'robust'")
    return robust_ahrs.params_from_dict(d["gains"], dtype=dtype)
