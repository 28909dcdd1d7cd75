"""The plain JAX Monte Carlos of benchmarks/plain_jax.py (issue 19's reference for the speed of jaxatt's fused
Monte Carlo) compute what jaxatt computes: fed the noise stream (and, for nlio-case1, the initial estimate) that
jaxatt's engine draws for the same run keys, every estimate of a short run and the accumulated angle errors agree
to rounding; for batista-ges also with benchmarks/numpy_reference.py fed numpy's noise. Plus a tiny run of
benchmarks/plain_vs_fused.py."""

import json
import pathlib
import sys

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402

from jaxatt import engine, montecarlo, studies  # noqa: E402
from jaxatt.sim import imu  # noqa: E402

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1] / "benchmarks"))
import numpy_reference as npref  # noqa: E402
import plain_jax  # noqa: E402
import plain_vs_fused  # noqa: E402

N_STEPS = 200
RUNS = 2
#: Output fields compared besides the SO(3) estimate r (plain record name -> jaxatt Out field).
FIELDS = {
    "batista-ges": ("x1", "x2", "r_hat"),
    "batista-so3": ("m_hat", "v_hat"),
    "nlio-case1": ("r_hat", "bias"),
    "complementary": (),
}
#: XLA's backend optimisation off: the same programs compile ~35 % faster (both sides; the comparisons are at
#: rounding level, which the optimisation level does not exceed).
FAST_COMPILE = {"xla_backend_optimization_level": 0}


def _call(jitted, *args):
    """``jitted(*args)``, compiled with :data:`FAST_COMPILE`."""
    return jitted.lower(*args).compile(FAST_COMPILE)(*args)


def _jaxatt_noise(key, n_steps, channels):
    """The standard normals of samples 0 ... n_steps of jaxatt's simulated run of ``key`` (jaxatt.sim.imu)."""
    rows = [imu.initial_noise(key, jnp.float64, channels)[None]]
    rows += [imu.noise_block(key, b, jnp.float64, channels) for b in range(-(-n_steps // imu.NOISE_BLOCK))]
    return jnp.concatenate(rows)[: n_steps + 1]


def _jaxatt_run(name, keys):
    """jaxatt's fused Monte Carlo of the study (its tuned observer, the engine's Simulated source), every estimate
    and the true attitude recorded."""
    s = studies.get(name).setup(duration=N_STEPS * 0.01)
    fields = FIELDS[name]

    def pick(t, truth, out):
        return {"r": out.r, "r_true": truth.r, **{f: getattr(out, f) for f in fields}}

    source = engine.Simulated(N_STEPS, s.dt, jnp.float64, s.init_params)
    fn = engine.compiled(s.observer, source, engine.records_of(pick), None, hold=s.hold, obs_dtype=jnp.float64)
    return s, _call(fn, s.scenario, s.params, keys).records


def _angles_deg(r_true, r):
    """Rotation angle of R_true^T R (deg), numpy."""
    c = 0.5 * (np.trace(np.swapaxes(r_true, -1, -2) @ r, axis1=-2, axis2=-1) - 1.0)
    return np.degrees(np.arccos(np.clip(c, -1.0, 1.0)))


def _check(name, plain_out, records, runs):
    for f in ("r", "r_true") + FIELDS[name]:
        a, b = np.asarray(plain_out[f][:runs]), np.asarray(records[f])
        assert a.shape == b.shape, (f, a.shape, b.shape)
        err = np.max(np.abs(a - b)) / np.max(np.abs(b))
        assert err <= 1e-10, f"{name} {f}: max |plain - jaxatt| / max |jaxatt| = {err:.3e}"
    ang = _angles_deg(np.asarray(records["r_true"]), np.asarray(records["r"]))[:, 1:]  # estimates 1 ... N_STEPS
    want = {"mean_angle_error_deg": ang.mean(1), "max_angle_error_deg": ang.max(1), "final_angle_error_deg": ang[:, -1]}
    for k, v in want.items():
        np.testing.assert_allclose(np.asarray(plain_out[k][:runs]), v, rtol=1e-9, atol=1e-9)


def test_batista_ges_matches_jaxatt_and_numpy_reference():
    name = "batista-ges"
    keys = montecarlo.run_keys(0, np.arange(RUNS))
    s, records = _jaxatt_run(name, keys)
    np_noise = np.random.default_rng(7).standard_normal((N_STEPS + 1, 6))  # what simulate_and_observe draws
    noise = jnp.concatenate([jnp.stack([_jaxatt_noise(k, N_STEPS, 6) for k in keys]), jnp.asarray(np_noise)[None]])
    fn = plain_jax.batista_ges(N_STEPS, s.dt, noise_at=lambda it, k: it[k], record=True)
    out = _call(fn, noise)
    _check(name, out, records, RUNS)
    # numpy reference (fused loop, numpy's noise) on the last run
    cfg = s.config
    p = npref.NpParams.from_any(s.params)
    _, _, rec = npref.simulate_and_observe(
        N_STEPS,
        s.dt,
        p,
        rate=npref.batista_rates(),
        ref_nav=np.asarray(cfg.reference_nT, float),
        earth_rate_nav=np.asarray(plain_jax.earth_rate_ned(cfg.latitude_deg)),
        gyro_arw=np.deg2rad(cfg.gyro_arw_deg_h_rthz) / 3600.0,
        mag_noise=cfg.mag_noise_nT,
        rng=np.random.default_rng(7),
        record=True,
    )
    for f in ("r", "x1", "x2", "r_hat"):  # estimates 1 ... N_STEPS
        b = np.array([o[f] for _, _, o in rec])
        err = np.max(np.abs(np.asarray(out[f][RUNS, 1:]) - b)) / np.max(np.abs(b))
        assert err <= 1e-9, f"{f}: max |plain - numpy| / max |numpy| = {err:.3e}"
    angles = _angles_deg(np.array([r for _, r, _ in rec]), np.array([o["r"] for _, _, o in rec]))
    np.testing.assert_allclose(float(out["mean_angle_error_deg"][RUNS]), np.mean(angles), rtol=1e-9)
    # the plain constants are the paper's, written independently of jaxatt's params
    c = plain_jax.ges_constants(s.dt)
    np.testing.assert_allclose(c.g, np.asarray(s.params.gain_z), rtol=1e-12)
    np.testing.assert_allclose(c.w, np.asarray(s.params.earth_rate_nav), rtol=1e-12)


@pytest.mark.parametrize("name", ["batista-so3", "nlio-case1", "complementary"])
def test_plain_matches_jaxatt(name):
    keys = montecarlo.run_keys(3, np.arange(RUNS))
    s, records = _jaxatt_run(name, keys)
    channels = s.scenario.n_channels  # the plain version reads the channels it needs (nlio: 9 of 15)
    items = {"noise": jnp.stack([_jaxatt_noise(k, N_STEPS, channels) for k in keys])}
    kw = {}
    if name == "nlio-case1":  # jaxatt's per-run initial estimate: ZYX angles drawn from the run's key
        items["angles"] = jax.vmap(
            lambda k: jax.random.uniform(
                jax.random.fold_in(k, engine.INIT_PARAMS_BLOCK), (3,), jnp.float64, -np.pi, np.pi
            )
        )(keys)
        kw["init_at"] = lambda it: it["angles"]
    fn = plain_jax.STUDIES[name](N_STEPS, s.dt, noise_at=lambda it, k: it["noise"][k], record=True, **kw)
    out = _call(fn, items)
    _check(name, out, records, RUNS)
    assert np.asarray(out["r"]).shape == (RUNS, N_STEPS + 1, 3, 3)


def test_plain_vs_fused_tiny(tmp_path):
    """The benchmark end to end on the cheapest study (compiles two small programs)."""
    assert (
        plain_vs_fused.main(
            ["--studies", "complementary", "--batches", "2", "--steps", "20", "--repeats", "1", "--out", str(tmp_path)]
        )
        == 0
    )
    (path,) = tmp_path.glob("plain_vs_fused-*.json")
    data = json.loads(path.read_text())
    (row,) = data["rows"]
    assert row["study"] == "complementary" and row["batch"] == 2 and row["steps"] == 20
    assert row["finite"] and row["ratio"] > 0 and row["ratio_angle_only"] > 0 and row["fused_compile_s"] > 0
    assert data["meta"]["versions"]["jax"] and data["meta"]["machine"]["loadavg_1_5_15"] is not None
    # equal in distribution: noise-free scenario, so the angle errors are identical
    for kind in ("fused", "fused_angle"):
        np.testing.assert_allclose(row[f"{kind}_mean_angle_error_deg"], row["plain_mean_angle_error_deg"], rtol=1e-9)
