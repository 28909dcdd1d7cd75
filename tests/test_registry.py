"""The observer registry: every name resolves to the entry its module declares, every entry's defaults pass its own
check, its declared gains are fields of its Params with a usable constraint, it has a docs page, and the gradient of
a loss through a whole recorded run with respect to its tuned gains matches central finite differences."""

from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxatt
from jaxatt import engine, montecarlo, so3
from jaxatt.fitting import parametrize as P
from jaxatt.observers import registry

DOCS = Path(__file__).resolve().parents[1] / "docs" / "observers"


@pytest.mark.parametrize("name", registry.names())
def test_entry_is_declared_by_its_module_and_consistent(name):
    e = registry.get(name)
    assert e.name == name and e.module == registry.INDEX[name]
    assert (DOCS / f"{e.module}.md").is_file(), f"docs/observers/{e.module}.md is missing"
    p = e.default_params(dtype=jnp.float64)
    if e.check is not None:
        e.check(p)
    fields = p._fields
    for g in e.gains:
        assert g.field in fields, (name, g.field)
        assert g.constraint in registry.CONSTRAINTS and g.unit and g.doc
        v = np.asarray(getattr(p, g.field))
        if g.constraint.startswith("spd"):
            assert v.ndim == 2 and v.shape[0] == v.shape[1] and np.all(np.linalg.eigvalsh(v) > 0)
        if g.constraint in ("positive", "schedule"):
            assert np.all(v > 0), (name, g.field)
        if g.constraint == "schedule":
            assert v.shape == (np.asarray(p.switch_times).shape[0] + 1,)
        if g.bounds is not None:
            assert g.bounds[0] <= float(np.min(v)) and float(np.max(v)) <= g.bounds[1], (name, g.field)
    for f in e.setup_fields:
        assert f in fields
    assert e.frame in jaxatt.frames.FRAMES and registry.hold_of(e) in jaxatt.types.HOLDS
    # one hold per observer: the Observer carries its entry's (a runner given the Observer alone uses it)
    assert e.make().hold in (None, registry.hold_of(e))
    if e.recorded:
        assert registry.recorded_observer(e).hold == registry.hold_of(e)
    # the parametrization of the declared gains round-trips the defaults
    bound = P.for_gains(e.gains).bind(p)
    back = bound.constrain(bound.init())
    for f in bound.transforms:
        np.testing.assert_allclose(np.asarray(getattr(back, f)), np.asarray(getattr(p, f)), rtol=1e-10, atol=1e-300)


def test_unknown_names_and_duplicate_registration():
    with pytest.raises(ValueError, match="registered: "):
        registry.get("vqf-maybe")
    e = registry.get("mahony")
    with pytest.raises(ValueError, match="already registered"):
        registry.register(e)
    mine = registry.register(e._replace(name="_test_mine"))
    try:
        assert registry.get("_test_mine") is mine and "_test_mine" in registry.names()
    finally:
        registry._EXTRA.pop("_test_mine")


@pytest.fixture(scope="module")
def short_log():
    scn = jaxatt.api.ahrs_scenario(gyro_noise_std=2e-3, acc_noise_std=0.1, mag_noise_std=0.5)
    samples, truth = montecarlo.simulate_log(scn, duration=2.0, dt=0.01, seed=3)
    return samples, np.asarray(truth.r)


#: Observers whose gradient another test checks already: NLIO-FG through the nlio-case1 study, the Batista
#: observers through their studies (tests/test_tune.py).
CHECKED_ELSEWHERE = ("nlio-fg",)


@pytest.mark.parametrize("name", [n for n in registry.names(recorded=True) if n not in CHECKED_ELSEWHERE])
def test_gradient_through_a_recorded_run_matches_finite_differences(name, short_log):
    """d/d theta of the mean squared angle error over a 2-s run (the observer set up from the first sample, as on
    recorded data) against a central difference along a random direction of the tuned gains."""
    samples, r_true = short_log
    e = registry.get(name)
    obs = registry.recorded_observer(e)
    p0 = e.default_params(dtype=jnp.float64)
    bound = P.for_gains(e.gains).bind(p0)
    run = montecarlo.log_runner(obs)  # the observer's own hold
    rt = jnp.asarray(r_true)

    def loss(theta):
        out = run(bound.constrain(theta), samples, 0.01)
        a = so3.angle_error(rt, engine.estimate_r(out))
        return jnp.mean(jnp.rad2deg(a) ** 2)

    th0 = bound.init()
    vg = jax.jit(jax.value_and_grad(loss))  # one compile: the finite differences reuse its value
    value, g = vg(th0)
    assert np.isfinite(float(value))
    leaves = jax.tree_util.tree_leaves(g)
    assert all(np.all(np.isfinite(np.asarray(x))) for x in leaves)
    rng = np.random.default_rng(0)
    d = jax.tree_util.tree_map(lambda x: jnp.asarray(rng.standard_normal(np.shape(x))), th0)
    d = bound.zero_frozen(d)
    h = 1e-5
    fp = vg(jax.tree_util.tree_map(lambda a, b: a + h * b, th0, d))[0]
    fm = vg(jax.tree_util.tree_map(lambda a, b: a - h * b, th0, d))[0]
    fd = float(fp - fm) / (2 * h)
    ad = sum(float(jnp.vdot(a, b)) for a, b in zip(jax.tree_util.tree_leaves(g), jax.tree_util.tree_leaves(d)))
    assert abs(fd) > 0, name
    assert abs(ad - fd) <= 1e-4 * abs(fd), (name, ad, fd)
