"""Articulation constraints propagated through a kinematic tree in O(N) — ALGORITHMS.md §2, Algorithm 1.

Problem (paper §4, eqs. 8, 11, 20). Component i (0..N-1) has its own motion estimate
``xi_hat_i`` (6,) and information ``C_i`` (6, 6), both in its own frame (from
:func:`artrack.edges.motion_statistics`). The tree is given by ``parents`` (N,) (-1 for
a root; a forest is allowed; no cycles). Each non-root i is joined to its parent
p by a linearised joint ``D12_i xi_i + D21_i xi_p = 0`` (child = component "1",
parent = component "2" of the paper). We want

    minimise  sum_i (xi_i - xi_hat_i)^T C_i (xi_i - xi_hat_i)   s.t. every joint holds.

Joint rows (:func:`joint_rows`), for a joint at ``p = (x, y, z)`` in the *child* frame:

* ball (3 rows): ``D12 = [I | -skew(p)]`` = rows ``[1,0,0, 0,z,-y], [0,1,0, -z,0,x], [0,0,1, y,-x,0]``,
  the first-order velocity ``v + w x p`` of the joint point under the generators of
  :mod:`artrack.lie`. **Sign note:** the matrix printed in ALGORITHMS.md / paper eq. 12,
  ``[I | +skew(p)]``, is the velocity of the point ``-p`` with these (standard, right-handed)
  generators; it is right only for generators with the opposite rotation sign. We use the
  matrix consistent with our generators (checked by finite differences in the tests). The two
  agree when the joint is at the child frame's origin (p = 0), the usual body-model layout.
* hinge (5 rows): the ball rows plus ``[0 | u1^T]``, ``[0 | u2^T]`` with u1, u2 unit vectors
  orthogonal to the hinge axis (child frame): the relative rotation is about the axis only.

``D21 = -D12 Ad(E1^-1 E2)`` (eq. 14) re-expresses the parent's motion in the child frame
(``E`` = component -> camera; only ``E1^-1 E2`` = parent -> child matters).

Algorithm 1 (:func:`propagate`). Leaves to root, marginalise each child into its parent
(eqs. 21, 22), with ``S = D12 C1^-1 D12^T``:

    C2'   = C2 + D21^T S^-1 D21
    xi2'  = xi2 - C2^-1 D21^T (S + D21 C2^-1 D21^T)^-1 (D12 xi1 + D21 xi2)

then the root takes ``xi = xi_hat'`` and, root to leaves, each child takes the best motion
consistent with its parent's final ``xi2`` (eq. 19):

    xi1 = xi1' - C1'^-1 D12^T S^-1 (D21 xi2 + D12 xi1').

**Derivation check (the issue asked for it).** Given xi2, minimising
``(xi1 - xi1')^T C1' (xi1 - xi1')`` subject to ``D12 xi1 = -D21 xi2`` gives eq. 19 and the minimum
``r^T S^-1 r`` with ``r = D12 xi1' + D21 xi2``. Adding the parent's own term and collecting
powers of xi2: the information becomes ``C2 + D21^T S^-1 D21`` — eq. 22 as printed is **correct** —
and the information vector ``eta2 = C2 xi2`` becomes ``eta2' = eta2 - D21^T S^-1 D12 xi1'``; by the
push-through identity ``(C2 + D21^T S^-1 D21)^-1 D21^T S^-1 = C2^-1 D21^T (S + D21 C2^-1 D21^T)^-1``
this is exactly eq. 21. So the printed formulas are right, with two conditions the text leaves
implicit: ``xi1', C1'`` in eqs. 19 and 21 are the child's *propagated* statistics (its own
children already folded in), and a parent with several children takes them one after another
(eq. 21 uses the parent's running ``C2``). The only correction needed in the ALGORITHMS.md text is
the sign of the rotation block of the ball-joint matrix (above).

Implementation. We run eqs. 21/22 in the equivalent information form
``(C, eta = C xi_hat)``: the updates of several children of one parent then simply add, and
the tree is processed level by level (all nodes of one depth at once, batched 6x6 numpy
algebra, ``np.linalg.inv`` on stacks; levels of a single node, as in a chain, use plain 2-D
arrays to save numpy call overhead), so the cost is linear in N for any tree shape.
:func:`propagate_reference` is a literal per-node transcription of eqs. 19, 21, 22
(used by the tests to show the two agree). Joints of 3 and 5 rows share padded (N, 5, 6)
arrays: unused rows are zero and get a unit diagonal in ``S``, which leaves the result unchanged.

Regularisation. A component seen as one quadric has a rank-5 ``C`` (a cylinder's outline
rank 4); the joints fix the missing directions, but eqs. 19/21 invert ``C``. Every
``C_i`` is therefore replaced by ``C_i + eps * max(trace(C_i)/6, tiny) * I`` (relative ``eps``,
default 1e-9): a very weak prior pulling each component toward its own ``xi_hat`` (for a
minimum-norm ``xi_hat``, toward no motion along unobserved directions). :func:`dense_kkt_solve`
uses the same regularised ``C`` so that the two solve the same problem. Eqs. 19/21 invert the
regularised ``C`` (condition up to ~1/eps) where the KKT solve does not, so on ill-conditioned
problems the two agree to about ``1e-16 / eps`` relative; a larger ``eps`` trades bias for accuracy.

Coercion (:func:`coerce_constraints`, paper eqs. 23-25). The linearised update leaves a
second-order violation. Root to leaves, with ``T0`` the joint's reference parent<-child
transform (:attr:`Joint.parent_from_child`, identity by default as in the paper):
``a = log(T0^-1 E2^-1 E1)``, ``a' = a - D12^T (D12 D12^T)^-1 D12 a`` (projection onto the null
space of the joint rows, i.e. onto rotations about the joint point / about the hinge axis),
``E1 = E2 T0 exp(a')``. The exponential of such a twist is exactly a rotation about the
point (axis), so the joint then holds exactly for any relative rotation below pi; the paper's
``T0 = I`` is the special case of a joint whose point has the same coordinates in both frames.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from artrack.lie import GeometryError, adjoint, exp_se3, inverse_se3, log_se3, skew

__all__ = [
    "MAX_ROWS",
    "Joint",
    "TreeSchedule",
    "articulated_update",
    "coerce_constraints",
    "constraint_matrices",
    "constraint_residuals",
    "dense_kkt_solve",
    "joint_rows",
    "propagate",
    "propagate_reference",
    "regularise",
    "tree_schedule",
]

#: Rows of the largest joint (hinge); constraint arrays are padded to this.
MAX_ROWS = 5


@dataclass(frozen=True)
class Joint:
    """Joint between a component (child) and its parent.

    kind: ``'ball'`` (3 constraint rows) or ``'hinge'`` (5 rows).
    point: (3,) joint centre in the *child* frame (m).
    axis: (3,) hinge axis in the child frame (hinge only; normalised here).
    parent_from_child: (4, 4) a reference relative pose satisfying the joint (e.g. the rest pose,
    ``E_parent^-1 E_child``), used only by :func:`coerce_constraints`; identity by default.
    """

    kind: str = "ball"
    point: np.ndarray = field(default_factory=lambda: np.zeros(3))
    axis: np.ndarray | None = None
    parent_from_child: np.ndarray = field(default_factory=lambda: np.eye(4))

    def __post_init__(self) -> None:
        if self.kind not in ("ball", "hinge"):
            raise GeometryError(f"Joint.kind must be 'ball' or 'hinge', got {self.kind!r}")
        object.__setattr__(self, "point", np.asarray(self.point, dtype=float).reshape(3))
        if self.kind == "hinge":
            if self.axis is None:
                raise GeometryError("Joint.axis is required for a hinge")
            ax = np.asarray(self.axis, dtype=float).reshape(3)
            nrm = np.linalg.norm(ax)
            if nrm == 0:
                raise GeometryError("Joint.axis must be non-zero")
            object.__setattr__(self, "axis", ax / nrm)
        object.__setattr__(self, "parent_from_child", np.asarray(self.parent_from_child, dtype=float))

    @property
    def n_rows(self) -> int:
        return 3 if self.kind == "ball" else 5


def _rows_batch(points: np.ndarray, axes: np.ndarray, hinge: np.ndarray) -> np.ndarray:
    """Padded joint rows (k, 5, 6) for points (k, 3), unit axes (k, 3) and hinge flags (k,)."""
    k = len(points)
    D = np.zeros((k, MAX_ROWS, 6))
    D[:, :3, :3] = np.eye(3)
    D[:, :3, 3:] = -skew(points)
    if np.any(hinge):
        ax = axes[hinge]
        helper = np.eye(3)[np.argmin(np.abs(ax), axis=1)]
        u1 = np.cross(ax, helper)
        u1 /= np.linalg.norm(u1, axis=1, keepdims=True)
        D[hinge, 3, 3:] = u1
        D[hinge, 4, 3:] = np.cross(ax, u1)
    return D


def joint_rows(joint: Joint) -> np.ndarray:
    """``D12`` (r, 6) of one joint in the child frame: ball r = 3, hinge r = 5 (see module docstring)."""
    hinge = joint.kind == "hinge"
    axis = joint.axis if joint.axis is not None else np.zeros(3)
    return _rows_batch(joint.point[None], axis[None], np.array([hinge]))[0, : joint.n_rows]


@dataclass(frozen=True)
class TreeSchedule:
    """Level structure of a forest: ``levels[d]`` = node indices at depth d (roots at depth 0),
    ``level_parents[d]`` their parents. Computed once per topology by :func:`tree_schedule`."""

    parents: np.ndarray
    levels: tuple[np.ndarray, ...]
    level_parents: tuple[np.ndarray, ...]

    @property
    def n(self) -> int:
        return len(self.parents)

    @property
    def order(self) -> np.ndarray:
        """All nodes, parents before children (breadth first)."""
        return np.concatenate(self.levels)


def tree_schedule(parents: Sequence[int] | np.ndarray) -> TreeSchedule:
    """Depth levels of the forest given by ``parents`` (N,) (-1 = root). Raises on cycles / bad indices."""
    par = np.asarray(parents, dtype=np.int64).reshape(-1)
    n = len(par)
    if np.any((par < -1) | (par >= n)) or np.any(par == np.arange(n)):
        raise GeometryError("tree_schedule: parents must be -1 or the index of another component")
    children: list[list[int]] = [[] for _ in range(n)]
    for i, p in enumerate(par.tolist()):
        if p >= 0:
            children[p].append(i)
    level = np.flatnonzero(par < 0)
    if len(level) == 0:
        raise GeometryError("tree_schedule: no root (parents has no -1): the graph has a cycle")
    levels, seen = [], 0
    while len(level):
        levels.append(level)
        seen += len(level)
        nxt = [c for i in level.tolist() for c in children[i]]
        level = np.array(nxt, dtype=np.int64)
    if seen != n:
        raise GeometryError("tree_schedule: parents contain a cycle (not every component reaches a root)")
    return TreeSchedule(par, tuple(levels), tuple(par[lv] for lv in levels))


def _joint_arrays(
    par: np.ndarray, joints: Sequence[Joint | None]
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Non-root indices (k,), their padded rows D12 (k, 5, 6), row masks (k, 5), reference poses (k, 4, 4)."""
    child = np.flatnonzero(par >= 0)
    js: list[Joint] = []
    for i in child.tolist():
        j = joints[i]
        if j is None:
            raise GeometryError(f"component {i} has a parent but no joint")
        js.append(j)
    hinge = np.array([j.kind == "hinge" for j in js], dtype=bool)
    points = np.array([j.point for j in js]).reshape(-1, 3)
    axes = np.array([j.axis if j.axis is not None else np.zeros(3) for j in js]).reshape(-1, 3)
    mask = np.zeros((len(child), MAX_ROWS), dtype=bool)
    mask[:, :3] = True
    mask[hinge, 3:] = True
    T0 = np.array([j.parent_from_child for j in js]).reshape(-1, 4, 4)
    return child, _rows_batch(points, axes, hinge), mask, T0


def constraint_matrices(
    E: np.ndarray, parents: Sequence[int] | np.ndarray, joints: Sequence[Joint | None]
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Padded joint matrices for every component: ``D12`` and ``D21`` (N, 5, 6), ``row_mask`` (N, 5).

    E: (N, 4, 4) component -> camera (any common frame). joints[i] joins i to parents[i]
    (None for roots). Row k of component i is a constraint iff ``row_mask[i, k]``; padded rows and
    roots are zero. ``D21_i = -D12_i Ad(E_i^-1 E_parent)`` (eq. 14).
    """
    E = np.asarray(E, dtype=float)
    par = np.asarray(parents, dtype=np.int64).reshape(-1)
    n = len(par)
    if E.shape != (n, 4, 4) or len(joints) != n:
        raise GeometryError(f"constraint_matrices: need E (N, 4, 4) and N joints for N = {n} parents")
    child, Dc, mc, _ = _joint_arrays(par, joints)
    D12 = np.zeros((n, MAX_ROWS, 6))
    mask = np.zeros((n, MAX_ROWS), dtype=bool)
    D12[child] = Dc
    mask[child] = mc
    D21 = np.zeros_like(D12)
    rel = inverse_se3(E[child]) @ E[par[child]]  # parent -> child
    D21[child] = -D12[child] @ adjoint(rel)
    return D12, D21, mask


def regularise(C: np.ndarray, eps: float = 1e-9) -> np.ndarray:
    """``C + eps * max(trace(C)/6, 1e-300) * I`` for a stack ``C`` (..., 6, 6) (module docstring)."""
    C = np.asarray(C, dtype=float)
    scale = np.maximum(np.trace(C, axis1=-2, axis2=-1) / C.shape[-1], 1e-300)
    return C + (eps * scale)[..., None, None] * np.eye(C.shape[-1])


def _check(xi_hat: np.ndarray, C: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    xi_hat = np.asarray(xi_hat, dtype=float)
    C = np.asarray(C, dtype=float)
    if xi_hat.shape != (n, 6) or C.shape != (n, 6, 6):
        raise GeometryError(
            f"propagation: need xi_hat (N, 6) and C (N, 6, 6) for N = {n}, got {xi_hat.shape}, {C.shape}"
        )
    return xi_hat, 0.5 * (C + np.swapaxes(C, -1, -2))


def propagate(
    xi_hat: np.ndarray,
    C: np.ndarray,
    parents: Sequence[int] | np.ndarray | TreeSchedule,
    D12: np.ndarray,
    D21: np.ndarray,
    row_mask: np.ndarray | None = None,
    *,
    eps: float = 1e-9,
) -> np.ndarray:
    """Algorithm 1: the constrained least-squares motion of every component, O(N).

    xi_hat: (N, 6), C: (N, 6, 6) per-component statistics in their own frames.
    parents: (N,) parent indices (-1 for roots) or a precomputed :class:`TreeSchedule` (reuse it
    across frames: the topology does not change). D12, D21: (N, R, 6) joint rows (from
    :func:`constraint_matrices`), row_mask: (N, R) rows in use (default: non-zero rows of D12).
    eps: relative regularisation of every C (:func:`regularise`).
    Returns xi: (N, 6), each in its component's frame, satisfying ``D12 xi_i + D21 xi_parent = 0``.
    """
    sched = parents if isinstance(parents, TreeSchedule) else tree_schedule(parents)
    n = sched.n
    xi_hat, C = _check(xi_hat, C, n)
    D12 = np.asarray(D12, dtype=float)
    D21 = np.asarray(D21, dtype=float)
    if row_mask is None:
        row_mask = np.any(D12 != 0, axis=-1)
    # (N, R, R): a unit diagonal on unused (padded) rows keeps S invertible without changing the result
    pad = np.where(row_mask, 0.0, 1.0)[..., None] * np.eye(D12.shape[1])
    Cacc = regularise(C, eps)
    eta = np.einsum("nij,nj->ni", Cacc, xi_hat)
    n_lev = len(sched.levels)
    # kept for the downward pass, preallocated (no per-node Python objects: O(N) memory, GC-friendly):
    # the gain G = C1^-1 D12^T S^-1 and the propagated xi_hat of every non-root component
    gain = np.zeros((n, 6, D12.shape[1]))
    xprop = np.zeros((n, 6))
    # leaves -> root: fold each level of children into their parents (eqs. 21, 22, information form)
    inv, swap, einsum = np.linalg.inv, np.swapaxes, np.einsum
    for d in range(n_lev - 1, 0, -1):
        ch, pa = sched.levels[d], sched.level_parents[d]
        if len(ch) == 1:  # chains: plain 2-D algebra, far less numpy call overhead than stacks of one
            i, p = int(ch[0]), int(pa[0])
            Cinv = inv(Cacc[i])
            xh = Cinv @ eta[i]
            A, B = D12[i], D21[i]
            CA = Cinv @ A.T
            Sinv = inv(A @ CA + pad[i])
            SB = Sinv @ B
            Cacc[p] += B.T @ SB
            eta[p] -= SB.T @ (A @ xh)
            gain[i] = CA @ Sinv
            xprop[i] = xh
            continue
        Cinv = inv(Cacc[ch])  # (k, 6, 6)
        xh = einsum("kij,kj->ki", Cinv, eta[ch])  # propagated xi_hat of the children
        A = D12[ch]
        B = D21[ch]
        CA = Cinv @ swap(A, -1, -2)
        Sinv = inv(A @ CA + pad[ch])
        SB = Sinv @ B  # (k, R, 6)
        dC = swap(B, -1, -2) @ SB
        deta = -einsum("kri,kr->ki", SB, einsum("krj,kj->kr", A, xh))
        if len(np.unique(pa)) == len(pa):
            Cacc[pa] += dC
            eta[pa] += deta
        else:
            np.add.at(Cacc, pa, dC)
            np.add.at(eta, pa, deta)
        gain[ch] = CA @ Sinv
        xprop[ch] = xh
    xi = np.empty((n, 6))
    roots = sched.levels[0]
    xi[roots] = np.linalg.solve(Cacc[roots], eta[roots][..., None])[..., 0]
    # root -> leaves: each child's best motion given its parent's (eq. 19):
    # xi1 = xi1' - G (D21 xi2 + D12 xi1')
    for d in range(1, n_lev):
        ch, pa = sched.levels[d], sched.level_parents[d]
        if len(ch) == 1:
            i, p = int(ch[0]), int(pa[0])
            xh = xprop[i]
            xi[i] = xh - gain[i] @ (D21[i] @ xi[p] + D12[i] @ xh)
            continue
        xh = xprop[ch]
        r = einsum("krj,kj->kr", D21[ch], xi[pa]) + einsum("krj,kj->kr", D12[ch], xh)
        xi[ch] = xh - einsum("kir,kr->ki", gain[ch], r)
    return xi


def propagate_reference(
    xi_hat: np.ndarray,
    C: np.ndarray,
    parents: Sequence[int] | np.ndarray,
    D12: np.ndarray,
    D21: np.ndarray,
    row_mask: np.ndarray | None = None,
    *,
    eps: float = 1e-9,
) -> np.ndarray:
    """Literal per-node transcription of Algorithm 1 with eqs. 21, 22 and 19 as printed (slow; for tests).

    Same arguments and result as :func:`propagate`. Children are folded into their parent one at a
    time (post-order), each using the parent's running ``C2, xi2``.
    """
    sched = tree_schedule(parents)
    n = sched.n
    xi_hat, C = _check(xi_hat, C, n)
    if row_mask is None:
        row_mask = np.any(np.asarray(D12) != 0, axis=-1)
    Cp = regularise(C, eps)
    xp = xi_hat.copy()
    rows = [np.flatnonzero(row_mask[i]) for i in range(n)]
    order = sched.order
    for i in order[::-1]:  # every child before its parent
        p = sched.parents[i]
        if p < 0:
            continue
        A, B = D12[i][rows[i]], D21[i][rows[i]]
        C1i, C2i = np.linalg.inv(Cp[i]), np.linalg.inv(Cp[p])
        S = A @ C1i @ A.T
        r = A @ xp[i] + B @ xp[p]
        xp[p] = xp[p] - C2i @ B.T @ np.linalg.solve(S + B @ C2i @ B.T, r)  # eq. 21
        Cp[p] = Cp[p] + B.T @ np.linalg.solve(S, B)  # eq. 22
    xi = np.empty((n, 6))
    for i in order:
        p = sched.parents[i]
        if p < 0:
            xi[i] = xp[i]
            continue
        A, B = D12[i][rows[i]], D21[i][rows[i]]
        C1i = np.linalg.inv(Cp[i])
        S = A @ C1i @ A.T
        xi[i] = xp[i] - C1i @ A.T @ np.linalg.solve(S, B @ xi[p] + A @ xp[i])  # eq. 19
    return xi


def dense_kkt_solve(
    xi_hat: np.ndarray,
    C: np.ndarray,
    parents: Sequence[int] | np.ndarray,
    D12: np.ndarray,
    D21: np.ndarray,
    row_mask: np.ndarray | None = None,
    *,
    eps: float = 1e-9,
) -> np.ndarray:
    """The same constrained least-squares problem by one dense KKT solve, O(N^3) (for checks and the bench).

    ``[[2 Cbar, A^T], [A, 0]] [xi; lambda] = [2 Cbar xi_hat; 0]`` with ``Cbar`` the block diagonal of the
    regularised ``C_i`` and ``A`` the stacked joint rows (``D12`` on the child's block, ``D21`` on the
    parent's). Arguments and result as :func:`propagate`; solved with ``numpy.linalg.solve`` (LU).
    """
    par = np.asarray(parents, dtype=np.int64).reshape(-1)
    n = len(par)
    xi_hat, C = _check(xi_hat, C, n)
    if row_mask is None:
        row_mask = np.any(np.asarray(D12) != 0, axis=-1)
    child = np.flatnonzero(par >= 0)
    ci, ri = np.nonzero(row_mask[child])
    nodes = child[ci]
    m = len(nodes)
    size = 6 * n + m
    K = np.zeros((size, size))
    rhs = np.zeros(size)
    Cr = regularise(C, eps)
    for i in range(n):
        K[6 * i : 6 * i + 6, 6 * i : 6 * i + 6] = 2.0 * Cr[i]
    rhs[: 6 * n] = 2.0 * np.einsum("nij,nj->ni", Cr, xi_hat).reshape(-1)
    cols = 6 * nodes[:, None] + np.arange(6)
    pcols = 6 * par[nodes][:, None] + np.arange(6)
    rr = 6 * n + np.arange(m)
    K[rr[:, None], cols] = D12[nodes, ri]
    K[rr[:, None], pcols] += D21[nodes, ri]
    K[: 6 * n, 6 * n :] = K[6 * n :, : 6 * n].T
    sol = np.linalg.solve(K, rhs)
    return sol[: 6 * n].reshape(n, 6)


def constraint_residuals(
    xi: np.ndarray, parents: Sequence[int] | np.ndarray, D12: np.ndarray, D21: np.ndarray
) -> np.ndarray:
    """``D12_i xi_i + D21_i xi_parent`` (N, R) for every component (zeros for roots)."""
    par = np.asarray(parents, dtype=np.int64).reshape(-1)
    xi = np.asarray(xi, dtype=float)
    out = np.zeros(D12.shape[:2])
    child = np.flatnonzero(par >= 0)
    out[child] = np.einsum("nrj,nj->nr", D12[child], xi[child]) + np.einsum(
        "nrj,nj->nr", D21[child], xi[par[child]]
    )
    return out


def coerce_constraints(
    E: np.ndarray, parents: Sequence[int] | np.ndarray | TreeSchedule, joints: Sequence[Joint | None]
) -> np.ndarray:
    """Make every joint hold exactly (paper eqs. 23-25, generalised with a reference pose ``T0``).

    E: (N, 4, 4) component -> camera (or world). Root to leaves, for child 1 of parent 2:
    ``a = log(T0^-1 E2^-1 E1)``, ``a' = a - D12^T (D12 D12^T)^-1 D12 a``, ``E1 = E2 T0 exp(a')`` with
    ``T0 = joint.parent_from_child``. Roots are unchanged. Returns the new (N, 4, 4) stack.
    """
    sched = parents if isinstance(parents, TreeSchedule) else tree_schedule(parents)
    E = np.array(E, dtype=float, copy=True)
    if E.shape != (sched.n, 4, 4) or len(joints) != sched.n:
        raise GeometryError(f"coerce_constraints: need E (N, 4, 4) and N joints for N = {sched.n}")
    child, D, mask, T0c = _joint_arrays(sched.parents, joints)
    pad = np.where(mask, 0.0, 1.0)[..., None] * np.eye(MAX_ROWS)
    Dt = np.swapaxes(D, -1, -2)
    proj = np.tile(np.eye(6), (sched.n, 1, 1))
    proj[child] = np.eye(6) - Dt @ np.linalg.inv(D @ Dt + pad) @ D  # projector onto the joint's null space
    T0 = np.tile(np.eye(4), (sched.n, 1, 1))
    T0[child] = T0c
    for d in range(1, len(sched.levels)):
        ch, pa = sched.levels[d], sched.level_parents[d]
        base = E[pa] @ T0[ch]
        a = log_se3(inverse_se3(base) @ E[ch])
        a = np.einsum("kij,kj->ki", proj[ch], a)
        E[ch] = base @ exp_se3(a)
    return E


def articulated_update(
    E: np.ndarray,
    xi_hat: np.ndarray,
    C: np.ndarray,
    parents: Sequence[int] | np.ndarray | TreeSchedule,
    joints: Sequence[Joint | None],
    *,
    eps: float = 1e-9,
) -> tuple[np.ndarray, np.ndarray]:
    """One articulated step: constraint rows at ``E``, :func:`propagate`, ``E_i <- E_i exp(xi_i)``, coerce.

    E: (N, 4, 4) component -> camera before the step; xi_hat (N, 6), C (N, 6, 6) edge statistics.
    Returns (E_new (N, 4, 4), xi (N, 6)).
    """
    sched = parents if isinstance(parents, TreeSchedule) else tree_schedule(parents)
    D12, D21, mask = constraint_matrices(E, sched.parents, joints)
    xi = propagate(xi_hat, C, sched, D12, D21, mask, eps=eps)
    E_new = np.asarray(E, dtype=float) @ exp_se3(xi)
    return coerce_constraints(E_new, sched, joints), xi
