"""benchmarks/broad.py: its per-trial figure shows the numbers of the results file, and its jaxatt rows agree with
independent computations on two short BROAD trials (one per fold of the 2-fold split, one per group): the
out-of-fold rows with ``jaxatt.broad_score`` of each trial alone with the gains of the fold it is NOT in, the
default Madgwick row with the ahrs package's Madgwick, the default Mahony row with ``jaxatt.filter`` scored by
numpy.

BROAD data (Laidig et al., Data 6(7), 2021, CC BY 4.0) in ../shared/data/broad: the tests that need it skip
without it, except under CI=true, where they fail.
"""

import json
import math
import pathlib
import sys

import jax
import numpy as np
import pytest
from broad_data import DATA, need_data

REPO = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "benchmarks"))

import broad as bench  # noqa: E402  (benchmarks/broad.py)

N_SAMPLES = 15000  # the first ~52 s of each trial (its movement starts after ~34-45 s)


def _payload():
    """A small results payload: 3 rows (one missing a trial), 2 undisturbed and 2 disturbed trials."""
    names = ["24_disturbed_tapping_A", "01_undisturbed_slow_rotation_A", "32_disturbed_attached_magnet_1cm"]
    names.append("02_undisturbed_slow_rotation_B")
    rng = np.random.default_rng(3)
    results = {}
    for row in ("jaxatt-vqf", "jaxatt-vqf-oof", "imufusion"):
        kept = names if row != "imufusion" else names[1:]
        trials = {
            n: {"total_rmse_deg": float(rng.uniform(0.3, 30.0)), "group": "disturbed" if "_dis" in n else "undisturbed"}
            for n in kept
        }
        groups = {
            g: {"total_rmse_deg": float(np.mean([v["total_rmse_deg"] for v in trials.values() if v["group"] == g]))}
            for g in ("undisturbed", "disturbed")
        }
        results[row] = {"trials": trials, "groups": groups, "wall_s": 1.0, "samples_per_s": None}
    return {"benchmark": "broad", "results": results}


def test_figure_shows_the_json_numbers(tmp_path):
    body = _payload()
    path = tmp_path / "broad-test.json"
    path.write_text(json.dumps(body))
    png = tmp_path / "fig.png"
    assert bench.main(["--figure-from", str(path), "--figure-out", str(png)]) == 0
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert bench.figure_from(path) == path.with_suffix(".png") and path.with_suffix(".png").stat().st_size > 0

    ax = bench.draw_figure(body).axes[0]
    ticks = {lab.get_text(): x for x, lab in zip(ax.get_xticks(), ax.get_xticklabels())}
    series = [ln for ln in ax.get_lines() if ln.get_gid() is not None]
    assert sorted(ln.get_gid() for ln in series) == sorted(body["results"])  # one series per row
    xs_u = [ticks["01 slow_rotation_A"], ticks["02 slow_rotation_B"]]
    xs_d = [ticks["24 tapping_A"], ticks["32 attached_magnet_1cm"]]
    assert max(xs_u) < min(xs_d)  # grouped: undisturbed, then disturbed
    for ln in series:
        row = body["results"][ln.get_gid()]
        x, y = np.asarray(ln.get_xdata(), float), np.asarray(ln.get_ydata(), float)
        for n in body["results"]["jaxatt-vqf"]["trials"]:
            label = n.split("_", 2)[0] + " " + n.split("_", 2)[2]
            (i,) = np.flatnonzero(x == ticks[label])
            want = row["trials"].get(n, {}).get("total_rmse_deg", math.nan)
            assert y[i] == want or (math.isnan(want) and math.isnan(y[i]))
        g = row["groups"]
        assert ln.get_label().endswith(
            f"{g['undisturbed']['total_rmse_deg']:.2f} / {g['disturbed']['total_rmse_deg']:.2f}"
        )
        assert np.isnan(y).sum() == 1 + (ln.get_gid() == "imufusion")  # the gap between the groups (+ missing)


@pytest.fixture(scope="module")
def short_trials():
    """Trials 01 (undisturbed, fold 1) and 26 (disturbed, fold 2), their first N_SAMPLES samples."""
    need_data()
    jax.config.update("jax_enable_x64", True)
    from jaxatt.data import broad

    return [
        tr._replace(
            samples=jax.tree_util.tree_map(lambda a: a[:N_SAMPLES], tr.samples),
            quat_true=tr.quat_true[:N_SAMPLES],
            movement=tr.movement[:N_SAMPLES],
        )
        for tr in broad.load(DATA, ["01", "26"])
    ]


@pytest.mark.parametrize("name", ["madgwick", "mahony", "vqf"])
def test_out_of_fold_row_uses_the_other_folds_gains(short_trials, name):
    import jaxatt
    from jaxatt.data import broad

    per, info, _, warm = bench.run_jaxatt_oof(DATA, short_trials, name, gains_dir=bench.OOF_GAINS_DIR)
    assert warm > 0
    names = broad.resolve_trials(DATA)
    folds = broad.stratified_folds(names, broad.load_trial_info(DATA))
    for tr in short_trials:
        (own,) = [k for k, f in enumerate(folds, start=1) if tr.name in f]
        assert [f["fold"] for f in info if tr.name in f["test"]] == [3 - own]
        other = jaxatt.broad_score(name, str(bench.OOF_GAINS_DIR / f"{name}_broad_fold{3 - own}.json"), [tr])
        same = jaxatt.broad_score(name, str(bench.OOF_GAINS_DIR / f"{name}_broad_fold{own}.json"), [tr])
        for m in broad.METRICS:
            assert per[tr.name][m] == pytest.approx(getattr(other.trials[tr.name], m), rel=1e-9, abs=1e-12)
        assert abs(per[tr.name]["total_rmse_deg"] - same.trials[tr.name].total_rmse_deg) > 1e-6


def test_default_madgwick_row_matches_ahrs(short_trials):
    from jaxatt.data import broad
    from jaxatt.observers import registry

    per, _, _ = bench.run_registered(short_trials, "madgwick")
    beta = float(registry.get("madgwick").params().beta)
    for tr in short_trials:
        q, _ = bench.run_ahrs(tr, "madgwick", beta=beta)
        ref = broad.broad_errors(q, tr.quat_true, tr.movement)
        for m in broad.METRICS:
            assert per[tr.name][m] == pytest.approx(ref[m], rel=1e-8)


def test_default_mahony_row_matches_the_front_door(short_trials):
    import jaxatt
    from jaxatt.data import broad

    per, _, _ = bench.run_registered(short_trials, "mahony")
    for tr in short_trials:
        est = jaxatt.filter("mahony", tr.samples.gyr, tr.samples.acc, tr.samples.mag, dt=1.0 / tr.rate_hz)
        ref = broad.broad_errors(np.asarray(est.quat, np.float64), tr.quat_true, tr.movement)
        for m in broad.METRICS:
            assert per[tr.name][m] == pytest.approx(ref[m], rel=1e-9)
