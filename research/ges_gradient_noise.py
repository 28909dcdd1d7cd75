"""How noisy is the gradient that tunes batista-ges (issue 6)? Per-run gradients of the steady-state loss
(mean angle error over t >= 2400 s of a 3600-s run) with respect to the tuned numbers, and the signal-to-noise
ratio of a minibatch mean.

For each of ``--runs`` training runs (seed 0, run indices 0 ...), the gradient of that run's loss with respect
to the unconstrained gains theta (log-gains of the schedule intervals that start at or after 720 s on the
refined schedule 720, 900, ..., 3300 s, and the log-diagonal of gain_z's Cholesky factor: the set tuned by
research/tune_acceptance.py --refine-schedule ... --schedule-from 720 --diagonal-spd). Per component:
mean g, standard deviation s across runs, and SNR_B = |mean| / (s / sqrt(B)) for minibatches of B runs.
SNR below ~1 at B = 8 means an Adam step follows the noise of the minibatch, not the held-out loss.

Writes research/results/ges-gradient-noise-<host>-<UTC>.json (``--out``).

Usage: python research/ges_gradient_noise.py [--runs 16] [--start G.json] [--duration S]
(--duration < 3600 s: a reduced check; the steady window then starts at 2/3 of it)
"""

from __future__ import annotations

import argparse
import pathlib
import sys
import time

HERE = pathlib.Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
sys.path.insert(0, str(HERE.parent / "benchmarks"))

import _common as C  # noqa: E402
from ges_refined_start import REFINED_TIMES, RESULTS_DIR  # noqa: E402


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--runs", type=int, default=16)
    ap.add_argument("--start", default=None, help="gains file to differentiate at (default: the paper's)")
    ap.add_argument("--duration", type=float, default=None, help="horizon, s (default the paper's 3600)")
    ap.add_argument("--out", default=str(RESULTS_DIR))
    args = ap.parse_args(argv)
    import jax

    jax.config.update("jax_enable_x64", True)
    import numpy as np

    from jaxatt import montecarlo, schedule, studies
    from jaxatt.fitting import gainsfile, losses
    from jaxatt.fitting import parametrize as P
    from jaxatt.observers import registry

    meta = C.metadata(sys.argv if argv is None else ["ges_gradient_noise.py"] + list(argv))
    s = studies.get("batista-ges").setup(**({} if args.duration is None else {"duration": args.duration}))
    base = s.params
    if args.start:  # as jaxatt.fit(start=...): the file's gains, then the refined schedule
        base = gainsfile.apply(base, gainsfile.read(args.start)["gains"], source=args.start)
    base = schedule.refine(base, REFINED_TIMES, ["alpha1", "alpha2"])
    starts = np.concatenate([[0.0], np.asarray(base.switch_times, float)])
    masks = {f: P.schedule_mask_from(base.switch_times, 720.0) for f in ("alpha1", "alpha2")}
    masks["gain_z"] = P.SPD.diagonal_mask(9)
    bound = P.for_gains(registry.get("batista-ges").gains, masks=masks).bind(base)
    th0 = bound.init()
    # the fitter's loss (jaxatt.fitting.losses): mean angle error (deg) over the steady window of each run
    ss, se = s.loss_windows["steady"]
    loss_fn = losses.make_loss_fn(
        s.observer,
        duration=s.duration,
        dt=s.dt,
        spec=losses.loss_spec("angle", steady_start=ss, steady_end=se),
        hold=s.hold,
        init_params=s.init_params,
    )

    def obj(th, keys):
        return loss_fn(s.scenario, bound.constrain(th), keys)

    vg = jax.jit(jax.value_and_grad(obj, has_aux=True))
    rows, losses = [], []
    t0 = time.perf_counter()
    for k in range(args.runs):
        (loss, _), g = vg(th0, montecarlo.run_keys(0, [k]))
        flat = []
        for f in ("alpha1", "alpha2", "gain_z"):
            v = np.asarray(g[f]).reshape(-1)[np.asarray(bound.masks[f]).reshape(-1)]
            flat.append(v)
        rows.append(np.concatenate(flat))
        losses.append(float(loss))
        print(f"run {k}: loss {float(loss):.4f} deg, {time.perf_counter() - t0:.0f} s", flush=True)
    G = np.stack(rows)
    names = (
        [f"alpha1[{i}] t>={starts[i]:g}" for i in np.nonzero(masks["alpha1"])[0]]
        + [f"alpha2[{i}] t>={starts[i]:g}" for i in np.nonzero(masks["alpha2"])[0]]
        + [f"gain_z chol diag {i}" for i in range(9)]
    )
    mean, std = G.mean(0), G.std(0, ddof=1)
    snr = {b: np.abs(mean) / (std / np.sqrt(b)) for b in (8, 32, 64)}
    print(f"\n{'component':26s} {'mean':>10s} {'std':>10s} {'SNR(8)':>7s} {'SNR(64)':>7s}")
    for i, n in enumerate(names):
        print(f"{n:26s} {mean[i]:10.3g} {std[i]:10.3g} {snr[8][i]:7.2f} {snr[64][i]:7.2f}")
    frac = {b: float(np.mean(v < 1.0)) for b, v in snr.items()}
    print("fraction of components with SNR < 1: " + ", ".join(f"batch {b}: {100 * v:.0f} %" for b, v in frac.items()))
    path = C.write_results(
        "ges-gradient-noise",
        {
            "settings": vars(args),
            "refined_times": REFINED_TIMES,
            "components": names,
            "per_run_loss_deg": losses,
            "mean": mean.tolist(),
            "std": std.tolist(),
            "snr": {str(b): v.tolist() for b, v in snr.items()},
            "fraction_snr_below_1": {str(b): v for b, v in frac.items()},
            "wall_s": time.perf_counter() - t0,
        },
        out_dir=args.out,
        meta=meta,
    )
    print(f"results written to {path}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
