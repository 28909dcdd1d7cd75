"""A per-axis gyro scale learnt with the robust AHRS on BROAD, out of fold (issue 18; research/README.md,
"broad_gyro_scale_fit.py").

For each fold k: gyr <- gyr * (1 + s), s (3,) learnt by Adam (``--steps``, ``--lr``, cosine decay; one unit of the
optimised variable = ``--unit`` of scale) on fold k's trials with the shipped fold-k gains of the robust AHRS held
fixed, float32, the mean total RMSE as the loss; the other fold's trials are then scored in float64 with and
without the learnt scale.

Usage: python research/broad_gyro_scale_fit.py [--data-dir DIR] [--steps 20] [--folds 1 2]
Prints one line per Adam step and the per-trial scores; writes research/results/broad-gyro-scale-fit.json.
"""

from __future__ import annotations

import argparse
import json
import pathlib
import time

import numpy as np

HERE = pathlib.Path(__file__).resolve().parent
GAINS = HERE.parent / "jaxatt" / "data" / "gains"


def scaled(trials, s):
    """``trials`` with every gyro sample multiplied by (1 + s) per axis."""
    return [t._replace(samples=t.samples._replace(gyr=np.asarray(t.samples.gyr) * (1 + np.asarray(s)))) for t in trials]


def group_means(res, names):
    from jaxatt.data import broad

    g: dict = {"undisturbed": [], "disturbed": []}
    for n in names:
        g[broad.group_of(n)].append(res[n]["total_rmse_deg"])
    return {k: round(float(np.mean(v)), 4) for k, v in g.items()}


def fit_scale(train, p0, steps: int, lr: float, unit: float):
    """s (3,) minimising the mean total RMSE of ``train`` (float32) with the gains ``p0`` fixed."""
    import jax
    import jax.numpy as jnp
    import optax

    from jaxatt.data import broad
    from jaxatt.observers import robust_ahrs

    fn, item = broad.metric_batch(robust_ahrs.make_observer(), train, dtype=jnp.float32, checkpoint="auto")

    def loss(theta):
        smp = item["samples"]
        it = dict(item, samples=smp._replace(gyr=smp.gyr * (1 + unit * theta).astype(smp.gyr.dtype)))
        return jnp.mean(fn(p0, it)["total_rmse_deg"])

    value_and_grad = jax.jit(jax.value_and_grad(loss))
    opt = optax.adam(optax.cosine_decay_schedule(lr, steps))
    theta = jnp.zeros(3)
    state, t0 = opt.init(theta), time.time()
    for i in range(steps):
        v, g = value_and_grad(theta)
        up, state = opt.update(g, state, theta)
        theta = optax.apply_updates(theta, up)
        pct = np.round(np.asarray(theta) * unit * 100, 4).tolist()
        print(f"  step {i} loss {float(v):.4f} scale-1 (%) {pct} {time.time() - t0:.0f} s", flush=True)
    return np.asarray(theta) * unit


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data-dir", default=str(HERE.parent.parent / "shared" / "data" / "broad"))
    ap.add_argument("--steps", type=int, default=20)
    ap.add_argument("--lr", type=float, default=0.05)
    ap.add_argument("--unit", type=float, default=1e-2, help="scale per unit of the optimised variable")
    ap.add_argument("--folds", type=int, nargs="+", default=[1, 2])
    a = ap.parse_args(argv)
    import jax
    import jax.numpy as jnp

    jax.config.update("jax_enable_x64", True)
    from jaxatt.data import broad
    from jaxatt.fitting import gainsfile
    from jaxatt.observers import registry, robust_ahrs

    by = {t.name: t for t in broad.load(a.data_dir)}
    folds = broad.stratified_folds(list(by))
    obs, out = robust_ahrs.make_observer(), {}
    for k in a.folds:
        train, test = folds[k - 1], folds[2 - k]
        gains = str(GAINS / f"robust_broad_fold{k}.json")
        print(f"fold {k}: learning the scale on {len(train)} trials", flush=True)
        s = fit_scale([by[n] for n in train], gainsfile.read_params(gains, registry.get("robust"), dtype=jnp.float32),
                      a.steps, a.lr, a.unit)  # fmt: skip
        p64 = gainsfile.read_params(gains, registry.get("robust"), dtype=jnp.float64)
        before = broad.score(obs, p64, [by[n] for n in test], dtype=jnp.float64)
        after = broad.score(obs, p64, scaled([by[n] for n in test], s), dtype=jnp.float64)
        print(f"fold {k}: learnt scale - 1 (%) {np.round(s * 100, 4).tolist()}")
        print(f"fold {k}: other fold before {group_means(before, test)} after {group_means(after, test)}")
        cells = (f"{n[:2]}:{before[n]['total_rmse_deg']:.2f}->{after[n]['total_rmse_deg']:.2f}" for n in test)
        print("   ", " ".join(cells), flush=True)
        out[k] = {"scale_minus_1": s.tolist(), "before": before, "after": after}
    path = HERE / "results" / "broad-gyro-scale-fit.json"
    path.write_text(json.dumps(out, indent=1))
    print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
