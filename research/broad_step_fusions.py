"""What bounds the robust AHRS on the BROAD batch (issue 19): XLA fusions per time step and time per step.

All trials of ``--data-dir`` padded and vmapped in one scan (float32, as benchmarks/broad.py's speed row), for the
observer as registered and for the same observer with its state packed into one float vector per run (the
engine's carry then has one array instead of ~44: does XLA fuse the step into fewer kernels?). Prints fusions in
the while body (benchmarks/step_profile.py's count), compile time, best-of-``--repeats`` samples/s and us/step.

    python research/broad_step_fusions.py --data-dir ../shared/data/broad
"""

import argparse
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
from step_profile import loop_body_profile  # noqa: E402

from jaxatt import engine  # noqa: E402
from jaxatt.data import broad  # noqa: E402
from jaxatt.observers import registry  # noqa: E402
from jaxatt.types import ImuSample, Observer  # noqa: E402


def packed(obs: Observer, params, sample0) -> Observer:
    """``obs`` with every float32 state leaf raveled into one vector (other leaves kept beside it)."""
    shapes = jax.eval_shape(lambda: engine.cast_floats(obs.init(params, sample0), jnp.float32))
    leaves, tree = jax.tree_util.tree_flatten(shapes)
    floats = [i for i, leaf in enumerate(leaves) if leaf.dtype == jnp.float32]

    def pack(state):
        ls = jax.tree_util.tree_leaves(state)
        return jnp.concatenate([jnp.ravel(ls[i]) for i in floats]), tuple(
            ls[i] for i in range(len(ls)) if i not in floats
        )

    def unpack(ps):
        vec, rest = ps
        out, offset, others = [], 0, iter(rest)
        for i, leaf in enumerate(leaves):
            if i in floats:
                size = int(np.prod(leaf.shape))
                out.append(vec[offset : offset + size].reshape(leaf.shape))
                offset += size
            else:
                out.append(next(others))
        return jax.tree_util.tree_unflatten(tree, out)

    def step(p, ps, u, dt):
        st, o = obs.step(p, unpack(ps), u, dt)
        return pack(st), o

    return Observer(
        lambda p, s: pack(obs.init(p, s)), step, "packed", lambda p, ps: obs.output(p, unpack(ps)), obs.time_reversed
    )


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data-dir", default=str(Path(__file__).resolve().parents[2] / "shared" / "data" / "broad"))
    ap.add_argument("--repeats", type=int, default=5)
    args = ap.parse_args()
    trials = broad.load(args.data_dir)
    padded = broad.pad_trials(trials)
    n_real = int(np.asarray(padded.lengths).sum())
    n_steps = int(padded.samples.t.shape[1]) - 1
    entry = registry.get("robust")
    obs = registry.recorded_observer(entry)
    p = entry.default_params(dtype=jnp.float32)
    zero = jnp.zeros(3, jnp.float32)
    item = jax.device_put({**broad.batch_item(padded, "float32"), "truth": None})
    print(f"{len(trials)} trials, {n_real} samples, {n_steps} steps (the longest trial)")
    for name, ob in (("as registered", obs), ("state packed", packed(obs, p, ImuSample(zero[0], zero, zero, zero)))):
        fn = engine.compiled(
            ob,
            engine.Recorded(n_steps, False),
            engine.records_of(lambda t, truth, o: o.q, 1),
            hold=registry.hold_of(entry),
            obs_dtype=np.dtype("float32"),
        )
        t0 = time.perf_counter()
        compiled = fn.lower(None, p, item).compile()
        compile_s = time.perf_counter() - t0
        fusions = loop_body_profile(compiled.as_text())["fusions"]
        jax.block_until_ready(compiled(None, p, item))
        best = np.inf
        for _ in range(args.repeats):
            t0 = time.perf_counter()
            jax.block_until_ready(compiled(None, p, item))
            best = min(best, time.perf_counter() - t0)
        print(
            f"{name:14s} fusions/step {fusions:3d}  compile {compile_s:4.1f} s  {n_real / best:.3g} samples/s  "
            f"{1e6 * best / n_steps:.2f} us/step"
        )


if __name__ == "__main__":
    main()
