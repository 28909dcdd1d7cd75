"""Constrained parametrizations (jaxatt.fitting.parametrize) and the gains file (jaxatt.fitting.gainsfile): every theta
gives a valid gain, round trips are exact, masks freeze exactly, gradients are finite. No simulation: fast."""

import json
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxatt import schedule
from jaxatt.fitting import gainsfile
from jaxatt.fitting import parametrize as P
from jaxatt.observers import registry
from jaxatt.studies import batista_ges, batista_so3


def for_observer(name, **kw):
    """The parametrization of a registered observer's declared gains."""
    return P.for_gains(registry.get(name).gains, **kw)


def ges_params():
    return batista_ges.params(batista_ges.Config(), dtype=jnp.float64)


def so3_params():
    return batista_so3.params(batista_so3.Config(), dtype=jnp.float64)


def random_spd(n, rng, cond=1e3):
    q, _ = np.linalg.qr(rng.normal(size=(n, n)))
    return q @ np.diag(np.geomspace(1.0, 1.0 / cond, n)) @ q.T


@pytest.mark.parametrize("method", ["log", "softplus"])
def test_positive_round_trip_and_range(method):
    x = np.array([1e-23, 3e-9, 0.5, 7.0, 2e4])
    tr = P.Positive(method).bind(x)
    u = tr.inverse(x)
    np.testing.assert_allclose(np.asarray(tr.forward(jnp.asarray(u))), x, rtol=1e-12)
    y = np.asarray(jax.vmap(tr.forward)(jnp.linspace(-30.0, 30.0, 101)[:, None] + jnp.asarray(u)))
    assert np.all(y > 0) and np.all(np.isfinite(y))
    g = jax.grad(lambda v: jnp.sum(tr.forward(v)))(jnp.asarray(u))
    assert np.all(np.isfinite(np.asarray(g))) and np.all(np.asarray(g) > 0)
    with pytest.raises(ValueError):
        tr.inverse(np.array([1.0, -1.0, 1.0, 1.0, 1.0]))


def test_spd_round_trip_and_every_theta_is_spd():
    rng = np.random.default_rng(0)
    g0 = random_spd(9, rng)
    tr = P.SPD().bind(g0)
    u = tr.inverse(g0)
    assert u.shape == (45,)
    np.testing.assert_allclose(np.asarray(tr.forward(jnp.asarray(u))), g0, rtol=1e-10, atol=1e-14)
    for _ in range(5):
        g = np.asarray(tr.forward(jnp.asarray(rng.normal(scale=1.0, size=45))))
        np.testing.assert_allclose(g, g.T, rtol=0, atol=0)
        assert np.min(np.linalg.eigvalsh(g)) > 0
    jac = jax.jacfwd(tr.forward)(jnp.asarray(u))
    assert np.all(np.isfinite(np.asarray(jac)))
    # the paper's diagonal G of batista-ges: C = I, u = 0 (scale = sqrt of the diagonal)
    gz = np.asarray(ges_params().gain_z)
    np.testing.assert_allclose(P.SPD().bind(gz).inverse(gz), 0.0, atol=1e-12)
    with pytest.raises(ValueError):
        P.SPD().inverse(-np.eye(3))


def test_spd_diagonal_structure_stays_diagonal():
    p = ges_params()
    bound = P.Parametrization({"gain_z": P.SPD(structure="diagonal")}).bind(p)
    th = {"gain_z": bound.init()["gain_z"] + 0.3}
    g = np.asarray(bound.constrain(th).gain_z)
    np.testing.assert_allclose(g, np.diag(np.diag(g)), atol=0)
    np.testing.assert_allclose(np.diag(g), np.diag(np.asarray(p.gain_z)) * np.exp(0.6), rtol=1e-12)
    assert bound.n_free() == 9


def test_bounded_round_trip():
    tr = P.Bounded(0.0, 1.0)
    x = np.array([1e-6, 0.5, 0.999])
    np.testing.assert_allclose(np.asarray(tr.forward(jnp.asarray(tr.inverse(x)))), x, rtol=1e-9)
    with pytest.raises(ValueError):
        tr.inverse(np.array([1.0]))


@pytest.mark.parametrize("name,make", [("batista-ges", ges_params), ("batista-so3", so3_params)])
def test_experiment_parametrization_round_trip(name, make):
    p = make()
    bound = for_observer(name).bind(p)
    back = bound.constrain(bound.init())
    for f in p._fields:
        np.testing.assert_allclose(np.asarray(getattr(back, f)), np.asarray(getattr(p, f)), rtol=1e-12, atol=1e-300)
    # switch times and references are never tunable
    assert "switch_times" not in bound.transforms and "ref_nav" not in bound.transforms
    # any theta gives params the observer accepts
    rng = np.random.default_rng(1)
    th = {k: v + jnp.asarray(rng.normal(scale=2.0, size=v.shape)) for k, v in bound.init().items()}
    (batista_ges.check_params if name == "batista-ges" else batista_so3.check_params)(bound.constrain(th))


def test_masks_freeze_exactly_with_zero_gradient():
    p = so3_params()
    par = for_observer("batista-so3", masks={"alpha1": P.schedule_mask(5, [-1]), "alpha0": False})
    bound = par.bind(p)
    assert bound.n_free() == 1 + 5 + 1 + 1  # last alpha1 interval, alpha2 (5), alpha3, alpha4
    th = {k: v + 0.7 for k, v in bound.init().items()}
    q = bound.constrain(th)
    np.testing.assert_array_equal(np.asarray(q.alpha1[:4]), np.asarray(p.alpha1[:4]))
    np.testing.assert_array_equal(np.asarray(q.alpha0), np.asarray(p.alpha0))
    assert float(q.alpha1[4]) == pytest.approx(float(p.alpha1[4]) * np.exp(0.7), rel=1e-12)

    def f(t):
        c = bound.constrain(t)
        return jnp.sum(c.alpha1 / p.alpha1) + c.alpha0 / p.alpha0 + c.alpha3 / p.alpha3

    g = jax.grad(f)(th)
    np.testing.assert_array_equal(np.asarray(g["alpha1"][:4]), 0.0)
    assert float(g["alpha0"]) == 0.0 and float(g["alpha1"][4]) > 0 and float(g["alpha3"]) > 0
    z = bound.zero_frozen({k: jnp.ones_like(v) for k, v in th.items()})
    np.testing.assert_array_equal(np.asarray(z["alpha1"]), [0, 0, 0, 0, 1])


def test_freeze_only_and_unknown_fields():
    par = for_observer("batista-ges", freeze=("gain_z",))
    assert set(par.transforms) == {"alpha1", "alpha2"}
    assert set(for_observer("batista-ges", tune=("gain_z",)).transforms) == {"gain_z"}
    assert isinstance(for_observer("batista-so3", method="softplus").transforms["alpha3"], P.Positive)
    assert for_observer("batista-so3", method="softplus").transforms["alpha3"].method == "softplus"
    with pytest.raises(ValueError, match="epsilon"):
        for_observer("batista-ges", freeze=("epsilon",))
    with pytest.raises(ValueError, match="no-such"):
        registry.get("no-such-observer")
    with pytest.raises(ValueError):
        P.Parametrization({"nope": P.Positive()}).bind(ges_params())


def test_a_gain_at_zero_is_kept_off_by_a_default_fit_and_named_when_asked_for():
    """complementary's k_i = 0 (no bias integrator): the fitter's default parametrization leaves it out (a log map
    cannot leave 0); asking to tune it is one error naming the gain."""
    from jaxatt import studies
    from jaxatt.fitting import fitter

    s = studies.get("complementary").setup(duration=1.0)
    assert float(s.params.k_i) == 0.0
    e = registry.get(s.entry)
    kw = dict(freeze=(), masks=None, method=None, transforms=None)
    bound = fitter._parametrization(e, s.params, tune=None, **kw)
    assert "k_i" not in bound.transforms and "k" in bound.transforms
    with pytest.raises(ValueError, match=r"^params\.k_i: a positive gain must be finite and > 0") as info:
        fitter._parametrization(e, s.params, tune=["k", "k_i"], **kw)
    assert "\n" not in str(info.value)


class MyParams(NamedTuple):
    k: jnp.ndarray
    tau: jnp.ndarray
    offset: jnp.ndarray


def test_params_of_your_own_observer():
    """for_params: every floating field whose values are all > 0 is a positive gain, a field with values <= 0 is
    left fixed with a warning naming it; tune= names the fields, a signed one is then learnt unconstrained (one
    unit = its largest magnitude); an integer field is refused with one line."""
    p = MyParams(jnp.asarray([0.5, 2.0]), jnp.asarray(3.0), jnp.asarray([-1.0, 2.0]))
    with pytest.warns(UserWarning, match=r"fields \['offset'\] have values <= 0 and are left fixed"):
        bound = P.for_params(p).bind(p)
    assert set(bound.transforms) == {"k", "tau"}
    back = bound.constrain({k: v + 0.3 for k, v in bound.init().items()})
    np.testing.assert_allclose(np.asarray(back.k), np.asarray(p.k) * np.exp(0.3), rtol=1e-12)
    np.testing.assert_array_equal(np.asarray(back.offset), np.asarray(p.offset))
    assert set(P.for_params(p, tune=("tau",)).transforms) == {"tau"}
    signed = P.for_params(p, tune=("offset",)).bind(p)
    np.testing.assert_allclose(signed.theta0["offset"], [-0.5, 1.0])
    moved = signed.constrain({"offset": jnp.asarray(signed.theta0["offset"]) + 0.25})
    np.testing.assert_allclose(np.asarray(moved.offset), [-0.5, 2.5], rtol=1e-12)  # u * 2: unconstrained
    with pytest.raises(ValueError, match="nope"):
        P.for_params(p, tune=("nope",))
    ints = MyParams(jnp.asarray(1), jnp.asarray(2), jnp.asarray(3))
    with pytest.raises(ValueError, match=r"params.k = 1 is an integer array, not a gain to tune: give it as floats"):
        P.for_params(ints, tune=("k",))
    with pytest.raises(ValueError, match=r"integer fields \['k', 'tau', 'offset'\] are not gains: write 1.0"):
        P.for_params(ints)


def test_bounded_positive_gains_are_projected_into_their_bounds():
    """A gain declared with bounds (the robust AHRS's time constants) is clipped into them in u."""
    g = registry.get("robust").gain("tau_acc")
    assert g.bounds == (0.05, 30.0)
    tr = P.from_constraint(g)
    lo, hi = tr.u_bounds()
    bound = P.Parametrization({"tau_acc": tr}).bind(registry.get("robust").default_params())
    th = bound.clip({"tau_acc": jnp.asarray(50.0)})
    assert float(bound.constrain(th).tau_acc) == pytest.approx(30.0, rel=1e-12)
    th = bound.clip({"tau_acc": jnp.asarray(-50.0)})
    assert float(bound.constrain(th).tau_acc) == pytest.approx(0.05, rel=1e-12)


@pytest.mark.parametrize("name,make", [("batista-ges", ges_params), ("batista-so3", so3_params)])
def test_gains_json_round_trip(name, make, tmp_path):
    p = make()
    p = p._replace(alpha2=p.alpha2 * 0.5)
    path = tmp_path / "g.json"
    gainsfile.write(str(path), observer=name, params=p, gains=registry.get(name).gains, study=name, note="test")
    payload = json.loads(path.read_text())
    assert payload["format"] == gainsfile.FORMAT and payload["observer"] == name and payload["note"] == "test"
    a1 = payload["gains"]["alpha1"]
    assert a1["intervals_s"][0][0] == 0.0 and a1["intervals_s"][-1][1] is None
    assert len(a1["intervals_s"]) == len(a1["value"]) == len(a1["switch_times_s"]) + 1
    assert all(isinstance(g["unit"], str) and g["doc"] for g in payload["gains"].values())
    q = gainsfile.read_params(str(path), name)
    for f in p._fields:
        np.testing.assert_allclose(np.asarray(getattr(q, f)), np.asarray(getattr(p, f)), rtol=1e-15)
    other = so3_params() if name == "batista-ges" else ges_params()
    with pytest.raises(ValueError, match="holds gains of"):
        gainsfile.read_params(str(path), "batista-ges" if name != "batista-ges" else "batista-so3")
    with pytest.raises(ValueError, match="holds gains of"):  # without an entry: the base params' type is checked
        gainsfile.read_params(str(path), base=other)
    np.testing.assert_array_equal(np.asarray(gainsfile.read_params(str(path), base=p).alpha2), np.asarray(p.alpha2))
    # a hand-edited file with a wrong shape, or an invalid gain, is refused
    payload["gains"]["alpha2"]["value"] = payload["gains"]["alpha2"]["value"][:-1]
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps(payload))
    with pytest.raises(ValueError, match="alpha2"):
        gainsfile.read_params(str(bad), name)
    payload["gains"]["alpha2"]["value"] = [-1.0] * len(a1["value"])
    bad.write_text(json.dumps(payload))
    with pytest.raises(ValueError):
        gainsfile.read_params(str(bad), name)
    # jaxatt 0.1's layout ("jaxatt-gains/1" with "experiment") reads as the same gains
    old = {"format": "jaxatt-gains/1", "experiment": name, "gains": json.loads(path.read_text())["gains"]}
    (tmp_path / "old.json").write_text(json.dumps(old))
    q_old = gainsfile.read_params(str(tmp_path / "old.json"), name)
    np.testing.assert_allclose(np.asarray(q_old.alpha2), np.asarray(p.alpha2), rtol=1e-15)
    empty = json.dumps({"format": "jaxatt-gains/2", "observer": name, "gains": {}, "status": "done"})
    for text, match in (("{", "JSON"), ('{"format": "x"}', "not a jaxatt gains file"), (empty, "'gains' is empty")):
        bad.write_text(text)
        with pytest.raises(ValueError, match=match):
            gainsfile.read(str(bad))
    with pytest.raises(ValueError, match="not found"):
        gainsfile.read(str(tmp_path / "missing.json"))


@pytest.mark.parametrize("name,make", [("batista-ges", ges_params), ("batista-so3", so3_params)])
def test_refine_schedule_keeps_the_gains_as_functions_of_time(name, make):
    """Extra switch times (inside intervals, before the first, after the last, and one already present) leave
    every schedule's value at every time unchanged; the refined params are valid and tunable per interval."""
    from jaxatt.observers import batista_ges as ges_obs
    from jaxatt.observers import batista_so3 as so3_obs

    p = make()
    extra = [30.0, 700.0, 1200.0, 2400.0, float(np.asarray(p.switch_times)[0])]
    fields = [g.field for g in registry.get(name).gains if g.constraint == "schedule"]
    assert set(fields) == {"alpha1", "alpha2"}
    q = schedule.refine(p, extra, fields)
    n_old, n_new = len(np.asarray(p.switch_times)), len(np.asarray(q.switch_times))
    assert n_new == n_old + 4 and np.all(np.diff(np.asarray(q.switch_times)) > 0)
    t = np.concatenate([np.linspace(-1.0, 3600.0, 7919), np.asarray(q.switch_times)])
    for field in fields:
        a = np.asarray(getattr(p, field))[np.sum(t[:, None] >= np.asarray(p.switch_times), axis=1)]
        b = np.asarray(getattr(q, field))[np.sum(t[:, None] >= np.asarray(q.switch_times), axis=1)]
        np.testing.assert_array_equal(a, b)
    if name == "batista-ges":  # the observer's own schedule lookup agrees
        np.testing.assert_array_equal(
            np.asarray(ges_obs._schedule(p, jnp.asarray(t))), np.asarray(ges_obs._schedule(q, jnp.asarray(t)))
        )
        ges_obs.check_params(q)
    else:
        so3_obs.check_params(q)
    bound = for_observer(name).bind(q)
    assert bound.theta0["alpha1"].shape == (n_new + 1,)
    late = schedule.mask_from(q.switch_times, 1200.0)  # the intervals starting at 1200 and 2400 s
    assert late.shape == (n_new + 1,) and int(late.sum()) == int(np.sum(np.asarray(q.switch_times) >= 1200.0))
    with pytest.raises(ValueError, match="shape"):
        schedule.refine(p, [10.0], ["alpha1", "ref_nav"])
    with pytest.raises(ValueError, match="finite"):
        schedule.refine(p, [np.nan], fields)


def test_basis_transforms_start_at_the_start_and_stay_valid():
    """LogBasis / ScaledSPD: u = 0 is the bound start exactly; a value in the span is recovered; every u gives
    a positive schedule / an SPD matrix; wrong shapes are refused."""
    rng = np.random.default_rng(3)
    p = P.refine_schedule(ges_params(), [900.0, 1800.0, 2700.0], ["alpha1", "alpha2"])
    starts = np.concatenate([[0.0], np.asarray(p.switch_times)])
    late = starts >= 900.0
    b = np.stack([~late, late, np.where(late, np.log(np.maximum(starts, 900.0) / 900.0), 0.0)], 1).astype(float)
    a2 = np.asarray(p.alpha2)
    tr = P.LogBasis(b).bind(a2)
    np.testing.assert_array_equal(np.asarray(tr.forward(jnp.zeros(3))), a2)
    u = np.array([-1.0, 0.5, -1.0])  # early x e^-1, late level x e^0.5, late ~ (t / 900)^-1
    v = np.asarray(tr.forward(jnp.asarray(u)))
    np.testing.assert_allclose(v[late] / a2[late], np.exp(0.5) * 900.0 / starts[late], rtol=1e-12)
    np.testing.assert_allclose(tr.inverse(v), u, atol=1e-12)
    assert np.all(v > 0)
    gz = np.asarray(p.gain_z)
    sz = P.ScaledSPD(np.kron(np.eye(3), np.ones((3, 1)))).bind(gz)
    np.testing.assert_array_equal(np.asarray(sz.forward(jnp.zeros(3))), gz)
    for _ in range(3):
        uz = rng.normal(size=3)
        g = np.asarray(sz.forward(jnp.asarray(uz)))
        assert np.min(np.linalg.eigvalsh(0.5 * (g + g.T))) > 0
        np.testing.assert_allclose(sz.inverse(g), uz, atol=1e-12)
    with pytest.raises(ValueError, match="basis"):
        P.LogBasis(np.ones((3, 1))).bind(a2)
    with pytest.raises(ValueError, match="not gains of"):
        for_observer("batista-ges", transforms={"epsilon": P.LogBasis(np.ones((1, 1)))})
