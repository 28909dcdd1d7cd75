"""Synthetic recordings with known body-to-ENU truth (``SCENARIOS``: name -> () -> dict of t, gyr, acc, mag, dt,
q), for probing jaxatt's start / end behaviour (research/start_in_motion_penalty.py). Needs scipy."""

import numpy as np
from scipy.spatial.transform import Rotation as Rot

G = 9.81
FIELD = 50.0  # uT
DIP = np.deg2rad(60.0)
M_NAV = FIELD * np.array([0.0, np.cos(DIP), -np.sin(DIP)])  # ENU: north horizontal, down component
BIAS = np.array([0.006, -0.005, 0.004])  # rad/s (~0.34 deg/s)


def Rz(a):
    return Rot.from_euler("z", a)


def finish(R, a_lin, dt, seed=0, d_mag=None, noise=1.0, bias=BIAS):
    """R: Rotation of length T (body->ENU); a_lin (T,3) nav linear acc; returns dict."""
    rng = np.random.default_rng(seed)
    T = len(R)
    rel = R[:-1].inv() * R[1:]
    w = rel.as_rotvec() / dt
    gyr = np.vstack([w[:1], w])  # gyr[k]: rate over (t_{k-1}, t_k]  ("next" hold)
    acc = R.inv().apply(np.array([0, 0, G]) + a_lin)
    m = np.broadcast_to(M_NAV, (T, 3)).copy()
    if d_mag is not None:
        m = m + d_mag
    mag = R.inv().apply(m)
    gyr = gyr + bias + noise * rng.normal(0, 0.004, (T, 3))
    acc = acc + noise * rng.normal(0, 0.05, (T, 3))
    mag = mag + noise * rng.normal(0, 0.4, (T, 3))
    q = R.as_quat()[:, [3, 0, 1, 2]]
    q = q * np.sign(q[:, :1] + 1e-12)
    return dict(gyr=gyr.astype(np.float32), acc=acc.astype(np.float32), mag=mag.astype(np.float32), q=q, dt=dt)


def t_axis(dur, rate):
    return np.arange(int(round(dur * rate))) / rate


MOUNT = Rot.from_euler("xyz", [25, -15, 0], degrees=True)


def walk(dur=40.0, rate=100.0, seed=1):
    """Picked up (lifted and tilted over the first second) and walked with; turns; ends mid-stride."""
    t = t_axis(dur, rate)
    heading = (
        np.deg2rad(30)
        + np.deg2rad(90) * (np.clip((t - 12) / 2, 0, 1) - np.clip((t - 25) / 3, 0, 1))
        + np.deg2rad(45) * np.clip((t - 33) / 2, 0, 1)
    )
    pick = np.clip(t / 1.0, 0, 1)
    pitch = np.deg2rad(-40) * (1 - pick) + np.deg2rad(35) + np.deg2rad(3) * np.sin(2 * np.pi * 2 * t + 0.3)
    roll = np.deg2rad(4) * np.sin(2 * np.pi * 1 * t)
    R = Rot.from_euler("z", heading[:, None]) * Rot.from_euler("x", pitch[:, None]) * Rot.from_euler("y", roll[:, None])
    fwd = np.stack([-np.sin(heading), np.cos(heading), 0 * t], -1)
    lat = np.stack([np.cos(heading), np.sin(heading), 0 * t], -1)
    a = (
        2.5 * np.sin(2 * np.pi * 2 * t)[:, None] * np.array([0, 0, 1.0])
        + 1.5 * np.sin(2 * np.pi * 2 * t + 1)[:, None] * fwd
        + 0.8 * np.sin(2 * np.pi * t)[:, None] * lat
    )
    a[:, 2] += np.where(t < 1, 3.0 * np.sin(np.pi * t), 0.0)  # the lift
    return finish(R, a, 1 / rate, seed)


def car(dur=60.0, rate=100.0, seed=2):
    """Phone in a car holder; starts driving at 12 m/s; turns (centripetal), braking; ends braking."""
    t = t_axis(dur, rate)
    dt = 1 / rate
    yaw_rate = np.zeros_like(t)
    for t0, t1, r in ((5, 10, 0.25), (20, 23, -0.4), (35, 42, 0.2), (50, 53, -0.3)):
        yaw_rate += np.where((t >= t0) & (t < t1), r, 0.0)
    long = np.zeros_like(t)
    for t0, t1, a in ((0, 0, 0), (14, 17, -3.0), (17, 22, 2.0), (28, 31, -3.0), (31, 34, 2.5), (56, 60.1, -2.5)):
        long += np.where((t >= t0) & (t < t1), a, 0.0)
    v = 12.0 + np.cumsum(long) * dt
    heading = np.deg2rad(70) + np.cumsum(yaw_rate) * dt
    rng = np.random.default_rng(seed + 100)
    vib = rng.normal(0, 0.3, (len(t), 3))
    R = Rot.from_euler("z", heading[:, None]) * MOUNT
    fwd = np.stack([-np.sin(heading), np.cos(heading), 0 * t], -1)
    left = np.stack([-np.cos(heading), -np.sin(heading), 0 * t], -1)
    a = long[:, None] * fwd + (v * yaw_rate)[:, None] * left + vib
    return finish(R, a, dt, seed)


def shake_cut(dur=30.0, rate=100.0, seed=3):
    """Handled gently, then fast shaking over the last 5 s; the recording is cut while shaking."""
    t = t_axis(dur, rate)
    s = np.clip((t - (dur - 5)) / 0.3, 0, 1)
    ang = 0.15 * s * np.sin(2 * np.pi * 5 * t)
    base = Rot.from_euler(
        "zxy", np.stack([np.deg2rad(20) + 0.3 * np.sin(0.2 * t), 0.2 * np.sin(0.3 * t), 0.15 * np.cos(0.25 * t)], -1)
    )
    R = base * Rot.from_euler("x", ang[:, None])
    a = (12.0 * s * np.sin(2 * np.pi * 5 * t + 0.5))[:, None] * R.apply(np.array([0, 1.0, 0]))
    return finish(R, a, 1 / rate, seed)


def gentle(dur=30.0, rate=100.0, seed=4):
    """Handled gently throughout (turning ~20-40 deg/s, small accelerations), starting and ending in motion."""
    t = t_axis(dur, rate)
    R = Rot.from_euler(
        "zxy",
        np.stack([np.deg2rad(-50) + 1.2 * np.sin(0.35 * t), 0.4 * np.sin(0.5 * t + 0.4), 0.3 * np.cos(0.45 * t)], -1),
    )
    a = 0.6 * np.stack([np.sin(1.3 * t), np.cos(1.1 * t), np.sin(0.9 * t + 1)], -1)
    return finish(R, a, 1 / rate, seed)


def magnet_start(dur=40.0, rate=100.0, seed=5):
    """Starts next to a magnet (field disturbed by 40 uT, 60 deg off) which goes away over t = 1.5 ... 3 s."""
    t = t_axis(dur, rate)
    D = np.array([30.0, -20.0, 20.0])
    fade = np.where(t < 1.5, 1.0, np.exp(-(t - 1.5) / 0.5))
    R = Rot.from_euler(
        "zxy",
        np.stack([np.deg2rad(-50) + 1.2 * np.sin(0.35 * t), 0.4 * np.sin(0.5 * t + 0.4), 0.3 * np.cos(0.45 * t)], -1),
    )
    a = 0.6 * np.stack([np.sin(1.3 * t), np.cos(1.1 * t), np.sin(0.9 * t + 1)], -1)
    return finish(R, a, 1 / rate, seed, d_mag=fade[:, None] * D)


def magnet_end(dur=40.0, rate=100.0, seed=6):
    """Gentle handling; a magnet approaches over the last 3 s and is there at the end."""
    t = t_axis(dur, rate)
    D = np.array([30.0, -20.0, 20.0])
    fade = np.exp(np.minimum(t - (dur - 1.5), 0) / 0.5)
    R = Rot.from_euler(
        "zxy",
        np.stack([np.deg2rad(-50) + 1.2 * np.sin(0.35 * t), 0.4 * np.sin(0.5 * t + 0.4), 0.3 * np.cos(0.45 * t)], -1),
    )
    a = 0.6 * np.stack([np.sin(1.3 * t), np.cos(1.1 * t), np.sin(0.9 * t + 1)], -1)
    return finish(R, a, 1 / rate, seed, d_mag=fade[:, None] * D)


def missing_mag(which, dur=30.0, rate=100.0, seed=7):
    d = gentle(dur, rate, seed)
    n = int(rate)
    if which in ("first", "both"):
        d["mag"][:n] = np.nan
    if which in ("last", "both"):
        d["mag"][-n:] = np.nan
    return d


def rest(dur=30.0, rate=100.0, seed=8):
    t = t_axis(dur, rate)
    R = Rot.from_euler("zxy", [[np.deg2rad(130), 0.3, -0.5]] * len(t))
    return finish(R, np.zeros((len(t), 3)), 1 / rate, seed)


def rotate_only(dur=30.0, rate=100.0, seed=9):
    """Only rotates (about the sensor's centre, no linear acceleration), ~60-120 deg/s, from start to end."""
    t = t_axis(dur, rate)
    R = Rot.from_euler(
        "zxy", np.stack([1.5 * t + 0.5 * np.sin(0.7 * t), 0.8 * np.sin(0.9 * t + 0.3), 0.6 * np.sin(1.1 * t + 1.0)], -1)
    )
    return finish(R, np.zeros((len(t), 3)), 1 / rate, seed)


SCENARIOS = {
    "walk": walk,
    "car": car,
    "shake_cut": shake_cut,
    "gentle": gentle,
    "magnet_start": magnet_start,
    "magnet_end": magnet_end,
    "mag_nan_first": lambda: missing_mag("first"),
    "mag_nan_last": lambda: missing_mag("last"),
    "mag_nan_both": lambda: missing_mag("both"),
    "rest": rest,
    "rotate_only": rotate_only,
}


def angle_deg(q_est, q_true):
    d = np.abs(np.sum(np.asarray(q_est, float) * q_true, -1))
    return np.rad2deg(2 * np.arccos(np.clip(d, 0, 1)))


def heading_incl_deg(q_est, q_true):
    """Heading and inclination errors (BROAD style decomposition) of the error rotation in the nav frame."""
    qe = Rot.from_quat(np.asarray(q_est, float)[:, [1, 2, 3, 0]])
    qt = Rot.from_quat(q_true[:, [1, 2, 3, 0]])
    err = (qe * qt.inv()).as_quat()  # nav-frame error, xyzw
    w, z = err[:, 3], err[:, 2]
    head = 2 * np.arctan2(np.abs(z), np.abs(w))
    incl = 2 * np.arccos(np.clip(np.sqrt(w**2 + z**2), 0, 1))
    return np.rad2deg(head), np.rad2deg(incl)
