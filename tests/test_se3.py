"""SE(3) / SO(3) helpers checked against independent code (scipy's Rotation and expm)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.linalg import expm
from scipy.spatial.transform import Rotation

from autoalign.geometry.se3 import (
    apply_twist,
    hat3,
    invert,
    make_pose,
    rotation_angle_deg,
    se3_exp,
    so3_exp,
    so3_log,
    transform_points,
    twist_about,
)

RNG_SEED = 1234


def _unit(rng: np.random.Generator, n: int) -> np.ndarray:
    v = rng.standard_normal((n, 3))
    return v / np.linalg.norm(v, axis=1, keepdims=True)


def _rotvecs(rng: np.random.Generator) -> np.ndarray:
    """Random axis-angle vectors with angles spread over (0, pi), plus angles near 0 and near pi."""
    angles = np.concatenate([
        rng.uniform(0.0, np.pi, 200),
        [0.0, 1e-12, 1e-9, 1e-7, 1e-6, 0.9e-6, 1.1e-6, 1e-5, 1e-4, 1e-3],
        np.pi - np.array([1e-2, 1e-3, 2e-4, 1.1e-4, 9e-5, 5e-5, 1e-5, 1e-6, 1e-7, 1e-9, 1e-12]),
    ])
    return _unit(rng, len(angles)) * angles[:, None]


def _hat4(xi: np.ndarray) -> np.ndarray:
    """The 4x4 twist matrix [[hat(w), v], [0, 0]] written out by hand (not via hat3)."""
    v, w = xi[:3], xi[3:]
    return np.array([[0.0, -w[2], w[1], v[0]],
                     [w[2], 0.0, -w[0], v[1]],
                     [-w[1], w[0], 0.0, v[2]],
                     [0.0, 0.0, 0.0, 0.0]])


# ---------------------------------------------------------------------------------------- SO(3)

def test_hat3_is_cross_product():
    rng = np.random.default_rng(RNG_SEED)
    for w, x in zip(rng.standard_normal((20, 3)), rng.standard_normal((20, 3))):
        np.testing.assert_allclose(hat3(w) @ x, np.cross(w, x), atol=1e-14)


def test_so3_exp_matches_scipy():
    rng = np.random.default_rng(RNG_SEED)
    for w in _rotvecs(rng):
        np.testing.assert_allclose(so3_exp(w), Rotation.from_rotvec(w).as_matrix(), atol=1e-13, err_msg=str(w))
    # angles beyond pi wrap around as they should
    for w in _unit(rng, 20) * rng.uniform(np.pi, 3 * np.pi, (20, 1)):
        np.testing.assert_allclose(so3_exp(w), Rotation.from_rotvec(w).as_matrix(), atol=1e-12)


def test_so3_log_matches_scipy_including_near_zero_and_pi():
    rng = np.random.default_rng(RNG_SEED + 1)
    for w in _rotvecs(rng):
        R = Rotation.from_rotvec(w).as_matrix()
        got = so3_log(R)
        ref = Rotation.from_matrix(R).as_rotvec()
        assert np.linalg.norm(got) <= np.pi + 1e-12
        if np.pi - np.linalg.norm(w) < 1e-10:
            # at pi the sign of the axis is arbitrary: both are logarithms of R
            err = min(np.abs(got - w).max(), np.abs(got + w).max())
        else:
            err = np.abs(got - ref).max()
            assert np.abs(ref - w).max() < 1e-9  # scipy itself agrees with the generating vector
        assert err < 1e-10, (np.linalg.norm(w), got, w)
        np.testing.assert_allclose(so3_exp(got), R, atol=1e-12)


def test_so3_log_exactly_pi_and_identity():
    for axis in np.eye(3).tolist() + [[1.0, 1.0, 0.0], [1.0, -2.0, 3.0]]:
        a = np.asarray(axis) / np.linalg.norm(axis)
        R = Rotation.from_rotvec(np.pi * a).as_matrix()
        w = so3_log(R)
        assert abs(np.linalg.norm(w) - np.pi) < 1e-12
        assert abs(abs(w @ a) - np.pi) < 1e-10
        np.testing.assert_allclose(so3_exp(w), R, atol=1e-12)
    np.testing.assert_array_equal(so3_log(np.eye(3)), np.zeros(3))


def test_rotation_pi_over_2_about_z_maps_x_to_y():
    R = so3_exp([0.0, 0.0, np.pi / 2])
    np.testing.assert_allclose(R @ [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], atol=1e-15)
    np.testing.assert_allclose(R @ [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0], atol=1e-15)
    np.testing.assert_allclose(R @ [0.0, 0.0, 1.0], [0.0, 0.0, 1.0], atol=1e-15)


# ---------------------------------------------------------------------------------------- SE(3)

def test_se3_exp_matches_expm_of_hat():
    rng = np.random.default_rng(RNG_SEED + 2)
    ws = _rotvecs(rng)
    vs = rng.uniform(-300.0, 300.0, (len(ws), 3))
    for v, w in zip(vs, ws):
        xi = np.concatenate([v, w])
        ref = expm(_hat4(xi))
        np.testing.assert_allclose(se3_exp(xi), ref, atol=1e-10 * max(1.0, np.abs(v).max()), err_msg=str(xi))


def se3_log(T: np.ndarray) -> np.ndarray:
    """Twist ``(v, w)`` with ``se3_exp(se3_log(T)) == T``: ``w = so3_log(R)``, and ``v`` solves
    ``J(w) v = t``, ``J``'s columns being the translations ``se3_exp`` gives the unit ``v``."""
    w = so3_log(T[:3, :3])
    J = np.column_stack([se3_exp(np.concatenate([e, w]))[:3, 3] for e in np.eye(3)])
    return np.concatenate([np.linalg.solve(J, T[:3, 3]), w])


def test_se3_log_round_trips():
    rng = np.random.default_rng(RNG_SEED + 3)
    ws = _rotvecs(rng)
    vs = rng.uniform(-300.0, 300.0, (len(ws), 3))
    for v, w in zip(vs, ws):
        xi = np.concatenate([v, w])
        T = se3_exp(xi)
        xi2 = se3_log(T)
        np.testing.assert_allclose(se3_exp(xi2), T, atol=1e-10)  # exp(log(T)) == T, always
        if np.linalg.norm(w) < np.pi - 1e-10:  # log(exp(xi)) == xi off the cut locus
            np.testing.assert_allclose(xi2, xi, atol=1e-9)
        # and log really is a matrix logarithm of T (independent of se3_exp)
        np.testing.assert_allclose(expm(_hat4(xi2)), T, atol=1e-9)


def test_pure_translation_twist():
    v = np.array([12.5, -3.0, 700.0])
    T = se3_exp(np.concatenate([v, np.zeros(3)]))
    np.testing.assert_allclose(T, make_pose(np.eye(3), v), atol=0)
    np.testing.assert_allclose(se3_log(T), np.concatenate([v, np.zeros(3)]), atol=1e-12)


def test_screw_motion_closed_form():
    """Twist (v, w) with w = theta z, v = -w x p + h theta z: rotate by theta about the z-parallel
    axis through p and advance h*theta along it (pitch h)."""
    p = np.array([40.0, -25.0, 7.0])
    for theta, pitch in [(np.pi / 2, 0.0), (np.pi / 3, 5.0), (2.5, -12.0), (1e-7, 3.0)]:
        w = np.array([0.0, 0.0, theta])
        v = -np.cross(w, p) + pitch * w
        T = se3_exp(np.concatenate([v, w]))
        c, s = np.cos(theta), np.sin(theta)
        Rz = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        t = p - Rz @ p + np.array([0.0, 0.0, pitch * theta])
        np.testing.assert_allclose(T, make_pose(Rz, t), atol=1e-12)
        # every point on the axis moves only along the axis
        q = p + np.array([0.0, 0.0, 33.0])
        np.testing.assert_allclose(transform_points(T, q[None])[0], q + [0.0, 0.0, pitch * theta], atol=1e-12)


def test_twist_about_keeps_centre_fixed_under_rotation():
    rng = np.random.default_rng(RNG_SEED + 4)
    for _ in range(20):
        T = se3_exp(np.concatenate([rng.uniform(-200, 200, 3), _rotvecs(rng)[0]]))
        c_m = rng.uniform(-30, 30, 3)
        c_w = transform_points(T, c_m[None])[0]
        w = _unit(rng, 1)[0] * rng.uniform(0.0, 3.0)
        T2 = apply_twist(T, np.concatenate([np.zeros(3), w]), c_w)
        np.testing.assert_allclose(transform_points(T2, c_m[None])[0], c_w, atol=1e-10)
        np.testing.assert_allclose(T2[:3, :3], Rotation.from_rotvec(w).as_matrix() @ T[:3, :3], atol=1e-12)
        # a pure translation twist moves the centre by exactly v, whatever the centre
        v = rng.uniform(-10, 10, 3)
        T3 = apply_twist(T, np.concatenate([v, np.zeros(3)]), c_w)
        np.testing.assert_allclose(transform_points(T3, c_m[None])[0], c_w + v, atol=1e-10)
        np.testing.assert_allclose(T3[:3, :3], T[:3, :3], atol=0)


def test_twist_about_formula_and_first_order_motion():
    rng = np.random.default_rng(RNG_SEED + 5)
    xi = rng.standard_normal(6)
    c = rng.uniform(-100, 100, 3)
    np.testing.assert_allclose(twist_about(xi, c), np.concatenate([xi[:3] - np.cross(xi[3:], c), xi[3:]]))
    # to first order a point X moves by v + w x (X - c): the rasterizer's documented convention
    X = rng.uniform(-100, 100, (10, 3))
    eps = 1e-6
    plus = transform_points(apply_twist(np.eye(4), eps * xi, c), X)
    minus = transform_points(apply_twist(np.eye(4), -eps * xi, c), X)
    np.testing.assert_allclose((plus - minus) / (2 * eps), xi[:3] + np.cross(xi[3:], X - c), atol=1e-6)


def test_apply_twist_is_left_multiplication():
    rng = np.random.default_rng(RNG_SEED + 6)
    for _ in range(20):
        T = se3_exp(np.concatenate([rng.uniform(-200, 200, 3), _rotvecs(rng)[0]]))
        xi = np.concatenate([rng.uniform(-20, 20, 3), rng.uniform(-1, 1, 3)])
        c = rng.uniform(-100, 100, 3)
        np.testing.assert_allclose(apply_twist(T, xi, c), se3_exp(twist_about(xi, c)) @ T, atol=1e-12)
        # independent: expm of the hand-written hat of (v - w x c, w), left-multiplied
        xi_w = np.concatenate([xi[:3] - np.cross(xi[3:], c), xi[3:]])
        np.testing.assert_allclose(apply_twist(T, xi, c), expm(_hat4(xi_w)) @ T, atol=1e-9)


def test_rotation_angle_deg_matches_scipy():
    rng = np.random.default_rng(RNG_SEED + 7)
    for w in _rotvecs(rng):
        Ra = Rotation.random(random_state=int(rng.integers(1 << 31)))
        Rb = Rotation.from_rotvec(w) * Ra  # Rb = R(w) Ra; geodesic distance |w|
        ref = np.degrees((Ra.inv() * Rb).magnitude())
        got = rotation_angle_deg(Ra.as_matrix(), Rb.as_matrix())
        assert abs(got - ref) < 2e-6, (got, ref)
        assert abs(got - np.degrees(np.linalg.norm(w))) < 2e-6
        assert abs(rotation_angle_deg(Rb.as_matrix(), Ra.as_matrix()) - got) < 1e-9


def test_invert():
    rng = np.random.default_rng(RNG_SEED + 8)
    for _ in range(20):
        T = make_pose(Rotation.random(random_state=int(rng.integers(1 << 31))).as_matrix(),
                      rng.uniform(-500, 500, 3))
        Ti = invert(T)
        np.testing.assert_allclose(Ti, np.linalg.inv(T), atol=1e-12)
        np.testing.assert_allclose(Ti @ T, np.eye(4), atol=1e-12)
        X = rng.uniform(-100, 100, (5, 3))
        np.testing.assert_allclose(transform_points(Ti, transform_points(T, X)), X, atol=1e-11)


@pytest.mark.parametrize("seed", range(3))
def test_transform_points_matches_homogeneous(seed):
    rng = np.random.default_rng(seed)
    T = make_pose(Rotation.random(random_state=seed).as_matrix(), rng.uniform(-500, 500, 3))
    X = rng.uniform(-100, 100, (7, 3))
    ref = (T @ np.column_stack([X, np.ones(7)]).T).T[:, :3]
    np.testing.assert_allclose(transform_points(T, X), ref, atol=1e-12)


def test_pose_change_against_scipy():
    """pose_change: the model point's distance under the two poses, and scipy's rotation angle."""
    from scipy.spatial.transform import Rotation

    from autoalign.geometry.se3 import pose_change

    rng = np.random.default_rng(4)
    for _ in range(5):
        Ra, Rb = Rotation.random(random_state=rng), Rotation.random(random_state=rng)
        A, B = np.eye(4), np.eye(4)
        A[:3, :3], A[:3, 3] = Ra.as_matrix(), rng.normal(size=3) * 50
        B[:3, :3], B[:3, 3] = Rb.as_matrix(), rng.normal(size=3) * 50
        c = rng.normal(size=3) * 20
        mm, deg = pose_change(A, B, c)
        assert mm == pytest.approx(np.linalg.norm(Ra.apply(c) + A[:3, 3] - Rb.apply(c) - B[:3, 3]))
        assert deg == pytest.approx(np.degrees((Ra.inv() * Rb).magnitude()))


def test_symmetric_pose_change_is_zero_for_an_equivalent_pose():
    """A pose turned about a continuous symmetry axis through an offset point, or by a discrete
    symmetry, is 0 mm / 0 deg from the original; the plain change is not (rotations by scipy)."""
    from scipy.spatial.transform import Rotation

    from autoalign.geometry.se3 import make_pose, pose_change, symmetric_pose_change

    rng = np.random.default_rng(4)
    A = make_pose(Rotation.random(random_state=5).as_matrix(), rng.normal(size=3) * 100)
    centre = np.array([3.0, 1.0, 30.0])
    axis, offset = np.array([0.0, 0.0, 1.0]), np.array([2.0, -1.0, 0.0])
    R = Rotation.from_rotvec(axis * np.radians(157.0)).as_matrix()
    B = A @ make_pose(R, offset - R @ offset)
    assert pose_change(A, B, centre)[1] > 150
    assert symmetric_pose_change(A, B, centre, (), [(axis, offset)]) == pytest.approx((0.0, 0.0), abs=1e-6)
    S = make_pose(Rotation.from_rotvec([np.pi, 0.0, 0.0]).as_matrix(), np.zeros(3))
    B2 = A @ np.linalg.inv(S) @ make_pose(Rotation.from_rotvec([0.0, 0.0, 0.02]).as_matrix(), np.zeros(3))
    mm, deg = symmetric_pose_change(A, B2, np.zeros(3), [S])
    assert deg == pytest.approx(np.degrees(0.02), abs=1e-6) and mm < 1e-9
