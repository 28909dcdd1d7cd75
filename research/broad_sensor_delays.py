"""How late each BROAD sensor is against the optical truth (issue 18: why the robust AHRS has ``mag_delay``).

For every trial in ``--data-dir``, with the optical attitude R(t) (sensor-to-ENU) as the reference:

* magnetometer: the shift s (samples, -6 ... 6) for which the field seen in the earth frame, R(t_k) m(t_{k+s}),
  has the steadiest heading (least standard deviation) over the motion phase; a late magnetometer makes the field
  turn with the sensor during fast rotations;
* gyroscope: the shift for which the gyro best matches the body rate differentiated from the optical attitude
  (central difference, RMS of the difference).

Writes research/results/broad-sensor-delays-<host>-<UTC>.json and prints one line per trial.

Usage: python research/broad_sensor_delays.py [--data-dir DIR]
"""

from __future__ import annotations

import argparse
import pathlib
import sys

import numpy as np

HERE = pathlib.Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent / "benchmarks"))

import _common as C  # noqa: E402

SHIFTS = range(-6, 7)


def rotmat(q):
    """(N, 3, 3) from (N, 4) (w, x, y, z)."""
    w, x, y, z = q.T
    return np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
            np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
            np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
        ],
        -2,
    )


def trial_delays(tr) -> dict:
    q = tr.quat_true
    ok = np.isfinite(q).all(1) & tr.movement
    r = rotmat(np.nan_to_num(q))
    dt = 1.0 / tr.rate_hz
    mag_std = {}
    for s in SHIFTS:
        m_e = np.einsum("nij,nj->ni", r, np.roll(tr.samples.mag, -s, axis=0))[ok][10:-10]
        head = np.degrees(np.arctan2(m_e[:, 0], m_e[:, 1]))
        mag_std[s] = float(np.std(head - np.median(head)))
    rd = np.einsum("nji,njk->nik", r[:-2], r[2:])  # R_{k-1}^T R_{k+1}
    w = np.stack([rd[:, 2, 1] - rd[:, 1, 2], rd[:, 0, 2] - rd[:, 2, 0], rd[:, 1, 0] - rd[:, 0, 1]], -1) / (4 * dt)
    okw = ok[1:-1] & ok[:-2] & ok[2:]
    gyr_rms = {}
    for s in SHIFTS:
        d = np.roll(tr.samples.gyr, -s, axis=0)[1:-1] - w
        gyr_rms[s] = float(np.sqrt(np.mean(np.sum(d[okw][20:-20] ** 2, 1))))
    mag_best, gyr_best = min(mag_std, key=mag_std.get), min(gyr_rms, key=gyr_rms.get)
    rate = np.degrees(np.linalg.norm(tr.samples.gyr[ok], axis=1))
    return {
        "mag_shift_samples": mag_best,
        "gyr_shift_samples": gyr_best,
        "mag_behind_gyr_ms": 1000 * (mag_best - gyr_best) * dt,
        "mag_heading_std_deg": {"best": mag_std[mag_best], "unshifted": mag_std[0]},
        "gyr_rms_rad_s": {"best": gyr_rms[gyr_best], "unshifted": gyr_rms[0]},
        "rate_rms_deg_s": float(np.sqrt(np.mean(rate**2))),
    }


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data-dir", default=str(C.REPO_ROOT.parent / "shared" / "data" / "broad"))
    ap.add_argument("--out", default=str(HERE / "results"))
    args = ap.parse_args(argv)
    from jaxatt.data import broad

    meta = C.metadata(sys.argv if argv is None else ["broad_sensor_delays.py"] + list(argv))
    rows = {}
    for name in broad.list_trials(args.data_dir):
        d = rows[name] = trial_delays(broad.load(args.data_dir, [name])[0])
        print(
            f"{name:46s} mag {d['mag_shift_samples']:+d}, gyro {d['gyr_shift_samples']:+d} samples: mag "
            f"{d['mag_behind_gyr_ms']:+5.1f} ms behind the gyro; heading std {d['mag_heading_std_deg']['best']:5.2f} "
            f"(unshifted {d['mag_heading_std_deg']['unshifted']:5.2f}) deg; rate RMS {d['rate_rms_deg_s']:4.0f} deg/s"
        )
    lag = np.array([d["mag_behind_gyr_ms"] for d in rows.values()])
    print(f"magnetometer behind the gyro: median {np.median(lag):.1f} ms (min {lag.min():.1f}, max {lag.max():.1f})")
    path = C.write_results(
        "broad-sensor-delays",
        {"settings": vars(args), "trials": rows, "data": broad.ATTRIBUTION},
        out_dir=args.out,
        meta=meta,
    )
    print(f"results written to {path}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
