"""Orthogonality error ||R^T R - I||_F of the batista-so3 attitude estimate after many steps, for the RKMK-4
step on SO(3) (``integrator="lie"``) and the paper's plain RK4 (``integrator="rk4"``), in float32 and float64.

One noisy run of Section 4's slow scenario (observer only, on a simulated log: 1e6 steps = 10^4 s at 100 Hz, run
through the engine's scan with a reducer that keeps the largest and the last error, so no trajectory is stored),
also reporting |m^| / |I_m| - 1 (eq. 9 preserves |m^|). Usage::

    python benchmarks/orthogonality.py [--steps 1000000]
"""

from __future__ import annotations

import argparse
import sys
import time

import jax

jax.config.update("jax_enable_x64", True)
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

sys.path.insert(0, str(__import__("pathlib").Path(__file__).resolve().parent))
from _common import print_table, write_results  # noqa: E402

from jaxatt import engine, montecarlo, so3  # noqa: E402
from jaxatt.studies import batista_so3 as E  # noqa: E402


# A reducer of the one scan (jaxatt.engine): the largest and the last ||R^T R - I||_F and the last |m^| over the
# estimates of a run (module-level functions: the compiled runner is cached on them).
def _orth_init(t0, truth0, out0):
    e = so3.orthogonality_error(out0.r)
    return (e, e, jnp.linalg.norm(out0.m_hat)), None


def _orth_update(acc, t, truth, out):
    e = so3.orthogonality_error(out.r)
    return (jnp.maximum(acc[0], e), e, jnp.linalg.norm(out.m_hat)), None


def _orth_finish(acc):
    return {"max": acc[0], "final": acc[1], "m_norm_final": acc[2]}


ORTHOGONALITY = engine.Reducer(_orth_init, _orth_update, _orth_finish)


def measure(steps: int, integrator: str, dtype, samples):
    cfg = E.Config(integrator=integrator)
    p = E.params(cfg, dtype=dtype)
    s = jax.tree_util.tree_map(lambda a: jnp.asarray(a, dtype)[None], samples)  # one run, all in ``dtype``
    fn = engine.compiled(E.observer(cfg), engine.Recorded(steps, False), ORTHOGONALITY, hold=cfg.hold, obs_dtype=dtype)
    item = {"samples": s, "dt": jnp.asarray(cfg.dt, dtype)[None], "truth": None}
    t0 = time.perf_counter()
    res = jax.block_until_ready(fn(None, p, item).summary)
    wall = time.perf_counter() - t0
    mref = float(np.linalg.norm(np.asarray(cfg.reference_nT)))
    return {
        "integrator": integrator,
        "dtype": np.dtype(dtype).name,
        "steps": steps,
        "orthogonality_error_final": float(res["final"][0]),
        "orthogonality_error_max": float(res["max"][0]),
        "m_norm_rel_error_final": float(abs(float(res["m_norm_final"][0]) / mref - 1.0)),
        "wall_s_incl_compile": wall,
    }


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--steps", type=int, default=1_000_000)
    ap.add_argument("--out", default=None)
    args = ap.parse_args()
    cfg = E.Config()
    samples, _ = montecarlo.simulate_log(E.scenario(cfg), duration=args.steps * cfg.dt, dt=cfg.dt, seed=0)
    samples = jax.tree_util.tree_map(np.asarray, samples)
    rows = []
    for integrator in ("lie", "rk4"):
        for dtype in (jnp.float64, jnp.float32):
            print(f"{integrator} {np.dtype(dtype).name} ...", flush=True)
            rows.append(measure(args.steps, integrator, dtype, samples))
    print_table(
        rows,
        [
            "integrator",
            "dtype",
            "steps",
            "orthogonality_error_final",
            "orthogonality_error_max",
            "m_norm_rel_error_final",
            "wall_s_incl_compile",
        ],
        title=f"batista-so3: ||R^T R - I||_F after {args.steps} steps (Section 4 slow, noisy)",
    )
    path = write_results("orthogonality", {"rows": rows}, out_dir=args.out)
    print(f"written {path}")


if __name__ == "__main__":
    main()
