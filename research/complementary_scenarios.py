"""Trumpf et al. 2012 scenarios: measured convergence rate of the observer (eq. 10, noise-free, from 150 deg)
and the excitation measures (Defs. 3.3/4.1, Lemmas 3.4/4.2) of each scenario; the excitation plot of the
switching-reference scenario. Usage: ``python research/complementary_scenarios.py [--out DIR] [--duration S]``
(default DIR research/results: complementary-scenarios-<host>-<UTC>.json and excitation-switching.png)."""

from __future__ import annotations

import argparse
import pathlib
import sys

import jax

jax.config.update("jax_enable_x64", True)
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

HERE = pathlib.Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent / "benchmarks"))
from _common import print_table, write_results  # noqa: E402

from jaxatt import analysis, montecarlo, so3  # noqa: E402
from jaxatt.sim import references  # noqa: E402
from jaxatt.studies import complementary as E  # noqa: E402

RESULTS_DIR = HERE / "results"


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default=None)
    ap.add_argument("--duration", type=float, default=120.0)
    args = ap.parse_args()
    rows = []
    window = 5.0
    for name in E.SCENARIO_NAMES:
        cfg = E.Config(scenario=name, duration=args.duration, noise_scale=0.0, hold="linear")
        scn = E.scenario(cfg)
        samples, truth_r = references.simulate_vectors(scn, cfg.duration, cfg.dt)
        out = montecarlo.run(E.observer(cfg), E.params(cfg), samples, dt=cfg.dt, hold="linear")
        # T estimates for T samples: row 0 is the initial estimate (t = 0), row k the estimate at t_k
        ang = np.rad2deg(np.asarray(jax.vmap(so3.angle_error)(jnp.asarray(truth_r), out.r)))
        t = np.asarray(out.t)
        sel = (ang < 20.0) & (ang > 1e-6)
        rate = float(-np.polyfit(t[sel], np.log(np.deg2rad(ang[sel])), 1)[0]) if sel.sum() > 100 else float("nan")
        exc = analysis.excitation_of_scenario(scn, duration=cfg.duration, dt=cfg.dt, window=window)
        rows.append(
            {
                "scenario": name,
                "angle_0_deg": float(ang[0]),
                "angle_final_deg": float(ang[-1]),
                "decay_rate_per_s": rate,
                "lambda2_per_s_median": float(np.median(exc.lambda2) / window),
                "lambda_min_projector_per_s_median": float(np.median(exc.lambda_min_projector) / window),
                "condition_per_s_median": float(np.median(exc.condition) / window),
            }
        )
        if name == "switching":
            import matplotlib

            matplotlib.use("Agg")
            import matplotlib.pyplot as plt

            fig, ax = plt.subplots(figsize=(7, 3.2), constrained_layout=True)
            analysis.plot_excitation(exc, ax=ax, title=f"switching reference, window {window:g} s")
            out_dir = pathlib.Path(args.out) if args.out else RESULTS_DIR
            out_dir.mkdir(parents=True, exist_ok=True)
            fig.savefig(out_dir / "excitation-switching.png", dpi=110)
    print_table(
        rows,
        list(rows[0]),
        title=f"complementary observer (gain {E.Config().gain} 1/s), noise-free, "
        f"held-out scenarios; excitation over {window:g}-s windows",
    )
    print(f"written {write_results('complementary-scenarios', {'rows': rows}, out_dir=args.out or RESULTS_DIR)}")


if __name__ == "__main__":
    main()
