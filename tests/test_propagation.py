"""O(N) propagation of articulation constraints (ALGORITHMS.md §2, Algorithm 1) against a dense KKT solve."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from artrack.lie import adjoint, exp_se3, inverse_se3, log_se3, make_se3, skew
from artrack.propagation import (
    Joint,
    articulated_update,
    coerce_constraints,
    constraint_matrices,
    constraint_residuals,
    dense_kkt_solve,
    joint_rows,
    propagate,
    propagate_reference,
    tree_schedule,
)


def random_parents(rng: np.random.Generator, n: int, kind: str) -> np.ndarray:
    if kind == "chain":
        return np.r_[-1, np.arange(n - 1)]
    if kind == "star":
        return np.r_[-1, np.zeros(n - 1, dtype=int)]
    par = np.r_[-1, [rng.integers(max(0, i - 8), i) for i in range(1, n)]]
    perm = rng.permutation(n)  # indices need not be topologically ordered
    inv = np.argsort(perm)
    out = np.full(n, -1)
    for i in range(n):
        if par[i] >= 0:
            out[inv[i]] = inv[par[i]]
    return out


def random_joints(rng: np.random.Generator, n: int, parents: np.ndarray) -> list[Joint | None]:
    return [
        None
        if parents[i] < 0
        else Joint("hinge" if rng.random() < 0.5 else "ball", rng.normal(size=3) * 0.2, rng.normal(size=3))
        for i in range(n)
    ]


def random_stats(rng: np.random.Generator, n: int, rank5_fraction: float = 0.0):
    L = rng.normal(size=(n, 6, 6))
    C = L @ np.swapaxes(L, 1, 2) + 0.05 * np.eye(6)
    for i in np.flatnonzero(rng.random(n) < rank5_fraction):  # single-quadric components
        J = rng.normal(size=(40, 6))
        J[:, 5] = 0.0
        C[i] = J.T @ J
    return rng.normal(size=(n, 6)) * 0.05, C


def random_problem(seed: int, n: int, kind: str, rank5_fraction: float = 0.0):
    rng = np.random.default_rng(seed)
    parents = random_parents(rng, n, kind)
    E = make_se3(Rotation.random(n, random_state=rng).as_matrix(), rng.normal(size=(n, 3)))
    joints = random_joints(rng, n, parents)
    xi_hat, C = random_stats(rng, n, rank5_fraction)
    return xi_hat, C, parents, E, joints


@pytest.mark.parametrize("kind", ["tree", "chain", "star"])
@pytest.mark.parametrize("n", [10, 37, 200])
def test_propagation_equals_dense_kkt(n, kind):
    xi_hat, C, parents, E, joints = random_problem(100 + n, n, kind)
    D12, D21, mask = constraint_matrices(E, parents, joints)
    xi = propagate(xi_hat, C, parents, D12, D21, mask)
    dense = dense_kkt_solve(xi_hat, C, parents, D12, D21, mask)
    assert np.max(np.abs(xi - dense)) < 1e-8
    assert np.max(np.abs(constraint_residuals(xi, parents, D12, D21))) < 1e-10
    # the literal per-node transcription of eqs. 19, 21, 22 agrees too
    ref = propagate_reference(xi_hat, C, parents, D12, D21, mask)
    assert np.max(np.abs(xi - ref)) < 1e-8


def test_forest_and_rank_deficient_components():
    rng = np.random.default_rng(5)
    n = 60
    parents = random_parents(rng, n, "tree")
    parents[[17, 40]] = -1  # three separate trees
    E = make_se3(Rotation.random(n, random_state=rng).as_matrix(), rng.normal(size=(n, 3)))
    joints = random_joints(rng, n, parents)
    xi_hat, C = random_stats(rng, n, rank5_fraction=0.5)
    D12, D21, mask = constraint_matrices(E, parents, joints)
    # random joint points near a rank-5 component's unobserved axis make this problem ill-conditioned
    # (condition ~1e5 after regularisation); the default eps = 1e-9 still agrees to ~5e-9 here
    for eps, tol in ((1e-7, 1e-9), (1e-9, 3e-8)):
        xi = propagate(xi_hat, C, parents, D12, D21, mask, eps=eps)
        dense = dense_kkt_solve(xi_hat, C, parents, D12, D21, mask, eps=eps)
        assert np.max(np.abs(xi - dense)) < tol, eps
        assert np.max(np.abs(constraint_residuals(xi, parents, D12, D21))) < tol


def test_optimality_by_perturbation():
    """No feasible perturbation lowers the cost (checks the dense solver's problem statement too)."""
    xi_hat, C, parents, E, joints = random_problem(9, 25, "tree")
    D12, D21, mask = constraint_matrices(E, parents, joints)
    xi = propagate(xi_hat, C, parents, D12, D21, mask)

    def cost(x):
        d = x - xi_hat
        return np.einsum("ni,nij,nj->", d, C, d)

    # feasible directions: null space of the stacked constraint matrix
    n = len(parents)
    rows = []
    for i in np.flatnonzero(parents >= 0):
        for r in np.flatnonzero(mask[i]):
            row = np.zeros(6 * n)
            row[6 * i : 6 * i + 6] = D12[i, r]
            row[6 * parents[i] : 6 * parents[i] + 6] += D21[i, r]
            rows.append(row)
    _, _, Vt = np.linalg.svd(np.array(rows))
    null = Vt[len(rows) :]
    rng = np.random.default_rng(0)
    c0 = cost(xi)
    for _ in range(20):
        step = (rng.normal(size=len(null)) @ null).reshape(n, 6) * 1e-3
        assert cost(xi + step) >= c0 - 1e-12


def test_ball_joint_rows_are_the_joint_point_velocity():
    """D12 xi is the first-order motion of the joint point (sign check against our generators)."""
    rng = np.random.default_rng(1)
    p = rng.normal(size=3)
    D = joint_rows(Joint("ball", p))
    xi = rng.normal(size=6)
    h = 1e-6
    vel = ((exp_se3(h * xi) - exp_se3(-h * xi)) @ np.r_[p, 1.0])[:3] / (2 * h)
    assert np.allclose(D @ xi, vel, atol=1e-7)
    printed = np.hstack([np.eye(3), skew(p)])  # ALGORITHMS.md eq. 12 as printed: the velocity of -p
    assert not np.allclose(printed @ xi, vel, atol=1e-3)
    assert np.allclose(
        printed @ xi, ((exp_se3(h * xi) - exp_se3(-h * xi)) @ np.r_[-p, 1.0])[:3] / (2 * h), atol=1e-7
    )


def test_linearised_constraint_keeps_joints_together_to_first_order():
    """Motions with D12 xi1 + D21 xi2 = 0 move the joint identically in both components (camera frame)."""
    rng = np.random.default_rng(2)
    E1, E2 = make_se3(Rotation.random(2, random_state=rng).as_matrix(), rng.normal(size=(2, 3)))
    for kind in ("ball", "hinge"):
        j = Joint(kind, rng.normal(size=3) * 0.3, rng.normal(size=3))
        E1_ok = E1.copy()
        D12, D21, _ = constraint_matrices(np.stack([E2, E1_ok]), [-1, 0], [None, j])
        A, B = D12[1, : j.n_rows], D21[1, : j.n_rows]
        xi2 = rng.normal(size=6)
        # a feasible xi1: least-norm solution of A xi1 = -B xi2 plus a null-space part
        xi1 = np.linalg.lstsq(A, -B @ xi2, rcond=None)[0]
        _, _, Vt = np.linalg.svd(A)
        xi1 = xi1 + Vt[j.n_rows :].T @ rng.normal(size=6 - j.n_rows)
        pj = np.r_[j.point, 1.0]
        rel = inverse_se3(E2) @ E1
        errs = []
        for t in (1e-2, 5e-3):
            a = E1 @ exp_se3(t * xi1) @ pj
            b = E2 @ exp_se3(t * xi2) @ rel @ pj
            errs.append(np.linalg.norm(a - b))
        assert errs[1] < errs[0] / 3.0  # second order: halving t quarters the gap
        if kind == "hinge":  # relative rotation only about the hinge axis, to first order
            w_rel = xi1[3:] - (adjoint(inverse_se3(rel)) @ xi2)[3:]
            assert np.allclose(np.cross(w_rel, j.axis), 0, atol=1e-9)


def make_body(rng: np.random.Generator, n: int):
    """A chain/tree whose poses satisfy their joints exactly: child frame origin at the joint."""
    parents = random_parents(rng, n, "tree")
    sched = tree_schedule(parents)
    E = np.zeros((n, 4, 4))
    joints: list[Joint | None] = [None] * n
    for i in sched.order:
        if parents[i] < 0:
            E[i] = make_se3(Rotation.random(random_state=rng).as_matrix(), rng.normal(size=3))
            continue
        T0 = make_se3(np.eye(3), rng.normal(size=3) * 0.3)  # parent <- child at rest
        kind = "hinge" if rng.random() < 0.5 else "ball"
        axis = rng.normal(size=3)
        joints[i] = Joint(kind, np.zeros(3), axis / np.linalg.norm(axis), parent_from_child=T0)
        if kind == "ball":
            R = Rotation.random(random_state=rng).as_matrix()
        else:
            R = Rotation.from_rotvec(joints[i].axis * rng.uniform(-2.5, 2.5)).as_matrix()
        E[i] = E[parents[i]] @ T0 @ make_se3(R, np.zeros(3))
    return parents, E, joints


def joint_violation(E, parents, joints) -> float:
    worst = 0.0
    for i, j in enumerate(joints):
        if j is None:
            continue
        rel = inverse_se3(j.parent_from_child) @ inverse_se3(E[parents[i]]) @ E[i]
        a = log_se3(rel)
        worst = max(worst, float(np.abs(joint_rows(j) @ a).max()))
    return worst


def test_coerce_makes_joints_exact_and_leaves_valid_poses_alone():
    rng = np.random.default_rng(3)
    parents, E, joints = make_body(rng, 30)
    assert joint_violation(E, parents, joints) < 1e-9
    assert np.allclose(coerce_constraints(E, parents, joints), E, atol=1e-9)
    # a linearised update leaves a second-order violation; coercion removes it
    D12, D21, mask = constraint_matrices(E, parents, joints)
    xi_hat, C = random_stats(rng, 30)
    xi = propagate(xi_hat, C, parents, D12, D21, mask)
    moved = E @ exp_se3(xi)
    violation = joint_violation(moved, parents, joints)
    assert violation > 1e-5
    fixed = coerce_constraints(moved, parents, joints)
    assert joint_violation(fixed, parents, joints) < 1e-9
    # only the small (second-order) violation was removed
    assert np.max(np.abs(fixed - moved)) < 20 * violation
    # joint points coincide exactly in the camera frame
    for i, j in enumerate(joints):
        if j is not None:
            a = fixed[i] @ np.r_[j.point, 1.0]
            b = fixed[parents[i]] @ j.parent_from_child @ np.r_[j.point, 1.0]
            assert np.allclose(a, b, atol=1e-10)


def test_articulated_update_recovers_a_consistent_motion():
    rng = np.random.default_rng(4)
    parents, E, joints = make_body(rng, 20)
    D12, D21, mask = constraint_matrices(E, parents, joints)
    # a feasible true motion: project random motions onto the constraint set (dense, identity metric)
    xi_true = dense_kkt_solve(
        rng.normal(size=(20, 6)) * 0.01, np.tile(np.eye(6), (20, 1, 1)), parents, D12, D21, mask
    )
    _, C = random_stats(rng, 20, rank5_fraction=0.5)
    noisy = xi_true + rng.normal(size=xi_true.shape) * 1e-4
    E_new, xi = articulated_update(E, noisy, C, parents, joints)
    assert np.max(np.abs(xi - xi_true)) < 1e-3
    assert joint_violation(E_new, parents, joints) < 1e-9
    exact = articulated_update(E, xi_true, C, parents, joints)[1]
    assert np.max(np.abs(exact - xi_true)) < 1e-7


def test_bad_trees_raise():
    with pytest.raises(ValueError):
        tree_schedule([1, 0])  # cycle, no root
    with pytest.raises(ValueError):
        tree_schedule([-1, 2, 1])  # cycle below a root
    with pytest.raises(ValueError):
        Joint("hinge", np.zeros(3))
    with pytest.raises(ValueError):
        constraint_matrices(np.tile(np.eye(4), (2, 1, 1)), [-1, 0], [None, None])
