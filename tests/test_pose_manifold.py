"""Tests of artrack.pose_manifold: chain forward kinematics, Jacobian, projection onto M
(ALGORITHMS.md §3 eqs. (2)-(4))."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.optimize import least_squares

from artrack.body_model import load_body_model
from artrack.motion import pose_at
from artrack.pose_manifold import PoseManifold, left_jacobian_so3


@pytest.fixture(scope="module")
def body():
    return load_body_model()


@pytest.fixture(scope="module")
def manifold(body):
    return PoseManifold(body, pose_at("default", 8.0, body))


def _random_inside(M, rng, n):
    return M.lower + (M.upper - M.lower) * rng.uniform(0.1, 0.9, (n, M.d))


def test_forward_kinematics_hand_computed(body):
    """Left arm raised sideways (abduction π/2), elbow flexed π/2, everything else at rest."""
    theta = body.rest_pose()
    theta[body.dof_slice("l_upper_arm")] = [np.pi / 2, 0.0, 0.0]
    theta[body.dof_slice("l_forearm")] = np.pi / 2
    M = PoseManifold(body, theta)
    pts = M.end_points(M.active(theta)[None])[0]
    # shoulder = pelvis (0, 0, 0.95) + torso offset (0, 0, 0.10) + shoulder offset (0, 0.19, 0.37)
    # elbow: R_x(π/2) (0, 0, -0.29) = (0, 0.29, 0); forearm about -y by π/2: (0, 0, -0.25) -> (0.25, 0, 0)
    # grip: 0.075 m further along the forearm
    expect = {"l_upper_arm": [0.0, 0.48, 1.42], "l_forearm": [0.25, 0.48, 1.42], "l_hand": [0.325, 0.48, 1.42],
              "torso": [0.0, 0.0, 1.47], "r_forearm": [0.0, -0.19, 0.88]}
    for name, p in expect.items():
        np.testing.assert_allclose(pts[M.point_names.index(name)], p, atol=1e-12)
    # the body model's own forward kinematics agrees
    T = body.forward_kinematics(theta)
    np.testing.assert_allclose(T[body.link_index("l_hand"), :3, 3], [0.25, 0.48, 1.42], atol=1e-12)


def test_batched_chain_fk_equals_single_pose_body_fk(body, manifold):
    rng = np.random.default_rng(1)
    th = _random_inside(manifold, rng, 40)
    batch = manifold.end_points(th)
    for k in range(len(th)):
        full = manifold.full_theta(th[k])
        T = body.forward_kinematics(full)                      # single pose
        ref = body.transform_points(T, manifold.point_link_idx, manifold.point_local)
        np.testing.assert_allclose(batch[k], ref, atol=1e-12)
    # and the body model's FK is itself batched consistently
    Tb = body.forward_kinematics(manifold.full_theta(th))
    np.testing.assert_allclose(Tb[7], body.forward_kinematics(manifold.full_theta(th[7])), atol=1e-12)


def test_jacobian_matches_finite_differences(manifold):
    rng = np.random.default_rng(2)
    th = _random_inside(manifold, rng, 5)
    _, J = manifold.jacobian(th)
    eps = 1e-6
    for k in range(manifold.d):
        e = np.zeros(manifold.d)
        e[k] = eps
        fd = (manifold.end_points(th + e) - manifold.end_points(th - e)) / (2 * eps)
        np.testing.assert_allclose(J[..., k], fd, atol=1e-8)


def test_left_jacobian_small_and_large_angles():
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(3)
    for r in [np.zeros(3), 1e-8 * rng.normal(size=3), rng.normal(size=3)]:
        d = 1e-7 * rng.normal(size=3)
        lhs = Rotation.from_rotvec(r + d).as_matrix()
        rhs = Rotation.from_rotvec(left_jacobian_so3(r) @ d).as_matrix() @ Rotation.from_rotvec(r).as_matrix()
        np.testing.assert_allclose(lhs, rhs, atol=1e-12)


def test_projection_of_reachable_points_recovers_them(manifold):
    rng = np.random.default_rng(4)
    truth = _random_inside(manifold, rng, 50)
    x = manifold.end_points(truth)
    start = manifold.clip(truth + rng.normal(0.0, 0.15, truth.shape))
    th, info = manifold.project(x, start, max_iter=200, tol=0.0)
    assert np.all((th >= manifold.lower) & (th <= manifold.upper))
    # end points reached (the pose itself may differ in directions that move no end point)
    np.testing.assert_allclose(manifold.end_points(th), x, atol=1e-4)


def _generic_best(manifold, x, w, reg, start, starts):
    """Lowest cost of a generic bounded least_squares (finite-difference Jacobian) over starts."""
    w3 = np.repeat(w, 3)

    def resid(q):
        r = w3 * (manifold.end_points(q[None])[0] - x).ravel()
        return np.concatenate([r, reg * (q - start)]) if reg > 0 else r

    return min(least_squares(resid, s, bounds=(manifold.lower, manifold.upper), xtol=1e-12, ftol=1e-12,
                             gtol=1e-12, max_nfev=2000).cost for s in starts)


@pytest.mark.parametrize("reg", [0.0, 0.05])
def test_projection_is_the_nearest_reachable_point(manifold, reg):
    """Samples near M (2 cm noise): the batched projection from the previous pose reaches the
    global minimum found by a generic optimiser from the same start and 6 random starts."""
    rng = np.random.default_rng(5)
    n = 6
    truth = _random_inside(manifold, rng, n)
    start = manifold.clip(truth + rng.normal(0.0, 0.1, truth.shape))
    x = manifold.end_points(truth) + rng.normal(0.0, 0.02, (n, manifold.P, 3))
    w = np.ones(manifold.P)
    w[manifold.hand_points] = 5.0
    th, info = manifold.project(x, start, w, reg=reg, max_iter=400, tol=0.0)
    th_sp, info_sp = manifold.project_scipy(x, start, w, reg=reg)
    assert np.all((th >= manifold.lower) & (th <= manifold.upper))
    assert np.all((th_sp >= manifold.lower) & (th_sp <= manifold.upper))
    for k in range(n):
        best = _generic_best(manifold, x[k], w, reg, start[k], [start[k]] + list(_random_inside(manifold, rng, 6)))
        assert info.cost[k] <= best * (1 + 1e-6) + 1e-12, (k, info.cost[k], best)
        assert info_sp.cost[k] <= best * (1 + 1e-6) + 1e-12, (k, info_sp.cost[k], best)


def test_projection_of_unreachable_points_is_a_constrained_local_minimum(manifold):
    """Targets far off M (an elbow 25 cm too high): joints end at their limits; the result is at
    least as good as the generic optimiser's from the same start, and no feasible direction
    lowers the cost (projected gradient zero). (The manifold is not convex: from far away a
    local method may miss a better basin, see README.)"""
    rng = np.random.default_rng(6)
    n = 6
    truth = _random_inside(manifold, rng, n)
    start = manifold.clip(truth + rng.normal(0.0, 0.1, truth.shape))
    x = manifold.end_points(truth) + rng.normal(0.0, 0.03, (n, manifold.P, 3))
    x[:, 3] += [0.0, 0.0, 0.25]
    w = np.ones(manifold.P)
    th, info = manifold.project(x, start, w, max_iter=400, tol=0.0)
    assert np.all((th >= manifold.lower) & (th <= manifold.upper))
    at_bound = (th <= manifold.lower + 1e-12) | (th >= manifold.upper - 1e-12)
    assert at_bound.any()
    X, J = manifold.jacobian(th)
    g = np.einsum("npcd,npc->nd", J, X - x)
    g_proj = np.where(th <= manifold.lower + 1e-12, np.minimum(g, 0.0),
                      np.where(th >= manifold.upper - 1e-12, np.maximum(g, 0.0), g))
    assert np.abs(g_proj).max() < 1e-6
    for k in range(n):
        local = _generic_best(manifold, x[k], w, 0.0, start[k], [start[k]])
        assert info.cost[k] <= local * (1 + 1e-6) + 1e-12, (k, info.cost[k], local)
