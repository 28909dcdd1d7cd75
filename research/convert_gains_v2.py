"""Convert jaxatt 0.1 gains files ("jaxatt-gains/1") to the gains file of jaxatt 0.2 ("jaxatt-gains/2",
:mod:`jaxatt.fitting.gainsfile`), checking that the converted file loads to exactly the same params.

What it converted (once, for the redesign; kept to show how the shipped files were derived):

* study outputs of 0.1's ``jaxatt tune`` / ``benchmarks/ges_refined_start.py`` -> ``jaxatt/data/gains/``:
  ``gains-batista-ges-growing.json`` -> ``batista-ges-growing.json`` (observer batista-ges),
  ``gains-batista-so3.json`` -> ``batista-so3.json``, ``gains-nlio-case1.json`` -> ``nlio-case1.json`` (observer
  nlio-fg, study nlio-case1). 0.1's keys are mapped to 0.2's: ``tuning`` (+ ``config``) -> ``settings``,
  ``environment`` -> ``provenance``, ``start_gains`` -> ``start``, ``best_val_loss`` -> ``best_loss``,
  ``start_val_loss`` -> ``start_loss``; ``notes``, ``family``, ``status``, ``best_step``, ``history`` kept;
  ``converted_from`` names the source file.
* the shipped robust AHRS files (``robust_broad_{all,fold1,fold2}.json``, 0.1's ``jaxatt broad-tune`` layout with
  gains {name: number}) in place: gains with units from the registry, every other key kept as it was.

Usage: python research/convert_gains_v2.py [--study-dir research/results] [--robust] [--check-only]
(the 0.1 originals of the three study files are kept in research/results/)
"""

from __future__ import annotations

import argparse
import json
import pathlib
import sys

REPO = pathlib.Path(__file__).resolve().parents[1]
SHIPPED = REPO / "jaxatt" / "data" / "gains"

#: 0.1 study file -> shipped name
STUDY_FILES = {
    "gains-batista-ges-growing.json": "batista-ges-growing.json",
    "gains-batista-so3.json": "batista-so3.json",
    "gains-nlio-case1.json": "nlio-case1.json",
}
ROBUST_FILES = ("robust_broad_all.json", "robust_broad_fold1.json", "robust_broad_fold2.json")


def _values(params, fields):
    import numpy as np

    return {f: np.asarray(getattr(params, f), float) for f in fields}


def _same(a, b) -> float:
    """Largest absolute difference between two field -> array dicts (inf on a shape mismatch)."""
    import numpy as np

    worst = 0.0
    for k in a:
        if np.shape(a[k]) != np.shape(b[k]):
            return float("inf")
        worst = max(worst, float(np.max(np.abs(a[k] - b[k]))) if np.size(a[k]) else 0.0)
    return worst


def convert_study(src: pathlib.Path, dst: pathlib.Path, check_only: bool = False) -> float:
    """One 0.1 study gains file -> 0.2; returns the largest difference of the loaded params (must be 0)."""
    from jaxatt import studies
    from jaxatt.fitting import gainsfile
    from jaxatt.observers import registry

    old = json.loads(src.read_text())
    d = gainsfile.read(src)  # 0.1 layout read as 0.2's: observer from the study, study = "experiment"
    study = studies.get(d["study"])
    config = old.get("config") or {}
    base = study.setup(**config).params
    entry = registry.get(d["observer"])
    params = gainsfile.apply(base, d["gains"], source=str(src))
    if entry.check is not None:
        entry.check(params)
    fields = [g.field for g in entry.gains] + (["switch_times"] if hasattr(base, "switch_times") else [])
    if not check_only:
        settings = dict(old.get("tuning") or {})
        settings.update({"study": study.name, "config": config})
        extra = {"status": old.get("status", "done"), "settings": settings}
        for k_old, k_new in (
            ("best_step", "best_step"),
            ("best_val_loss", "best_loss"),
            ("start_val_loss", "start_loss"),
            ("history", "history"),
            ("notes", "notes"),
            ("family", "family"),
            ("environment", "provenance"),
        ):
            if k_old in old:
                extra[k_new] = old[k_old]
        if "start_gains" in old:
            start = gainsfile.apply(base, old["start_gains"], source=f"{src} start_gains")
            extra["start"] = gainsfile.gains_to_dict(start, entry.gains)
        where = src.resolve().relative_to(REPO) if src.resolve().is_relative_to(REPO) else src
        extra["converted_from"] = {"file": str(where), "format": old.get("format")}
        gainsfile.write(dst, observer=entry.name, params=params, gains=entry.gains, study=study.name, **extra)
    loaded = gainsfile.read_params(dst, entry.name, base=base)
    return _same(_values(params, fields), _values(loaded, fields))


def convert_robust(path: pathlib.Path, check_only: bool = False) -> float:
    """A shipped robust AHRS file, in place; returns the largest difference of the loaded params (must be 0)."""
    import jax.numpy as jnp

    from jaxatt.fitting import gainsfile
    from jaxatt.observers import registry

    entry = registry.get("robust")
    old = json.loads(path.read_text())
    base = entry.default_params(dtype=jnp.float64)
    before = gainsfile.apply(base, old["gains"], source=str(path))  # {name: number} (0.1) or 0.2's entries
    if not check_only and old.get("format") != gainsfile.FORMAT:
        extra = {k: v for k, v in old.items() if k not in ("format", "observer", "gains", "study")}
        gainsfile.write(path, observer="robust", params=before, gains=entry.gains, study=None, **extra)
    after = gainsfile.read_params(path, "robust", dtype=jnp.float64)
    fields = [g.field for g in entry.gains]
    return _same(_values(before, fields), _values(after, fields))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--study-dir", default=None, help="folder holding the 0.1 study gains files")
    ap.add_argument("--robust", action="store_true", help="convert the shipped robust_broad_*.json in place")
    ap.add_argument("--check-only", action="store_true", help="only load and compare")
    args = ap.parse_args(argv)
    import jax

    jax.config.update("jax_enable_x64", True)
    bad = 0
    if args.study_dir:
        for src, dst in STUDY_FILES.items():
            diff = convert_study(pathlib.Path(args.study_dir) / src, SHIPPED / dst, args.check_only)
            print(f"{src} -> jaxatt/data/gains/{dst}: largest difference of the loaded params {diff:g}")
            bad += diff != 0.0
    if args.robust:
        for name in ROBUST_FILES:
            diff = convert_robust(SHIPPED / name, args.check_only)
            print(f"jaxatt/data/gains/{name}: largest difference of the loaded params {diff:g}")
            bad += diff != 0.0
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
