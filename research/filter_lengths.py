"""How long a script takes to filter many recordings of different lengths with ``jaxatt.filter`` (each new scan
length is a new compiled program; ``jaxatt.api.LENGTHS_PER_OCTAVE`` pads recordings to a few lengths per octave).

Run: ``python research/filter_lengths.py [--per-octave N]`` (N = 0: no padding). Prints the wall time of filtering
10 simulated recordings of 3,000-6,000 samples (robust AHRS, float32, one process, compile included).
"""

from __future__ import annotations

import argparse
import time

import numpy as np

import jaxatt
from jaxatt import api, montecarlo


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--per-octave", type=int, default=api.LENGTHS_PER_OCTAVE, help="0: no padding")
    args = ap.parse_args()
    if args.per_octave:
        api.LENGTHS_PER_OCTAVE = args.per_octave
    else:
        api._run_length = lambda n: n  # type: ignore[assignment]
    samples, _ = montecarlo.simulate_log(jaxatt.api.ahrs_scenario(), duration=60.0, dt=0.01, seed=1)
    g, a, m = (np.asarray(x, np.float32) for x in (samples.gyr, samples.acc, samples.mag))
    lengths = np.random.default_rng(0).integers(3000, 6000, size=10)
    t0 = time.perf_counter()
    for n in lengths:
        jaxatt.filter("robust", g[:n], a[:n], m[:n], dt=0.01)
    print(
        f"lengths per octave {args.per_octave or 'none'}: 10 recordings of 3,000-6,000 samples, robust float32: "
        f"{time.perf_counter() - t0:.1f} s"
    )


if __name__ == "__main__":
    main()
