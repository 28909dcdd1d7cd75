"""jaxatt.frames: the conversions at the edges (frames, quaternion order, scipy, units), checked against scipy's
rotations and jaxatt.so3's quaternion-to-matrix map (independent computations)."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from jaxatt import frames, so3


def _random_quats(n, seed=0):
    q = np.random.default_rng(seed).normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=-1, keepdims=True)
    return np.where(q[:, :1] < 0, -q, q)


def test_frame_rotations_are_proper_and_compose():
    east_enu, north_enu, up_enu = np.eye(3)
    ned = frames.frame_rotation("NED", "ENU")
    np.testing.assert_array_equal(ned @ north_enu, [1, 0, 0])  # north is NED's x
    np.testing.assert_array_equal(ned @ east_enu, [0, 1, 0])
    np.testing.assert_array_equal(ned @ up_enu, [0, 0, -1])  # down
    nwu = frames.frame_rotation("NWU", "ENU")
    np.testing.assert_array_equal(nwu @ east_enu, [0, -1, 0])  # west is NWU's y
    for a in frames.FRAMES:
        np.testing.assert_allclose(np.linalg.det(frames.frame_rotation(a, "ENU")), 1.0)
        np.testing.assert_array_equal(frames.up(a), frames.frame_rotation(a, "ENU") @ up_enu)
        for b in frames.FRAMES:
            for c in frames.FRAMES:
                np.testing.assert_allclose(
                    frames.frame_rotation(a, b) @ frames.frame_rotation(b, c), frames.frame_rotation(a, c)
                )


@pytest.mark.parametrize("to,frm", [("NED", "ENU"), ("ENU", "NED"), ("NWU", "ENU"), ("NED", "NWU"), ("ENU", "ENU")])
def test_change_frame_is_the_left_multiplied_rotation(to, frm):
    q = _random_quats(50)
    r_frm = np.asarray(so3.quat_to_matrix(q))
    q_to = frames.change_frame(q, to, frm)
    np.testing.assert_allclose(np.asarray(so3.quat_to_matrix(q_to)), frames.frame_rotation(to, frm) @ r_frm, atol=1e-14)
    # a vector measured in the sensor frame, expressed in frm then moved, equals the rotation by q_to
    v = np.random.default_rng(1).normal(size=(50, 3))
    v_frm = np.einsum("nij,nj->ni", r_frm, v)
    np.testing.assert_allclose(
        frames.change_vector_frame(v_frm, to, frm), np.einsum("nij,nj->ni", so3.quat_to_matrix(q_to), v), atol=1e-13
    )
    assert frames.change_frame(q.astype(np.float32), to, frm).dtype == np.float32


def test_scipy_round_trip_and_order():
    q = _random_quats(20, seed=2)
    rot = frames.to_scipy(q)
    np.testing.assert_allclose(rot.as_matrix(), np.asarray(so3.quat_to_matrix(q)), atol=1e-14)
    np.testing.assert_allclose(frames.from_scipy(rot), q, atol=1e-15)
    np.testing.assert_array_equal(frames.to_xyzw(q)[:, 3], q[:, 0])
    np.testing.assert_array_equal(frames.from_xyzw(frames.to_xyzw(q)), q)
    # scipy's scalar-last quaternion of a 90-degree turn about z
    np.testing.assert_allclose(
        frames.from_scipy(Rotation.from_euler("z", 90, degrees=True)), [np.sqrt(0.5), 0, 0, np.sqrt(0.5)]
    )


def test_units():
    np.testing.assert_allclose(frames.deg_s_to_rad_s(180.0), np.pi)
    np.testing.assert_allclose(frames.rad_s_to_deg_s(frames.deg_s_to_rad_s([1.0, -2.5])), [1.0, -2.5])
    assert frames.g_to_m_s2(1.0) == 9.80665 and frames.m_s2_to_g(9.80665) == 1.0
    assert frames.gauss_to_ut(0.5) == 50.0 and frames.ut_to_gauss(50.0) == 0.5  # 1 G = 100 uT
    assert frames.nt_to_ut(48_000.0) == 48.0 and frames.ut_to_nt(48.0) == 48_000.0


def test_check_frame():
    assert frames.check_frame("ned") == "NED"
    with pytest.raises(ValueError, match="frame must be one of ENU, NED, NWU, got 'XYZ'"):
        frames.check_frame("XYZ")


def test_change_frame_promotes_integer_quaternions():
    """An integer quaternion came back as zeros (the frame quaternion, entries sqrt(1/2), was cast to int)."""
    import jax.numpy as jnp

    want = frames.change_frame(np.array([1.0, 0.0, 0.0, 0.0]), "NED")
    for q in (jnp.array([1, 0, 0, 0]), np.array([[1, 0, 0, 0]] * 2, np.int64), [1, 0, 0, 0]):
        got = frames.change_frame(q, "NED")
        assert got.dtype == np.float64
        np.testing.assert_allclose(got.reshape(-1, 4)[0], want, atol=1e-15)
        assert np.linalg.norm(got.reshape(-1, 4)[0]) == pytest.approx(1.0)
    np.testing.assert_array_equal(frames.change_vector_frame(np.array([1, 2, 3]), "NED"), [2.0, 1.0, -3.0])
    with pytest.raises(TypeError, match=r"change_frame: q must be real numbers, got dtype bool"):
        frames.change_frame(np.array([True, False, False, False]), "NED")


@pytest.mark.parametrize(
    "call,match",
    [
        (lambda: frames.change_frame(np.zeros(3), "NED"), r"change_frame: q must have shape \(\.\.\., 4\), got \(3,\)"),
        (lambda: frames.change_frame(np.zeros((2, 5)), "NED"), r"q must have shape \(\.\.\., 4\), got \(2, 5\)"),
        (
            lambda: frames.change_vector_frame(np.zeros(4), "NED"),
            r"change_vector_frame: v must have shape \(\.\.\., 3\)",
        ),
        (lambda: frames.to_xyzw(np.zeros(3)), r"to_xyzw: q must have shape \(\.\.\., 4\), got \(3,\)"),
        (lambda: frames.from_xyzw(np.zeros(5)), r"from_xyzw: q must have shape \(\.\.\., 4\), got \(5,\)"),
        (lambda: frames.to_scipy(np.zeros((2, 3))), r"to_scipy: q must have shape \(\.\.\., 4\), got \(2, 3\)"),
        (lambda: frames.from_scipy(np.zeros(4)), r"from_scipy: rotation must be a scipy"),
    ],
)
def test_frames_refuse_wrong_shapes(call, match):
    with pytest.raises((ValueError, TypeError), match=match):
        call()


def test_frames_keep_batches_and_lists():
    q = _random_quats(6).reshape(2, 3, 4)
    assert frames.change_frame(q, "NED").shape == (2, 3, 4)
    np.testing.assert_array_equal(frames.to_xyzw([1.0, 2.0, 3.0, 4.0]), [2.0, 3.0, 4.0, 1.0])
    np.testing.assert_array_equal(frames.from_xyzw(frames.to_xyzw(q)), q)


def test_unit_tables_are_the_definitions_and_agree_with_the_helpers():
    """The factors of the unit arguments (gyr_unit, acc_unit, time_unit) are the definitions (deg = pi / 180
    rad, standard gravity 9.80665 m/s^2, SI prefixes) and give what the hand conversion helpers give."""
    x = np.array([[180.0, -90.0, 1.5]])
    np.testing.assert_allclose(frames.to_si(x, "gyr_unit", "deg/s"), frames.deg_s_to_rad_s(x), rtol=1e-15)
    np.testing.assert_allclose(frames.to_si(x, "gyr_unit", "mdps") * 1e3, frames.deg_s_to_rad_s(x), rtol=1e-15)
    assert frames.unit_factor("gyr_unit", "dps") == frames.unit_factor("gyr_unit", "deg/s")
    np.testing.assert_allclose(frames.to_si(x, "acc_unit", "g"), frames.g_to_m_s2(x), rtol=1e-15)
    np.testing.assert_allclose(frames.to_si(x, "acc_unit", "mg") * 1e3, frames.g_to_m_s2(x), rtol=1e-15)
    assert frames.unit_factor("acc_unit", "g") == 9.80665 and frames.unit_factor("acc_unit", "m/s2") == 1.0
    assert [frames.unit_factor("time_unit", u) for u in ("s", "ms", "us", "ns")] == [1.0, 1e-3, 1e-6, 1e-9]
    for argument, own in (("gyr_unit", "rad/s"), ("acc_unit", "m/s^2"), ("time_unit", "s")):
        assert frames.unit_factor(argument, own) == 1.0


def test_to_si_keeps_float32_makes_integers_float64_and_leaves_si_alone():
    a32 = np.array([[180.0, -90.0, 1.0]], np.float32)
    out = frames.to_si(a32, "gyr_unit", "deg/s")
    assert out.dtype == np.float32
    np.testing.assert_allclose(out, np.deg2rad(a32.astype(np.float64)), rtol=1e-7)
    ints = frames.to_si(np.array([1, 2, 3]), "time_unit", "ms")
    assert ints.dtype == np.float64 and np.array_equal(ints, [1e-3, 2e-3, 3e-3])
    assert frames.to_si(None, "acc_unit", "g") is None
    same = np.ones(3)
    assert frames.to_si(same, "acc_unit", "m/s^2") is same  # already in jaxatt's unit: not copied


@pytest.mark.parametrize(
    "argument, unit, match",
    [
        ("gyr_unit", "rpm", r"gyr_unit must be one of 'rad/s', 'deg/s', 'dps', 'mdps', got 'rpm'"),
        ("acc_unit", None, r"acc_unit must be one of 'm/s\^2', 'm/s2', 'g', 'mg', got None"),
        ("time_unit", "minutes", r"time_unit must be one of 's', 'ms', 'us', 'ns', got 'minutes'"),  # 'sec' is read
        ("mag_unit", "uT", r"unit argument must be one of gyr_unit, acc_unit, time_unit, got 'mag_unit'"),
    ],
)
def test_an_unknown_unit_is_one_line_naming_the_argument(argument, unit, match):
    with pytest.raises(ValueError, match=match) as e:
        frames.to_si(np.ones(3), argument, unit)
    assert "\n" not in str(e.value)
