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
