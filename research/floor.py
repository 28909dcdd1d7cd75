"""The floor (issue 20 item 4): the best attitude error any estimator can reach with each seed experiment's
sensors (the Kalman filter of the problem linearised along the noise-free run, :mod:`jaxatt.fitting.floor`), and
every observer of research/varfree_check.py's cases, with the paper's gains and the shipped tuned gains, as a
ratio to it, over the same steady windows.

For each case (batista-ges, batista-so3, nlio-case1, complementary; set-ups and windows of varfree_check.CASES):

* the floor over the steady window: RMS (sqrt of the window mean of E[theta^2]) and mean angle (window mean of
  E[theta]) of the causal Kalman filter, and of the RTS smoother (offline floor), with the default prior
  (:class:`jaxatt.fitting.floor.Prior`); the same with the prior's standard deviations x0.1 and x10 (the steady
  floor must not depend on it);
* the observers' values from research/results/varfree-<case>.json (variance-free prediction and Monte Carlo over
  1000 runs), as ratios to the floor; with ``--extra``, the variance-free prediction of the other observers of
  the sensors2020 Case 1 (NLO, NLO-a, NLIO-TV, paper gains; about a minute each), which varfree_check does not
  cover;
* batista-ges: the closed form of the heading floor, sigma_g / (|omega_E x m_hat| sqrt(t)) (its coth form,
  :func:`jaxatt.fitting.floor.heading_floor_closed_form`), averaged like the floor.

Writes research/results/floor-<host>-<UTC>.json (jaxatt.io.write_json) and prints the table.

Usage: python research/floor.py [--cases batista-ges ...] [--extra]
"""

from __future__ import annotations

import argparse
import datetime
import json
import math
import pathlib
import socket
import sys
import time

HERE = pathlib.Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))
sys.path.insert(0, str(HERE))

import jax

jax.config.update("jax_enable_x64", True)
import numpy as np
from varfree_check import CASES  # noqa: E402

from jaxatt import io, studies
from jaxatt.fitting import floor as FL
from jaxatt.fitting import varfree as V

RESULTS = HERE / "results"
#: sensors2020 Case 1 observers without a varfree_check entry (paper gains), computed with --extra
NLIO_EXTRA = ("NLO", "NLO-a", "NLIO-TV")


def floor_case(case: str) -> dict:
    study, overrides, ws, _ = CASES[case]
    s = studies.get(study).setup(**overrides)
    wins = (("steady", ws, math.inf),)
    t0 = time.perf_counter()
    res = FL.floor(s.scenario, duration=s.duration, dt=s.dt, windows=wins, hold=s.hold, smoother=True)
    wall = time.perf_counter() - t0
    out = {
        "study": study,
        "config": io.to_jsonable(s.config._asdict()),
        "window": [ws, None],
        "hold": s.hold,
        "unknowns": res["unknowns"],
        "measurements": res["measurements"],
        "prior": res["prior"],
        "filter": res["windows"]["steady"],
        "smoother": res["smoothed"]["steady"],
        "wall_s": wall,
        "prior_sensitivity": {},
    }
    p0 = FL.Prior()
    for k in (0.1, 10.0):
        r = FL.floor(
            s.scenario,
            duration=s.duration,
            dt=s.dt,
            windows=wins,
            hold=s.hold,
            prior=FL.Prior(p0.attitude_rad * k, p0.bias_rad_s * k),
        )["windows"]["steady"]
        out["prior_sensitivity"][f"x{k:g}"] = {
            "rms_deg": r["rms_deg"],
            "mean_deg": r["mean_deg"],
            "rel_change_rms": r["rms_deg"] / out["filter"]["rms_deg"] - 1.0,
        }
    if study == "batista-ges":
        t = np.arange(int(round(ws / s.dt)), int(round(s.duration / s.dt)) + 1) * s.dt
        var = FL.heading_floor_closed_form(s.scenario, t)
        m = np.asarray(s.scenario.ref_nav)
        c = np.linalg.norm(np.cross(np.asarray(s.scenario.earth_rate_nav), m / np.linalg.norm(m)))
        inv_sqrt = float(s.scenario.gyro_arw) / c / np.sqrt(t)
        out["closed_form"] = {
            "what": "heading about m_hat only: sigma_g / (|omega_E x m_hat| sqrt(t)) and (q / c) coth(c t); "
            "mean angle = sqrt(2 / pi) sigma (one axis), RMS = sqrt(window mean of sigma^2)",
            "one_over_sqrt_t": {
                "mean_deg": float(np.degrees(np.mean(np.sqrt(2 / np.pi) * inv_sqrt))),
                "rms_deg": float(np.degrees(np.sqrt(np.mean(inv_sqrt**2)))),
            },
            "coth": {
                "mean_deg": float(np.degrees(np.mean(np.sqrt(2 / np.pi * var)))),
                "rms_deg": float(np.degrees(np.sqrt(np.mean(var)))),
            },
        }
    return out


def observers_case(case: str, floor: dict) -> dict:
    path = RESULTS / f"varfree-{case}.json"
    rows = {}
    if not path.exists():
        return rows
    d = json.loads(path.read_text())
    label = "NLIO-FG " if case == "nlio-case1" else ""
    for name, e in d["gain_sets"].items():
        pr = e.get("prediction")
        if pr is None:
            continue
        gains = e["gains"]
        row = {
            "gains": pathlib.Path(gains).name if isinstance(gains, str) and gains != "None" else gains,
            "source": f"research/results/varfree-{case}.json",
            "predicted": {"rms_deg": pr["rms_deg"], "mean_deg": pr["mean_deg"]},
        }
        if "mc" in e:
            mc = e["mc"]
            row["monte_carlo"] = {k: mc[k] for k in ("runs", "rms_deg", "rms_se", "mean_deg", "mean_se")}
        rows[label + name] = _ratios(row, floor)
    return rows


def _ratios(row: dict, floor: dict) -> dict:
    f, sm = floor["filter"], floor["smoother"]
    for src in ("predicted", "monte_carlo"):
        if src in row:
            v = row[src]
            row[src]["ratio_rms"] = v["rms_deg"] / f["rms_deg"]
            row[src]["ratio_mean"] = v["mean_deg"] / f["mean_deg"]
            row[src]["ratio_rms_smoother"] = v["rms_deg"] / sm["rms_deg"]
    return row


def nlio_extra(floor: dict) -> dict:
    """Variance-free predictions of the other Case-1 observers (paper gains) over the steady window."""
    from jaxatt.studies import nlio as N

    study, overrides, ws, _ = CASES["nlio-case1"]
    cfg = N.config(study, **overrides)
    scn = N.scenario(cfg)
    rows = {}
    for name in NLIO_EXTRA:
        t0 = time.perf_counter()
        pred = V.predict(
            N.observer(cfg, name),
            scn,
            N.params(cfg, name, dtype=np.float64),
            duration=cfg.duration,
            dt=cfg.dt,
            windows=(("steady", ws, math.inf),),
            hold=cfg.hold,
        )["windows"]["steady"]
        row = {
            "gains": "paper",
            "source": "varfree.predict (this script)",
            "predicted": {"rms_deg": pred["rms_deg"], "mean_deg": pred["mean_deg"]},
            "wall_s": time.perf_counter() - t0,
        }
        rows[f"{name} paper"] = _ratios(row, floor)
        print(f"nlio-case1 {name}: predicted RMS {pred['rms_deg']:.4f} deg ({row['wall_s']:.0f} s)", flush=True)
    return rows


def table(payload: dict) -> str:
    lines = [
        "| case (window) | floor RMS / mean (deg) | smoother RMS (deg) | observer, gains | predicted RMS (deg) | "
        "ratio RMS | ratio mean | Monte Carlo RMS (SE) | ratio RMS |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for case, c in payload["cases"].items():
        f, sm = c["floor"]["filter"], c["floor"]["smoother"]
        w0 = c["floor"]["window"][0]
        head = f"| {case} (t >= {w0:g} s) | {f['rms_deg']:.4f} / {f['mean_deg']:.4f} | {sm['rms_deg']:.4f} "
        for i, (name, r) in enumerate(c["observers"].items()):
            p = r["predicted"]
            mc = r.get("monte_carlo")
            mcs = f"{mc['rms_deg']:.4f} ({mc['rms_se']:.4f}) | {mc['ratio_rms']:.3f}" if mc else "- | -"
            lead = head if i == 0 else "| | | "
            lines.append(
                f"{lead}| {name} | {p['rms_deg']:.4f} | {p['ratio_rms']:.3f} | {p['ratio_mean']:.3f} | {mcs} |"
            )
    return "\n".join(lines)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--cases", nargs="*", default=list(CASES), choices=sorted(CASES))
    ap.add_argument("--extra", action="store_true", help="also predict NLO, NLO-a, NLIO-TV of nlio-case1")
    ap.add_argument("--out", default=None, help="result path (default research/results/floor-<host>-<UTC>.json)")
    a = ap.parse_args(argv)
    host = "".join(ch if ch.isalnum() or ch in "-_." else "_" for ch in socket.gethostname()) or "host"
    stamp = datetime.datetime.now(datetime.timezone.utc).strftime("%Y%m%dT%H%M%SZ")
    out = pathlib.Path(a.out) if a.out else RESULTS / f"floor-{host}-{stamp}.json"
    payload = {
        "what": "filtering floor (Kalman filter / RTS smoother of the linearised problem, jaxatt.fitting.floor) over "
        "each case's steady window, and the observers of research/varfree_check.py as ratios to it: RMS = sqrt(window "
        "mean of E[theta^2]), mean = window mean of E[theta] (deg)",
        "environment": io.environment(),
        "cases": {},
    }
    for case in a.cases:
        fl = floor_case(case)
        f = fl["filter"]
        print(
            f"{case}: floor RMS {f['rms_deg']:.4f} deg, mean {f['mean_deg']:.4f} deg; smoother RMS "
            f"{fl['smoother']['rms_deg']:.4f} ({fl['wall_s']:.0f} s)",
            flush=True,
        )
        obs = observers_case(case, fl)
        if case == "nlio-case1" and a.extra:
            obs.update(nlio_extra(fl))
        payload["cases"][case] = {"floor": fl, "observers": obs}
        io.write_json(out, payload)
    print(table(payload))
    print(f"results written to {out}")


if __name__ == "__main__":
    main()
