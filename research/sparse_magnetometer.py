"""A magnetometer slower than the gyro: RMS angle error (deg) of each recorded-data filter on one simulated 60-s
log (``jaxatt.api.ahrs_scenario()``, 100 Hz, seed 3) with every n-th magnetometer reading kept and NaN between.

    python research/sparse_magnetometer.py

Prints, per n, each filter's RMS over the whole log and over its second half. Findings: research/README.md.
"""

import warnings

import jax
import jax.numpy as jnp
import numpy as np

jax.config.update("jax_enable_x64", True)

import jaxatt  # noqa: E402
from jaxatt import montecarlo, so3  # noqa: E402

FILTERS = ("robust", "mahony", "madgwick", "vqf", "mekf")


def main() -> None:
    warnings.simplefilter("ignore")
    scn = jaxatt.api.ahrs_scenario()
    samples, truth = montecarlo.simulate_log(scn, duration=60.0, dt=0.01, seed=3)
    gyr, acc, mag = (np.asarray(x) for x in (samples.gyr, samples.acc, samples.mag))
    r_true = jnp.asarray(truth.r)
    half = len(gyr) // 2
    for every in (1, 2, 4, 10):
        m = np.where((np.arange(len(mag)) % every == 0)[:, None], mag, np.nan)
        row = []
        for name in FILTERS:
            est = jaxatt.filter(name, gyr, acc, m, dt=0.01, frame="ENU")
            a = np.rad2deg(np.asarray(so3.angle_error(r_true, jnp.asarray(est.rotation))))
            row.append(f"{name} {np.sqrt(np.mean(a**2)):.2f} / {np.sqrt(np.mean(a[half:] ** 2)):.2f}")
        print(f"1 reading in {every:2d}: " + " | ".join(row), flush=True)


if __name__ == "__main__":
    main()
