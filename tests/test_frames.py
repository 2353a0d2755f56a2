"""Frame conventions: known vectors and round trips."""

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from droneulator import frames as F

rng = np.random.default_rng(0)
QUATS = [F.quat_normalize(q) for q in rng.normal(size=(20, 4))]


@pytest.mark.parametrize("q", QUATS)
def test_quaternion_matrix_round_trip_and_scipy_agreement(q):
    R = F.quat_to_matrix(q)
    np.testing.assert_allclose(R, Rotation.from_quat(q).as_matrix(), atol=1e-12)
    q2 = F.matrix_to_quat(R)
    assert np.allclose(q2, q) or np.allclose(q2, -q)


@pytest.mark.parametrize("rpy", [(0.1, -0.2, 0.3), (0.0, 0.0, 3.0), (-1.0, 0.5, -2.0)])
def test_euler_matches_scipy_zyx_and_round_trips(rpy):
    q = F.quat_from_euler(*rpy)
    ref = Rotation.from_euler("ZYX", [rpy[2], rpy[1], rpy[0]]).as_quat()
    assert np.allclose(q, ref) or np.allclose(q, -ref)
    np.testing.assert_allclose(F.quat_to_euler(q), rpy, atol=1e-12)


def test_quat_multiply_composes_rotations():
    a, b = QUATS[0], QUATS[1]
    np.testing.assert_allclose(
        F.quat_to_matrix(F.quat_multiply(a, b)), F.quat_to_matrix(a) @ F.quat_to_matrix(b), atol=1e-12
    )
    np.testing.assert_allclose(F.quat_multiply(a, F.quat_conjugate(a)), [0, 0, 0, 1], atol=1e-12)


def test_zup_to_gl_known_vectors():
    np.testing.assert_allclose(F.zup_to_gl([0, 0, 1]), [0, 1, 0])  # up is +Y in OpenGL
    np.testing.assert_allclose(F.zup_to_gl([0, 1, 0]), [0, 0, -1])  # world north is -Z (Godot forward)
    np.testing.assert_allclose(F.zup_to_gl([1, 0, 0]), [1, 0, 0])
    p = rng.normal(size=(5, 3))
    np.testing.assert_allclose(F.gl_to_zup(F.zup_to_gl(p)), p)
    assert np.isclose(np.linalg.det(F.R_GL_ZUP), 1.0)


def test_optical_frame_axes():
    """A camera on the body's nose: optical z is body forward, x is body right, y is body down."""
    T = F.T_world_optical(np.eye(4), F.camera_mount(np.zeros(3), (0.0, 0.0, 0.0)))
    R = T[:3, :3]
    np.testing.assert_allclose(R @ [0, 0, 1], [1, 0, 0], atol=1e-12)
    np.testing.assert_allclose(R @ [1, 0, 0], [0, -1, 0], atol=1e-12)
    np.testing.assert_allclose(R @ [0, 1, 0], [0, 0, -1], atol=1e-12)


def test_positive_camera_pitch_looks_down():
    T = F.T_world_optical(np.eye(4), F.camera_mount(np.zeros(3), (0.0, math.radians(30), 0.0)))
    forward = T[:3, :3] @ [0, 0, 1]
    np.testing.assert_allclose(
        forward, [math.cos(math.radians(30)), 0, -math.sin(math.radians(30))], atol=1e-12
    )


def test_gl_view_matrix_puts_points_in_front_on_negative_z():
    T_wb = F.transform_from_pose(np.array([1.0, 2.0, 3.0]), F.quat_from_yaw(0.7))
    T_wo = F.T_world_optical(T_wb, F.camera_mount(np.array([0.1, 0.0, 0.0]), (0.0, 0.0, 0.0)))
    p_world = F.transform_points(T_wo, np.array([0.3, -0.2, 5.0]))  # 5 m ahead of the camera
    V = F.gl_view_matrix(T_wo)
    p_cam = F.transform_points(V, F.zup_to_gl(p_world))
    np.testing.assert_allclose(p_cam, [0.3, 0.2, -5.0], atol=1e-12)


def test_enu_ned_known_vectors_and_round_trip():
    np.testing.assert_allclose(F.enu_to_ned([1, 2, 3]), [2, 1, -3])  # east, north, up -> north, east, down
    np.testing.assert_allclose(F.flu_to_frd([1, 2, 3]), [1, -2, -3])
    v = rng.normal(size=(4, 3))
    np.testing.assert_allclose(F.ned_to_enu(F.enu_to_ned(v)), v)


def test_attitude_enu_flu_to_ned_frd():
    # level, nose pointing north (ENU yaw = +90 deg) -> NED yaw 0 (identity attitude)
    q = F.quat_ned_frd_to_enu_flu(F.quat_enu_flu_to_ned_frd(QUATS[3]))
    assert np.allclose(q, QUATS[3]) or np.allclose(q, -QUATS[3])
    q_ned = F.quat_enu_flu_to_ned_frd(F.quat_from_yaw(math.pi / 2))
    np.testing.assert_allclose(np.abs(q_ned), [0, 0, 0, 1], atol=1e-12)
    # nose east in ENU (yaw 0) is yaw +90 deg in NED
    _, _, yaw_ned = F.quat_to_euler(F.quat_enu_flu_to_ned_frd(F.quat_from_yaw(0.0)))
    assert math.isclose(yaw_ned, math.pi / 2, abs_tol=1e-12)
    # a body vector maps consistently through both representations
    qe = QUATS[4]
    v_flu = np.array([0.3, -1.0, 2.0])
    lhs = F.enu_to_ned(F.quat_to_matrix(qe) @ v_flu)
    rhs = F.quat_to_matrix(F.quat_enu_flu_to_ned_frd(qe)) @ F.flu_to_frd(v_flu)
    np.testing.assert_allclose(lhs, rhs, atol=1e-12)


def test_transform_inverse_and_wxyz():
    T = F.transform_from_pose(np.array([1.0, -2.0, 0.5]), QUATS[5])
    np.testing.assert_allclose(T @ F.invert_transform(T), np.eye(4), atol=1e-12)
    p, q = F.pose_from_transform(T)
    np.testing.assert_allclose(p, [1.0, -2.0, 0.5])
    np.testing.assert_allclose(F.wxyz_to_xyzw(F.xyzw_to_wxyz(q)), q)
    assert math.isclose(F.wrap_angle(3 * math.pi), -math.pi)


def test_enu_to_geodetic_known_offsets_and_round_trip():
    lat0, lon0, alt0 = 53.2281, -0.5470, 10.0
    assert F.enu_to_geodetic([0.0, 0.0, 0.0], lat0, lon0, alt0) == (lat0, lon0, alt0)
    lat, lon, alt = F.enu_to_geodetic([0.0, 100.0, 5.0], lat0, lon0, alt0)  # 100 m north, 5 m up
    assert math.isclose(lat - lat0, math.degrees(100.0 / F.EARTH_RADIUS_M), rel_tol=1e-6)
    assert math.isclose(lon, lon0, abs_tol=1e-12) and alt == 15.0
    lat, lon, _ = F.enu_to_geodetic([100.0, 0.0, 0.0], lat0, lon0, alt0)  # 100 m east
    expected = math.degrees(100.0 / (F.EARTH_RADIUS_M * math.cos(math.radians(lat0))))
    assert math.isclose(lon - lon0, expected, rel_tol=1e-6)
    assert abs(lat - lat0) < 1e-7  # a great circle heading east stays within 1 cm of the parallel
    for enu in np.random.default_rng(7).uniform(-3000.0, 3000.0, size=(20, 3)):
        back = F.geodetic_to_enu(*F.enu_to_geodetic(enu, lat0, lon0, alt0), lat0, lon0, alt0)
        np.testing.assert_allclose(back, enu, atol=1e-6)


# --------------------------------------------------------------------------- numba twins
def test_numba_twins_equal_the_numpy_conversions_on_random_inputs():
    from droneulator import frames_numba as N

    r = np.random.default_rng(11)
    for _ in range(200):
        q = r.normal(size=4) * r.uniform(0.2, 5.0)  # unnormalised on purpose: both normalise
        v = r.normal(size=3) * 10.0
        np.testing.assert_allclose(N.quat_to_matrix(q), F.quat_to_matrix(q), atol=1e-12)
        qu = F.quat_normalize(q)
        assert math.isclose(N.yaw_of(qu), F.yaw_of(q), abs_tol=1e-12)
        np.testing.assert_allclose(N.body_to_world(qu, v), F.body_to_world(q, v), atol=1e-10)
        np.testing.assert_allclose(N.world_to_body(qu, v), F.world_to_body(q, v), atol=1e-10)
        np.testing.assert_allclose(N.enu_to_ned(v), F.enu_to_ned(v), atol=0)
        np.testing.assert_allclose(N.flu_to_frd(v), F.flu_to_frd(v), atol=0)
        yaw = r.uniform(-math.pi, math.pi)
        out = np.full(4, np.nan)
        N.set_quat_from_yaw(out, yaw)
        np.testing.assert_allclose(out, F.quat_from_yaw(yaw), atol=0)
        assert math.isclose(N.yaw_of(out), yaw, abs_tol=1e-12)


def test_yaw_of_matches_scipy_and_ignores_scale_and_rejects_zero():
    for q in QUATS:
        expected = Rotation.from_quat(q).as_euler("ZYX")[0]
        assert math.isclose(F.yaw_of(3.7 * q), expected, abs_tol=1e-12)
    with pytest.raises(ValueError, match="not all zero"):
        F.yaw_of(np.zeros(4))
    unit = np.array([q / np.linalg.norm(q) for q in QUATS])
    batched = F.yaws_of(unit.reshape(-1, 1, 4))[:, 0]  # the state rows' form, any leading axes
    np.testing.assert_allclose(batched, [F.yaw_of(q) for q in QUATS], atol=1e-12)


def test_slerp_interpolates_on_the_shorter_arc():
    a, b = F.quat_from_yaw(0.2), F.quat_from_yaw(1.0)
    assert math.isclose(F.yaw_of(F.quat_slerp(a, b, 0.25)), 0.4, abs_tol=1e-12)
    np.testing.assert_allclose(F.quat_to_matrix(F.quat_slerp(a, -b, 1.0)), F.quat_to_matrix(b), atol=1e-12)
    # the sign of either end does not change the path: -b is the same attitude as b
    mid, mid_flipped = F.quat_slerp(a, b, 0.5), F.quat_slerp(a, -b, 0.5)
    np.testing.assert_allclose(F.quat_to_matrix(mid), F.quat_to_matrix(mid_flipped), atol=1e-12)
    # across +-pi it goes the short way (yaw 3.0 -> -3.0 passes through pi, not 0)
    q = F.quat_slerp(F.quat_from_yaw(3.0), F.quat_from_yaw(-3.0), 0.5)
    assert abs(abs(F.yaw_of(q)) - math.pi) < 1e-12
