"""Excitation measures of Trumpf et al. (2012) (jaxatt.analysis): agreement with an independent brute-force
computation, the paper's lemmas as properties, closed forms on the scenarios, inputs from logs, errors."""

import jax

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402
import pytest  # noqa: E402

from jaxatt import analysis as A  # noqa: E402
from jaxatt.observers import complementary as C  # noqa: E402
from jaxatt.sim import references as S  # noqa: E402
from jaxatt.types import ImuSample  # noqa: E402


# ---------------------------------------------------------------------------------------------------------
# Independent reference: explicit loops over windows, samples and measurements
# ---------------------------------------------------------------------------------------------------------
def _unit_or_none(v):
    if not np.all(np.isfinite(v)) or np.linalg.norm(v) == 0:
        return None
    return v / np.linalg.norm(v)


def brute_force(t, window, ref_inertial, inertial_meas, ref_body, gyr, gains, rule="trapezoid", growing=False):
    T, n1, n2 = len(t), ref_inertial.shape[1], inertial_meas.shape[1]
    q = np.ones(n1 + n2) if gains is None else np.asarray(gains, float)

    def at(m):
        S_, P_, A_, c_ = np.zeros((3, 3)), np.zeros((3, 3)), np.zeros((3, 3)), np.zeros(3)
        vs = [ref_inertial[m, i] for i in range(n1)] + [inertial_meas[m, j] for j in range(n2)]
        for idx, v in enumerate(vs):
            u = _unit_or_none(v)
            if u is None:
                continue
            S_ += np.outer(u, u)
            P_ += q[idx] * (np.eye(3) - np.outer(u, u))
            if idx < n1:
                A_ += np.outer(u, u)
        for j in range(n2):
            u = _unit_or_none(ref_body[m, j])
            if u is not None and np.all(np.isfinite(gyr[m])):
                c_ += np.cross(gyr[m], u)
        return S_, P_, A_, c_

    vals = [at(m) for m in range(T)]
    rows = []
    windows = []
    if growing:
        windows = [(0, e) for e in range(1, T)]
    else:
        for s in range(T):
            e = next((i for i in range(s, T) if t[i] >= t[s] + window * (1 - 1e-9)), None)
            if e is not None:
                windows.append((s, e))
    for s, e in windows:
        acc = [np.zeros((3, 3)), np.zeros((3, 3)), np.zeros((3, 3)), np.zeros(3)]
        for m in range(s, e):
            h = t[m + 1] - t[m]
            for k in range(4):
                acc[k] = acc[k] + (0.5 * (vals[m][k] + vals[m + 1][k]) if rule == "trapezoid" else vals[m][k]) * h
        deriv = np.zeros(3)  # ∫ d b̊/dτ: increments between consecutive valid samples
        for m in range(s, e):
            for j in range(n2):
                u0, u1 = _unit_or_none(ref_body[m, j]), _unit_or_none(ref_body[m + 1, j])
                if u0 is not None and u1 is not None:
                    deriv += u1 - u0
        ev = np.sort(np.linalg.eigh(acc[0])[0])[::-1]
        lam_p = np.linalg.eigh(acc[1])[0].min()
        lam_a = np.sort(np.linalg.eigh(acc[2])[0])[1]
        comp = np.linalg.norm(acc[3] + deriv)
        rows.append((t[s], t[e], ev[1], lam_p, lam_a, comp, lam_a + comp, ev))
    return A.Excitation(*(np.array(c) for c in zip(*rows)))


def random_case(seed=0, T=45, n1=2, n2=1):
    rng = np.random.default_rng(seed)
    t = np.cumsum(rng.uniform(0.05, 0.15, T)) + 3.0  # non-uniform sampling
    ar = rng.normal(size=(T, n1, 3)) * rng.uniform(0.5, 3.0, (T, n1, 1))  # not unit: normalised inside
    b = rng.normal(size=(T, n2, 3))
    br = rng.normal(size=(T, n2, 3))
    g = rng.normal(size=(T, 3))
    ar[7, 0, 1] = np.nan  # missing readings contribute nothing
    b[11, 0] = 0.0
    br[20, 0, 2] = np.nan
    g[30] = np.nan
    gains = rng.uniform(0.2, 2.0, n1 + n2)
    return t, ar, b, br, g, gains


@pytest.mark.parametrize("rule", ["trapezoid", "left"])
def test_matches_brute_force(rule):
    t, ar, b, br, g, gains = random_case()
    for window in (0.5, 1.3):
        got = A.excitation(
            t, window=window, ref_inertial=ar, inertial_meas=b, ref_body=br, gyr=g, gains=gains, rule=rule
        )
        ref = brute_force(t, window, ar, b, br, g, gains, rule)
        assert got.t_start.shape == ref.t_start.shape and len(got.t_start) > 10
        for name, x, y in zip(A.Excitation._fields, got, ref):
            np.testing.assert_allclose(x, y, rtol=1e-11, atol=1e-12, err_msg=name)
    got = A.sufficient_excitation(t, ref_inertial=ar, inertial_meas=b, ref_body=br, gyr=g, gains=gains, rule=rule)
    ref = brute_force(t, None, ar, b, br, g, gains, rule, growing=True)
    for name, x, y in zip(A.Excitation._fields, got, ref):
        np.testing.assert_allclose(x, y, rtol=1e-11, atol=1e-12, err_msg=name)


def test_stride_selects_window_starts():
    t, ar, b, br, g, gains = random_case(seed=1)
    full = A.excitation(t, window=1.0, ref_inertial=ar, inertial_meas=b, ref_body=br, gyr=g)
    sub = A.excitation(t, window=1.0, ref_inertial=ar, inertial_meas=b, ref_body=br, gyr=g, stride=4)
    idx = np.searchsorted(full.t_start, sub.t_start)
    np.testing.assert_allclose(sub.t_start, t[::4][: len(sub.t_start)])
    for x, y in zip(sub, full):
        np.testing.assert_allclose(x, y[idx])


# ---------------------------------------------------------------------------------------------------------
# The paper's lemmas as properties
# ---------------------------------------------------------------------------------------------------------
def test_lemma_a1_and_trace_identity():
    """tr ∫Σvv^T = n Δt; with unit gains λmin(∫Σ(I - vv^T)) = nΔt - λ1, λ2 <= λmin <= 2 λ2 (Lemma A.1)."""
    for seed in range(4):
        rng = np.random.default_rng(seed)
        t = np.sort(rng.uniform(0, 10, 200))
        v = rng.normal(size=(200, 3, 3)) * [1.0, 0.3, 0.1]  # three directions, anisotropic spread
        v[:, 1] += [0, 0, 1]
        ex = A.excitation(t, window=0.5 + seed, ref_inertial=v)
        dt = ex.t_end - ex.t_start
        np.testing.assert_allclose(ex.eigenvalues.sum(-1), 3 * dt, rtol=1e-12)
        np.testing.assert_allclose(ex.lambda_min_projector, 3 * dt - ex.eigenvalues[:, 0], rtol=1e-9, atol=1e-12)
        assert np.all(ex.lambda2 <= ex.lambda_min_projector * (1 + 1e-12))
        assert np.all(ex.lambda_min_projector <= 2 * ex.lambda2 * (1 + 1e-12))
        assert np.all(np.diff(ex.eigenvalues, axis=-1) <= 1e-12)  # descending


def test_lemma_a2_non_collinear_pair():
    """Two constant directions: λmin ∫ (I - aa^T + I - bb^T) >= |a x b|^2 / 2 per second (Lemma A.2, 3.8)."""
    rng = np.random.default_rng(3)
    t = np.linspace(0.0, 4.0, 41)
    for _ in range(10):
        a, b = rng.normal(size=(2, 3))
        a, b = a / np.linalg.norm(a), b / np.linalg.norm(b)
        ex = A.excitation(t, window=2.0, ref_inertial=np.stack([a, b]))
        assert np.all(ex.lambda_min_projector / 2.0 >= 0.5 * np.linalg.norm(np.cross(a, b)) ** 2 - 1e-12)
        # and the closed form: eigenvalues of aa^T + bb^T are 1 ± |a.b| and 0
        np.testing.assert_allclose(ex.eigenvalues[0] / 2.0, [1 + abs(a @ b), 1 - abs(a @ b), 0.0], atol=1e-12)


# ---------------------------------------------------------------------------------------------------------
# Closed forms on the scenarios of Sections III-IV
# ---------------------------------------------------------------------------------------------------------
def test_rotating_cone_closed_form():
    """å(t) on a cone of half-angle θ about z, one turn per window:
    ∫å å^T / T = diag(sin²θ/2, sin²θ/2, cos²θ)."""
    th, period = np.deg2rad(60.0), 12.0
    t = np.arange(0.0, 36.0 + 1e-9, 0.01)
    w = 2 * np.pi / period
    a = np.stack([np.sin(th) * np.cos(w * t), np.sin(th) * np.sin(w * t), np.cos(th) * np.ones_like(t)], -1)[:, None]
    ex = A.excitation(t, window=period, ref_inertial=a, stride=50)
    np.testing.assert_allclose(ex.eigenvalues / period, [[0.375, 0.375, 0.25]] * len(ex.t_start), atol=1e-9)
    np.testing.assert_allclose(ex.lambda_min_projector / period, 0.625, atol=1e-9)
    np.testing.assert_allclose(ex.condition, ex.lambda2)  # no compatible measurement
    # the one direction as (T, 3), one row per sample: the same (it was read as T constant directions)
    flat = A.excitation(t, window=period, ref_inertial=a[:, 0], stride=50)
    np.testing.assert_allclose(flat.eigenvalues, ex.eigenvalues, rtol=1e-12)


def test_scenarios_excitation():
    """(a) rotating and switching: PE; (b) one constant reference: λ2 = 0; (c) two at 60 deg: 1 - cos 60."""
    kw = dict(duration=36.0, dt=0.02, window=12.0, stride=20)
    rate = lambda ex, f: getattr(ex, f) / (ex.t_end - ex.t_start)  # noqa: E731
    ex = A.excitation_of_scenario(S.rotating_reference(), **kw)
    np.testing.assert_allclose(rate(ex, "lambda2"), 0.375, atol=1e-6)
    ex = A.excitation_of_scenario(S.switching_reference(half_period_s=3.0), **kw)
    assert np.min(rate(ex, "lambda2")) > 0.4  # two orthogonal directions, about half the time each
    ex = A.excitation_of_scenario(S.constant_reference(), **kw)
    assert np.max(np.abs(ex.lambda2)) < 1e-12 and np.max(np.abs(ex.lambda_min_projector)) < 1e-12
    ex = A.excitation_of_scenario(S.two_constant_references(60.0), **kw)
    np.testing.assert_allclose(rate(ex, "lambda2"), 0.5, atol=1e-9)


def test_compatible_term():
    """Second term of (13): ||∫ Omega x b̊ + d b̊/dτ||. Body spinning about x with b̊ = e3: |Omega| T; the same
    spin with b̊(t) counter-rotating so that b = R b̊ stays constant: 0 (and λ2 of {b_j} = 0)."""
    w = 0.4
    t = np.arange(0.0, 20.0 + 1e-9, 0.01)
    gyr = np.tile([w, 0.0, 0.0], (len(t), 1))
    e3 = np.array([[0.0, 0.0, 1.0]])
    b_spin = np.stack([np.zeros_like(t), -np.sin(w * t), np.cos(w * t)], -1)[:, None]  # R(t) e3, R = Rx(w t)
    ex = A.excitation(t, window=5.0, inertial_meas=b_spin, ref_body=e3, gyr=gyr, stride=100)
    np.testing.assert_allclose(ex.compatible_term, w * 5.0, rtol=1e-12)
    np.testing.assert_allclose(ex.condition, ex.compatible_term)
    assert np.min(ex.lambda2) > 0.1 * 5.0
    # b̊(t) = Rx(-w t) e3, b = Rx(w t) b̊ = e3 constant
    br = np.stack([np.zeros_like(t), np.sin(w * t), np.cos(w * t)], -1)[:, None]
    ex = A.excitation(
        t, window=5.0, inertial_meas=np.broadcast_to(e3, (len(t), 1, 3)), ref_body=br, gyr=gyr, stride=100
    )
    assert np.max(ex.compatible_term) < 1e-4 and np.max(ex.lambda2) < 1e-12


# ---------------------------------------------------------------------------------------------------------
# From logs
# ---------------------------------------------------------------------------------------------------------
def test_from_samples():
    field = np.array([2.6338e4, 0.0851e4, 3.6359e4])
    p = C.imu_params(mag_ref=field, frame="NED")
    t = np.linspace(0.0, 10.0, 101)
    readings = np.tile([0.1, 0.2, 9.8], (101, 1))  # any valid readings: only the references' directions count
    imu = ImuSample(t, np.zeros((101, 3)), acc=readings, mag=readings)
    ex = A.excitation_from_samples(imu, window=2.0, params=p)
    c = abs(field @ np.array(C.UP_NED)) / np.linalg.norm(field)
    np.testing.assert_allclose(ex.lambda2 / 2.0, 1.0 - c, rtol=1e-9)
    ex_g = A.excitation_from_samples(imu, window=2.0, params=p._replace(k=np.array([2.0, 3.0])), gains="params")
    assert np.all(ex_g.lambda_min_projector > ex.lambda_min_projector)
    suff = A.excitation_from_samples(imu, params=p)  # window None: from t0 (Definition 3.3)
    np.testing.assert_allclose(suff.t_end, t[1:])
    np.testing.assert_allclose(suff.lambda2, (1.0 - c) * t[1:], rtol=1e-9)
    # a VectorSample whose references are constant in params
    samples, _ = S.simulate_vectors(S.two_constant_references(60.0), 4.0, 0.02)
    ref = A.excitation_from_samples(samples, window=1.0)
    p2 = C.default_params(2, 0, ref_inertial=np.asarray(samples.ref_inertial[0]))
    got = A.excitation_from_samples(samples._replace(ref_inertial=None), window=1.0, params=p2)
    for x, y in zip(got, ref):
        np.testing.assert_allclose(x, y, atol=1e-12)
    with pytest.raises(ValueError, match="params"):
        A.excitation_from_samples(samples._replace(ref_inertial=None), window=1.0)


def test_log_references_count_only_where_their_readings_are_valid():
    """A constant reference contributes only at samples where its sensor gave a finite, non-zero reading: with
    acc invalid (NaN, then zero) in the second half, windows there see the magnetic reference alone (rank 1,
    lambda2 = 0) while windows of the first half keep the two-reference value 1 - c."""
    field = np.array([2.6338e4, 0.0851e4, 3.6359e4])
    p = C.imu_params(mag_ref=field, frame="NED")
    c = abs(field @ np.array(C.UP_NED)) / np.linalg.norm(field)
    t = np.linspace(0.0, 20.0, 2001)
    acc = np.tile([0.0, 0.0, -9.8], (t.size, 1))
    acc[1000:1500] = np.nan
    acc[1500:] = 0.0
    mag = np.tile(field, (t.size, 1))
    ex = A.excitation_from_samples(ImuSample(t, np.zeros_like(acc), acc=acc, mag=mag), window=2.0, params=p)
    first = ex.t_end <= 10.0 - 1e-9
    second = ex.t_start >= 10.0
    np.testing.assert_allclose(ex.lambda2[first] / 2.0, 1.0 - c, rtol=1e-9)
    np.testing.assert_allclose(ex.lambda2[second], 0.0, atol=1e-12)
    dead = ImuSample(t, np.zeros_like(acc), acc=np.full_like(acc, np.nan), mag=np.zeros_like(mag))
    assert np.all(A.excitation_from_samples(dead, window=2.0, params=p).lambda2 == 0.0)
    with pytest.raises(ValueError, match="imu_fields"):
        A.excitation_from_samples(ImuSample(t, acc, acc=acc, mag=None), window=2.0, params=p)


def test_gaps_in_the_timestamps_count_as_no_data():
    """A 1e6-s gap adds nothing to the integrals: no window's lambda2 exceeds its covered time x 2 (two unit
    references), and a window across the gap holds only the data on either side."""
    a = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0]])
    t = np.arange(2000) * 0.01
    t[1000:] += 1e6
    ex = A.excitation(t, window=2.0, ref_inertial=a)
    assert np.max(ex.lambda2) <= 2.0 * 1.0 + 1e-9  # lambda2 of I_2 over 2 s of data is 2 (one per reference)
    across = (ex.t_start < t[999]) & (ex.t_end >= t[1000])
    assert across.sum() > 100
    covered = (t[999] - ex.t_start[across]) + (ex.t_end[across] - t[1000])
    np.testing.assert_allclose(ex.lambda2[across], covered, atol=1e-9)
    with pytest.raises(ValueError, match="max_gap"):
        A.excitation(t, window=2.0, ref_inertial=a, max_gap=-1.0)
    # a larger max_gap takes the gap as data again (what the trapezoid rule did before)
    assert np.max(A.excitation(t, window=2.0, ref_inertial=a, max_gap=2e6).lambda2) > 1e5


def test_plot_excitation(tmp_path):
    t = np.linspace(0.0, 10.0, 101)
    ex = A.excitation(t, window=2.0, ref_inertial=np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0]]))
    ax = A.plot_excitation(ex, threshold=0.1, title="two constant references")
    assert len(ax.get_lines()) == 4
    ax.figure.savefig(tmp_path / "excitation.png")
    assert (tmp_path / "excitation.png").stat().st_size > 1000


def test_bad_inputs():
    t = np.linspace(0.0, 1.0, 11)
    a = np.array([[0.0, 0.0, 1.0]])
    with pytest.raises(ValueError, match="window"):
        A.excitation(t, window=0.0, ref_inertial=a)
    with pytest.raises(ValueError, match="longer than the log"):
        A.excitation(t, window=5.0, ref_inertial=a)
    with pytest.raises(ValueError, match="increasing"):
        A.excitation(t[::-1], window=0.5, ref_inertial=a)
    with pytest.raises(ValueError, match="at least one"):
        A.excitation(t, window=0.5)
    with pytest.raises(ValueError, match="shape"):
        A.excitation(t, window=0.5, ref_inertial=np.zeros((5, 1, 3)))
    with pytest.raises(ValueError, match="gains"):
        A.excitation(t, window=0.5, ref_inertial=a, gains=[-1.0])
    with pytest.raises(ValueError, match="gyr"):
        A.excitation(t, window=0.5, inertial_meas=np.ones((11, 1, 3)), ref_body=a)
    with pytest.raises(ValueError, match="rule"):
        A.excitation(t, window=0.5, ref_inertial=a, rule="simpson")
    with pytest.raises(ValueError, match="stride"):
        A.excitation(t, window=0.5, ref_inertial=a, stride=0)
