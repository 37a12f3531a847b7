import numpy as np
from scipy.spatial.transform import Rotation

from pdr_mag.conventions import (
    heading_deg_from_quat,
    heading_deg_from_rot,
    quat_to_rot,
    rot_to_quat,
    rotation_about_up,
    wrap_deg,
)


def test_quaternion_round_trip_is_w_first():
    rng = np.random.default_rng(1)
    rots = Rotation.random(50, random_state=rng)
    q = rot_to_quat(rots.as_matrix())
    assert np.all(q[:, 0] >= 0)
    np.testing.assert_allclose(quat_to_rot(q), rots.as_matrix(), atol=1e-12)
    # identity is (1, 0, 0, 0)
    np.testing.assert_allclose(rot_to_quat(np.eye(3)), [1, 0, 0, 0], atol=1e-15)


def test_heading_of_flat_phone_pointing_east_is_90():
    # device +y points east: device→world maps y_d to +x_w (east); flat screen up keeps z_d = z_w
    rot_wd = np.array([[0.0, 1.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    assert np.isclose(heading_deg_from_rot(rot_wd), 90.0)
    assert np.isclose(heading_deg_from_quat(rot_to_quat(rot_wd)), 90.0)


def test_heading_from_quat_matches_matrix_formula_for_any_attitude():
    rng = np.random.default_rng(2)
    rots = Rotation.random(200, random_state=rng)
    q = rot_to_quat(rots.as_matrix())
    d = wrap_deg(heading_deg_from_quat(q) - heading_deg_from_rot(rots.as_matrix()))
    assert np.max(np.abs(d)) < 1e-9


def test_rotation_about_up_decreases_heading_for_positive_angle():
    rot_wd = np.eye(3)  # heading 0
    turned = rotation_about_up(np.radians(30.0)).as_matrix() @ rot_wd
    assert np.isclose(wrap_deg(heading_deg_from_rot(turned)), -30.0)


def test_vectorised_quaternion_algebra_agrees_with_scipy():
    from pdr_mag.conventions import quat_multiply, quat_rotate, quat_slerp, rotvec_to_matrix

    rng = np.random.default_rng(4)
    a, b = Rotation.random(20, random_state=rng), Rotation.random(20, random_state=rng)
    qa, qb = rot_to_quat(a.as_matrix()), rot_to_quat(b.as_matrix())
    np.testing.assert_allclose(quat_to_rot(quat_multiply(qa, qb)), (a * b).as_matrix(), atol=1e-12)
    v = rng.normal(size=(20, 3))
    np.testing.assert_allclose(quat_rotate(qa, v), a.apply(v), atol=1e-12)
    np.testing.assert_allclose(quat_rotate(qa, v, inverse=True), a.inv().apply(v), atol=1e-12)
    r = rng.normal(size=3)
    np.testing.assert_allclose(rotvec_to_matrix(r), Rotation.from_rotvec(r).as_matrix(), atol=1e-12)
    # slerp: ends reproduce the keys, the midpoint is half the relative rotation
    mid = quat_slerp(np.array([0.0, 1.0]), np.stack([qa[0], qb[0]]), np.array([0.0, 0.5, 1.0]))
    np.testing.assert_allclose(quat_to_rot(mid[[0, 2]]), [a[0].as_matrix(), b[0].as_matrix()], atol=1e-12)
    half = a[0] * Rotation.from_rotvec(0.5 * (a[0].inv() * b[0]).as_rotvec())
    np.testing.assert_allclose(quat_to_rot(mid[1]), half.as_matrix(), atol=1e-12)

