"""Orthogonality error ||R^T R - I||_F of the batista-so3 attitude estimate after many steps, for the RKMK-4
step on SO(3) (``integrator="lie"``) and the paper's plain RK4 (``integrator="rk4"``), in float32 and float64.

One noisy run of Section 4's slow scenario (observer only, on a simulated log: 1e6 steps = 10^4 s at 100 Hz),
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
from _common import metadata, print_table, write_results  # noqa: E402

from jaxatt import montecarlo, so3  # noqa: E402
from jaxatt.experiments import batista_so3 as E  # noqa: E402


def measure(steps: int, integrator: str, dtype, samples):
    cfg = E.Config(integrator=integrator)
    obs = E.observer(cfg)
    p = E.params(cfg, dtype=dtype)
    s = jax.tree_util.tree_map(lambda a: None if a is None else jnp.asarray(a, dtype), samples)
    first = jax.tree_util.tree_map(lambda a: a[0], s)

    @jax.jit
    def go(p, s):
        st = obs.init(p, first)
        nxt = jax.tree_util.tree_map(lambda a: a[1:], s)

        def body(st, u):
            st, out = obs.step(p, st, u, jnp.asarray(cfg.dt, dtype))
            return st, (so3.orthogonality_error(out.r), jnp.linalg.norm(out.m_hat))

        cur = jax.tree_util.tree_map(lambda a: a[:-1], s)
        st, (orth, mnorm) = jax.lax.scan(body, st, cur)
        return st, orth, mnorm

    t0 = time.perf_counter()
    st, orth, mnorm = go(p, s)
    orth = np.asarray(orth, float)
    wall = time.perf_counter() - t0
    mref = float(np.linalg.norm(np.asarray(cfg.reference_nT)))
    return {"integrator": integrator, "dtype": np.dtype(dtype).name, "steps": steps,
            "orthogonality_error_final": float(orth[-1]), "orthogonality_error_max": float(orth.max()),
            "m_norm_rel_error_final": float(abs(float(mnorm[-1]) / mref - 1.0)), "wall_s_incl_compile": wall}


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
    print_table(rows, ["integrator", "dtype", "steps", "orthogonality_error_final", "orthogonality_error_max",
                       "m_norm_rel_error_final", "wall_s_incl_compile"],
                title=f"batista-so3: ||R^T R - I||_F after {args.steps} steps (Section 4 slow, noisy)")
    path = write_results("orthogonality", {"rows": rows}, out_dir=args.out)
    print(f"written {path}")


if __name__ == "__main__":
    main()
