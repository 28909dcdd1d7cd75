"""Does a decaying bias gain close nlio-case1's gap to its floor? (issue 20, one-off.)

Variance-free predictions (:func:`jaxatt.fitting.varfree.predict`, the study's windows, angle_sq) of NLIO-FG with
the variance-free L-BFGS gains (``--gains``) and kv replaced by kv * min(1, (T / t)^a): a constant bias is learnt
best by a gain that decays like 1/t once it has converged. Prints the steady RMS and its deterministic part
(``bias_rms_deg``) per (T, a). Findings: research/README.md, nlio_varfree.py section.

Usage: python research/nlio_kv_schedule.py [--gains research/results/gains-nlio-case1-varfree-lbfgs.json]
"""

from __future__ import annotations

import argparse
import pathlib
import sys
import time

HERE = pathlib.Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))

import jax

jax.config.update("jax_enable_x64", True)
import jax.numpy as jnp

from jaxatt import studies
from jaxatt.fitting import gainsfile
from jaxatt.fitting import varfree as V

#: (T s, a): kv * min(1, (T / t)^a); T = inf is the constant gain
PROFILES = ((float("inf"), 1.0), (100.0, 1.0), (200.0, 1.0), (250.0, 1.0), (200.0, 2.0), (100.0, 0.5))


def decaying_kv(observer, t_from: float, power: float):
    """``observer`` whose bias gain is kv * min(1, (t_from / t)^power) at the step's start time t (s)."""

    def step(p, state, u, dt):
        f = jnp.where(state.t > t_from, (t_from / jnp.maximum(state.t, 1e-9)) ** power, 1.0)
        return observer.step(p._replace(kv=p.kv * f), state, u, dt)

    return observer._replace(step=step)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--gains", default=str(HERE / "results" / "gains-nlio-case1-varfree-lbfgs.json"))
    args = ap.parse_args(argv)
    s = studies.get("nlio-case1").setup()
    p = gainsfile.read_params(args.gains, "nlio-fg", base=s.params)
    windows = tuple((n, a, b) for n, (a, b) in s.loss_windows.items())
    for t_from, power in PROFILES:
        t0 = time.perf_counter()
        obs = s.observer if t_from == float("inf") else decaying_kv(s.observer, t_from, power)
        r = V.predict(obs, s.scenario, p, duration=s.duration, dt=s.dt, windows=windows, kind="angle_sq", hold=s.hold)
        w = r["windows"]["steady"]
        print(
            f"T {t_from:g} s, a {power:g}: steady RMS {w['rms_deg']:.5f} deg "
            f"(deterministic {w['bias_rms_deg']:.5f}) [{time.perf_counter() - t0:.0f} s]",
            flush=True,
        )


if __name__ == "__main__":
    main()
