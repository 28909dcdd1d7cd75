"""The smoother's start-in-motion rule (``jaxatt.smoothing._start_in_motion``, MOVING_START_S, SETTLE_S) on
simulated recordings that start or end in motion (research/motion_recordings.py: a walk, a car, gentle
handling, a recording cut mid-shake, a magnet near the end, a sensor that only turns, one at rest), for the
robust AHRS, VQF and the MEKF: whole-recording RMS error (deg) of the causal filter and of the offline estimate
with and without the rule, and the worst second of offline minus causal. Needs scipy.

    python research/start_in_motion_penalty.py
"""

import os
import sys
import warnings

import jax.numpy as jnp
import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import motion_recordings as sim  # noqa: E402

import jaxatt  # noqa: E402
from jaxatt import smoothing  # noqa: E402


def per_second(err, rate):
    n = int(rate)
    return np.array([np.sqrt(np.mean(err[i * n : (i + 1) * n] ** 2)) for i in range(len(err) // n)])


def main():
    warnings.simplefilter("ignore")
    rule = smoothing._start_in_motion
    for name in ("car", "walk", "gentle", "shake_cut", "magnet_end", "rotate_only", "rest"):
        d = sim.SCENARIOS[name]()
        rate = 1 / d["dt"]
        for obs in ("robust", "vqf", "mekf"):
            res = []
            for on in (True, False):
                smoothing._start_in_motion = rule if on else (lambda s, lengths: jnp.zeros((s.t.shape[0], 2), bool))
                smoothing._compiled.cache_clear()
                est = jaxatt.filter(obs, d["gyr"], d["acc"], d["mag"], dt=d["dt"], offline=True)
                e, ec = sim.angle_deg(est.quat, d["q"]), sim.angle_deg(est.outputs["q_forward"], d["q"])
                worst = np.max(per_second(e, rate) - per_second(ec, rate))
                res.append((np.sqrt(np.mean(e**2)), worst, np.sqrt(np.mean(ec**2))))
            print(
                f"{name:11s} {obs:7s} causal {res[0][2]:6.2f} | rule: offline {res[0][0]:6.2f} worst-s "
                f"{res[0][1]:+6.2f} | none: offline {res[1][0]:6.2f} worst-s {res[1][1]:+6.2f}",
                flush=True,
            )
    smoothing._start_in_motion = rule


if __name__ == "__main__":
    main()
