"""Virtual-work constraint solver (ALGORITHMS.md §1, hard constraints)."""

import numpy as np
import pytest

from artrack.constraints import (
    BallJoints,
    ConstraintSolver,
    Force,
    HingeAxes,
    HingeAxis,
    OrientationGoal,
    PointCoincidence,
    PointDistance,
    PointGoal,
    apply_block_diagonal,
    assemble,
    block_inverse,
    exp_so3,
    log_so3,
    orientation_goals,
    pack_terms,
    retract,
    soft_energy_terms,
    solve_multipliers,
)
from artrack.errors import ArtrackError

BONE = np.array([0.0, 0.0, -0.3])  # each link's distal end in its own frame


def _chain(n: int = 5, hinge_at: tuple[int, ...] = (2, 4)) -> list:
    """A chain hanging from a world anchor: link 0 ball-jointed to the world point (0, 0, 1),
    link k's origin at link k-1's distal end; hinges about the local x axis at ``hinge_at``."""
    cons = [PointCoincidence(-1, np.array([0.0, 0.0, 1.0]), 0, np.zeros(3))]
    for k in range(1, n):
        cons.append(PointCoincidence(k - 1, BONE, k, np.zeros(3)))
        if k in hinge_at:
            cons.append(HingeAxis(k - 1, np.array([1.0, 0.0, 0.0]), k, np.array([1.0, 0.0, 0.0])))
    return cons


def _random_poses(rng, n):
    p = rng.normal(scale=0.5, size=(n, 3))
    R = exp_so3(rng.normal(scale=1.0, size=(n, 3)))
    return p, R


def test_so3_roundtrip():
    rng = np.random.default_rng(0)
    w = rng.normal(size=(20, 3))
    w *= (np.minimum(np.linalg.norm(w, axis=1), 3.0) / np.linalg.norm(w, axis=1))[:, None]
    np.testing.assert_allclose(log_so3(exp_so3(w)), w, atol=1e-10)
    R = exp_so3(w)
    np.testing.assert_allclose(R @ np.swapaxes(R, 1, 2), np.broadcast_to(np.eye(3), R.shape), atol=1e-12)


def test_jacobian_matches_finite_differences():
    rng = np.random.default_rng(1)
    n = 5
    cons = _chain(n) + [PointDistance(0, np.array([0.1, 0.0, 0.0]), 4, np.array([0.0, 0.05, -0.3]), 0.7)]
    p, R = _random_poses(rng, n)
    c0, J = assemble(cons, p, R)
    assert J.shape == (c0.size, 6 * n)
    eps = 1e-6
    J_fd = np.zeros(J.shape)
    for j in range(6 * n):
        d = np.zeros(6 * n)
        d[j] = eps
        cp = assemble(cons, *retract(p, R, d))[0]
        cm = assemble(cons, *retract(p, R, -d))[0]
        J_fd[:, j] = (cp - cm) / (2 * eps)
    np.testing.assert_allclose(J.toarray(), J_fd, atol=1e-7)
    # Also where the joints hold (the hinge residual's small-angle branch).
    R_ok = R.copy()
    for k in (2, 4):
        R_ok[k] = R_ok[k - 1] @ exp_so3(np.array([0.3, 0.0, 0.0]))
    _, J_ok = assemble(cons, p, R_ok)
    for j in range(6 * n):
        d = np.zeros(6 * n)
        d[j] = eps
        J_fd[:, j] = (assemble(cons, *retract(p, R_ok, d))[0] - assemble(cons, *retract(p, R_ok, -d))[0]) / (
            2 * eps
        )
    np.testing.assert_allclose(J_ok.toarray(), J_fd, atol=1e-7)
    # Sparse: each ball joint touches at most 2 links (≤ 36 non-zeros per joint).
    assert J.nnz <= 36 * len(cons)


def test_soft_force_is_minus_energy_gradient():
    rng = np.random.default_rng(2)
    p, R = _random_poses(rng, 2)
    S = np.diag([3.0, 1.0, 2.0])
    terms = [
        PointGoal(0, np.array([0.1, 0.2, -0.3]), np.array([1.0, 0.0, 0.0]), S),
        OrientationGoal(1, exp_so3(np.array([0.3, -0.2, 0.5])), S),
        Force(1, np.array([0.0, 0.0, -0.2]), np.array([0.0, 0.0, -9.81])),
    ]
    Q, _, E0 = soft_energy_terms(2, p, R, terms)
    eps = 1e-6
    for j in range(12):
        d = np.zeros(12)
        d[j] = eps
        Ep = soft_energy_terms(2, *retract(p, R, d), terms)[2]
        Em = soft_energy_terms(2, *retract(p, R, -d), terms)[2]
        assert -(Ep - Em) / (2 * eps) == pytest.approx(Q.ravel()[j], abs=1e-6)


def test_sparse_solution_equals_dense():
    rng = np.random.default_rng(3)
    n = 6
    cons = _chain(n)
    p, R = _random_poses(rng, n)
    _, J = assemble(cons, p, R)
    H = rng.normal(size=(n, 6, 6))
    H = H @ np.swapaxes(H, 1, 2) + 0.5 * np.eye(6)
    W = block_inverse(H)
    b = rng.normal(size=J.shape[0])
    lam_dense = np.linalg.solve((J @ W @ J.T).toarray(), b)
    for method in ("cg", "bicg", "dense"):
        lam = solve_multipliers(J, W, b, method)
        np.testing.assert_allclose(lam, lam_dense, rtol=1e-7, atol=1e-9 * np.abs(lam_dense).max())


def test_cg_through_the_bare_operators_gives_scipys_iterates_bit_for_bit():
    """The dense path hands scipy's cg its matrix and identity preconditioner as operators whose
    ``matvec`` is the bare product (speed only): the solution must be scipy's own on the ndarray."""
    import scipy.sparse.linalg as spla

    from artrack.constraints import _DenseSymmetricOperator, _IdentityOperator

    rng = np.random.default_rng(8)
    m = 54
    Q = rng.normal(size=(m, m))
    A = Q @ Q.T + 1e-2 * np.eye(m)
    b = rng.normal(size=m)
    want, info_want = spla.cg(A, b, rtol=1e-13, atol=0.0, maxiter=2000)
    got, info_got = spla.cg(_DenseSymmetricOperator(A), b, rtol=1e-13, atol=0.0, maxiter=2000,
                            M=_IdentityOperator(m, A.dtype))
    assert info_want == info_got == 0
    assert np.array_equal(got, want)
    np.testing.assert_allclose(A @ got, b, atol=1e-9)


@pytest.mark.parametrize("seed", range(5))
def test_constraints_satisfied_from_random_starts(seed):
    rng = np.random.default_rng(10 + seed)
    n = 5
    cons = _chain(n)
    solver = ConstraintSolver(n, cons)
    p, R = _random_poses(rng, n)  # far from consistent
    goals = [
        PointGoal(k, BONE, rng.normal(scale=0.4, size=3) + [0, 0, 0.5], np.eye(3) * 100.0) for k in range(n)
    ]
    res = solver.solve_kinematic(p, R, goals, max_iterations=100)
    assert res.converged
    assert np.linalg.norm(solver.residual(res.p, res.R)) < 1e-9
    # Hinges: the child's x axis stays parallel to the parent's.
    for k in (2, 4):
        assert np.dot(res.R[k][:, 0], res.R[k - 1][:, 0]) == pytest.approx(1.0, abs=1e-9)
    # Stationary: the applied and constraint forces balance (KKT), so this is the constrained optimum.
    Q, _, _ = soft_energy_terms(n, res.p, res.R, goals)
    _, J = assemble(cons, res.p, res.R)
    lam = np.linalg.lstsq(J.T.toarray(), -Q.ravel(), rcond=None)[0]
    assert np.linalg.norm(Q.ravel() + J.T @ lam) < 1e-3 * max(1.0, np.linalg.norm(Q))


def test_free_link_follows_goal_exactly():
    rng = np.random.default_rng(4)
    solver = ConstraintSolver(1, [])
    p_goal = np.array([[0.3, -1.2, 0.9]])
    R_goal = exp_so3(np.array([[0.4, 1.1, -0.7]]))
    local = np.array([[0.1, 0, 0], [0, 0.2, 0], [0, 0, -0.3]])
    goals = [PointGoal(0, r, p_goal[0] + R_goal[0] @ r, np.eye(3) * 50.0) for r in local]
    res = solver.solve_kinematic(np.zeros((1, 3)), np.eye(3)[None], goals)
    np.testing.assert_allclose(res.p, p_goal, atol=1e-9)
    np.testing.assert_allclose(res.R, R_goal, atol=1e-9)
    # A pose goal (point + orientation) is followed exactly too, from any start.
    p0, R0 = _random_poses(rng, 1)
    goals = [PointGoal(0, np.zeros(3), p_goal[0], np.eye(3)), OrientationGoal(0, R_goal[0], 1.0)]
    res = solver.solve_kinematic(p0, R0, goals)
    np.testing.assert_allclose(res.p, p_goal, atol=1e-9)
    np.testing.assert_allclose(res.R, R_goal, atol=1e-9)


def test_reachable_goals_are_met_with_constraints():
    # Goals taken from a consistent configuration: the solver recovers it (the chain is exact).
    rng = np.random.default_rng(5)
    n = 4
    cons = _chain(n, hinge_at=(2,))
    solver = ConstraintSolver(n, cons)
    # Build a consistent chain by forward kinematics.
    R_true = exp_so3(rng.normal(scale=0.6, size=(n, 3)))
    ang = 0.8
    R_true[2] = R_true[1] @ exp_so3(np.array([ang, 0.0, 0.0]))
    p_true = np.zeros((n, 3))
    p_true[0] = [0.0, 0.0, 1.0]
    for k in range(1, n):
        p_true[k] = p_true[k - 1] + R_true[k - 1] @ BONE
    assert np.linalg.norm(solver.residual(p_true, R_true)) < 1e-12
    goals = [PointGoal(k, BONE, p_true[k] + R_true[k] @ BONE, np.eye(3)) for k in range(n)]
    goals += [OrientationGoal(k, R_true[k], 0.01) for k in range(n)]
    p0, R0 = retract(p_true, R_true, rng.normal(scale=0.2, size=(n, 6)))
    res = solver.solve_kinematic(p0, R0, goals, max_iterations=50)
    np.testing.assert_allclose(res.p, p_true, atol=1e-6)
    np.testing.assert_allclose(res.R, R_true, atol=1e-6)


def test_point_masses_with_distance_constraints():
    # Particle model: three "links" used as points, a rigid triangle of bones.
    n = 3
    L = {(0, 1): 0.5, (1, 2): 0.4, (0, 2): 0.6}
    cons = [PointDistance(a, np.zeros(3), b, np.zeros(3), d) for (a, b), d in L.items()]
    solver = ConstraintSolver(n, cons)
    targets = np.array([[0.0, 0, 0], [1.0, 0, 0], [0.0, 1.0, 0]])
    goals = [PointGoal(k, np.zeros(3), targets[k], np.eye(3)) for k in range(n)]
    res = solver.solve_kinematic(
        targets + 0.01, np.broadcast_to(np.eye(3), (n, 3, 3)), goals, max_iterations=60
    )
    for (a, b), d in L.items():
        assert np.linalg.norm(res.p[a] - res.p[b]) == pytest.approx(d, abs=1e-9)


def test_dynamic_pendulum_period_and_constraints():
    # One link hanging from a world pivot at its origin: a compound pendulum.
    m, length = 1.0, 0.5
    com = np.array([0.0, 0.0, -length])
    inertia = np.eye(3) * 1e-3  # about the centre of mass
    solver = ConstraintSolver(
        1,
        [PointCoincidence(-1, np.zeros(3), 0, np.zeros(3))],
        np.array([m]),
        inertia[None],
        centres_of_mass=com[None],
    )
    theta0 = 0.1
    p, R = np.zeros((1, 3)), exp_so3(np.array([[theta0, 0.0, 0.0]]))
    nu = np.zeros((1, 6))
    dt, g = 2e-3, 9.81
    gravity = [Force(0, com, np.array([0.0, 0.0, -m * g]))]
    angles = []
    for _ in range(1500):
        res = solver.step_dynamic(p, R, nu, dt, gravity)
        p, R, nu = res.p, res.R, res.nu
        assert res.constraint_norm < 1e-9
        angles.append(np.arctan2(-(R[0] @ com)[1], -(R[0] @ com)[2]))
    angles = np.asarray(angles)
    crossings = np.flatnonzero(np.diff(np.sign(angles)) > 0) * dt
    period = np.mean(np.diff(crossings))
    expected = 2 * np.pi * np.sqrt((inertia[0, 0] + m * length**2) / (m * g * length))
    assert period == pytest.approx(expected, rel=0.02)
    assert np.max(np.abs(angles[-250:])) == pytest.approx(theta0, rel=0.05)  # little numerical damping


def test_dynamic_springs_settle_on_goal_with_constraints():
    n = 3
    cons = _chain(n, hinge_at=(1,))
    solver = ConstraintSolver(n, cons, masses=np.array([2.0, 1.5, 0.5]))
    p = np.array([[0.0, 0.0, 1.0], [0.0, 0.0, 0.7], [0.0, 0.0, 0.4]])
    R = np.broadcast_to(np.eye(3), (n, 3, 3)).copy()
    nu = np.zeros((n, 6))
    target = np.array([0.0, 0.45, 0.6])
    goals = [PointGoal(2, BONE, target, np.eye(3) * 400.0)]
    for _ in range(300):  # stiff springs at a video frame rate: implicit springs keep it stable
        res = solver.step_dynamic(p, R, nu, 1.0 / 30.0, goals, linear_damping=5.0, angular_damping=5.0)
        p, R, nu = res.p, res.R, res.nu
        assert res.constraint_norm < 1e-9
    np.testing.assert_allclose(p[2] + R[2] @ BONE, target, atol=1e-3)
    assert np.max(np.abs(nu)) < 1e-3


def test_stiffness_damping_settles_a_light_link_on_a_stiff_spring():
    """A hand-sized body (0.5 kg, spin inertia 3e-4 kg m²) on a 150 N m/rad torsional spring: with
    mass-proportional damping alone it rings (its frequency, ~700 rad/s, is far above what 8 /s damps);
    stiffness-proportional (Rayleigh) damping ``β K`` settles it without overshoot. β = 0 is the old step."""
    crossings = {}
    for beta in (0.0, 0.01):
        solver = ConstraintSolver(1, [], masses=np.array([0.5]), inertias=np.diag([6e-4, 6e-4, 3e-4])[None])
        p, R, nu = np.zeros((1, 3)), exp_so3(np.array([[0.0, 0.0, 0.3]])), np.zeros((1, 6))
        goal = [OrientationGoal(0, np.eye(3), 150.0)]
        angle = []
        for _ in range(60):
            res = solver.step_dynamic(p, R, nu, 1.0 / 120.0, goal, 8.0, 8.0, stiffness_damping=beta)
            p, R, nu = res.p, res.R, res.nu
            angle.append(float(log_so3(R)[0, 2]))
        crossings[beta] = int(np.sum(np.diff(np.sign(angle)) != 0))
        assert abs(angle[-1]) < 1e-3
        if beta > 0:
            assert min(angle) > -1e-6  # no overshoot past the goal
    assert crossings[0.0] >= 5 and crossings[0.01] == 0, crossings


def test_bad_input():
    with pytest.raises(ArtrackError):
        ConstraintSolver(2, [PointCoincidence(0, np.zeros(3), 5, np.zeros(3))])
    solver = ConstraintSolver(2, [])
    with pytest.raises(ArtrackError):
        solver.solve_kinematic(np.zeros((3, 3)), np.zeros((2, 3, 3)), [])
    with pytest.raises(ArtrackError):
        solve_multipliers(
            assemble(_chain(2), np.zeros((2, 3)), np.broadcast_to(np.eye(3), (2, 3, 3)))[1],
            block_inverse(np.broadcast_to(np.eye(6), (2, 6, 6))),
            np.ones(6),
            "lu",
        )


def test_batched_constraints_match_single():
    rng = np.random.default_rng(7)
    n = 5
    p, R = _random_poses(rng, n)
    a, b = np.array([0, 1, 1, 3]), np.array([1, 2, 3, 4])
    pa, pb = rng.normal(size=(4, 3)), rng.normal(size=(4, 3))
    ua, ub = rng.normal(size=(4, 3)), rng.normal(size=(4, 3))
    single = [PointCoincidence(a[k], pa[k], b[k], pb[k]) for k in range(4)]
    single += [HingeAxis(a[k], ua[k], b[k], ub[k]) for k in range(4)]
    batched = [BallJoints(a, pa, b, pb), HingeAxes(a, ua, b, ub)]
    c1, J1 = assemble(single, p, R)
    c2, J2 = assemble(batched, p, R)
    np.testing.assert_allclose(c2, c1, atol=1e-12)
    np.testing.assert_allclose(J2.toarray(), J1.toarray(), atol=1e-12)
    # the one-pass residual + Jacobian agree with the separate calls, and dense assembly with sparse
    for con in batched:
        c_k, triplets = con.residual_and_triplets(p, R)
        np.testing.assert_array_equal(c_k, con.residual(p, R))
        for got, want in zip(triplets, con.triplets(p, R), strict=True):
            np.testing.assert_array_equal(got, want)
    c3, J3 = assemble(single, p, R, dense=True)
    assert isinstance(J3, np.ndarray)
    np.testing.assert_array_equal(c3, c1)
    np.testing.assert_allclose(J3, J1.toarray(), atol=1e-15)


def test_packed_terms_equal_the_term_list():
    """PackedTerms (what the solver iterates on) give the list's forces, stiffness and energy;
    ``+`` joins packs as list concatenation does; orientation_goals packs torsional springs."""
    rng = np.random.default_rng(11)
    p, R = _random_poses(rng, 3)
    S = np.diag([3.0, 1.0, 2.0])
    goals = [
        PointGoal(0, np.array([0.1, 0.2, -0.3]), np.array([1.0, 0.0, 0.0]), S),
        PointGoal(2, np.zeros(3), np.array([0.0, 1.0, 0.5]), 2.0 * S),
        Force(1, np.array([0.0, 0.0, -0.2]), np.array([0.0, 0.0, -9.81])),
    ]
    targets = exp_so3(rng.normal(size=(2, 3)))
    springs = [OrientationGoal(1, targets[0], 4.0), OrientationGoal(2, targets[1], 4.0)]
    for second_order in (False, True):
        want = soft_energy_terms(3, p, R, goals + springs, second_order)
        got = soft_energy_terms(3, p, R, pack_terms(goals) + orientation_goals([1, 2], targets, 4.0), second_order)
        for g, w in zip(got, want, strict=True):
            np.testing.assert_allclose(g, w, rtol=1e-13, atol=1e-13)
    assert len(pack_terms(goals) + pack_terms(springs)) == 5
    with pytest.raises(ArtrackError, match="unknown soft term"):
        pack_terms([object()])


def test_dense_and_sparse_solver_paths_agree():
    """Small systems run on dense arrays with W as (L, 6, 6) blocks, large ones on scipy.sparse:
    the same solve either way (the kinematic solve and the multipliers)."""
    rng = np.random.default_rng(12)
    n = 6
    cons = _chain(n)
    p, R = _random_poses(rng, n)
    goals = [PointGoal(k, BONE, rng.normal(scale=0.4, size=3), np.eye(3) * 100.0) for k in range(n)]
    dense = ConstraintSolver(n, cons)
    sparse = ConstraintSolver(n, cons)
    sparse._dense = False
    assert dense._dense
    a = dense.solve_kinematic(p, R, goals, max_iterations=100)
    b = sparse.solve_kinematic(p, R, goals, max_iterations=100)
    assert a.converged and b.converged
    # (a link's spin about its bone is free of the point goals: compare the points, not R)
    np.testing.assert_allclose(a.p, b.p, atol=1e-7)
    np.testing.assert_allclose(a.R @ BONE, b.R @ BONE, atol=1e-7)
    assert a.energy == pytest.approx(b.energy, rel=1e-9)
    H = rng.normal(size=(n, 6, 6))
    H = H @ np.swapaxes(H, 1, 2) + 0.5 * np.eye(6)
    x = rng.normal(size=6 * n)
    np.testing.assert_allclose(apply_block_diagonal(block_inverse(H, as_blocks=True), x), block_inverse(H) @ x)
    _, J = assemble(cons, p, R)
    _, Jd = assemble(cons, p, R, dense=True)
    rhs = rng.normal(size=J.shape[0])
    want = solve_multipliers(J, block_inverse(H), rhs, "dense")
    blocks, sparse_W = block_inverse(H, as_blocks=True), block_inverse(H)
    for J_k, W_k in ((Jd, blocks), (Jd, sparse_W), (J, blocks)):
        got = solve_multipliers(J_k, W_k, rhs, "cg")  # dense or sparse J, W sparse or as blocks
        np.testing.assert_allclose(got, want, rtol=1e-7, atol=1e-9 * np.abs(want).max())
