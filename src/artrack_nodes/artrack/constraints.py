"""Hard constraints by virtual work over free rigid bodies (ALGORITHMS.md §1).

Representation (the paper's, "every link is a free rigid body"): the state
``q`` stacks, for each of L links, its world pose ``world_from_link`` as a
position ``p`` (3,) m (the link-frame origin = its proximal joint) and a
rotation ``R`` (3, 3). Generalised velocities / increments are twists
``ν = [v, ω]`` (6 per link, world frame: ``p ← p + δp``,
``R ← exp([δω]×) R``), so ``J = ∂c/∂q`` is (m, 6L) with respect to ν.
Because each link is a rigid body, bone lengths are fixed by construction;
joints are constraint functions ``c(q) = 0``:

* ``PointCoincidence`` — a point of link a equals a point of link b (ball
  joint: the child's origin equals the parent's attachment point; 3 rows).
  Link index -1 means the world (a fixed anchor).
* ``HingeAxis`` — a direction of link a equals a direction of link b
  (together with a ball joint this is a hinge; 2 rows).
* ``PointDistance`` — fixed distance between two points (1 row), for
  particle models (links used as point masses).

Virtual work (paper Eq. 1–5): with applied forces Q and constraint forces
``C = Jᵀ λ``, ``q̈ = W (Q + C)``, and requiring ``c̈ = 0`` gives

    (J W Jᵀ) λ = −J W Q − J̇ q̇ − k_s c − k_d ċ

which is assembled as scipy.sparse matrices (W block-diagonal, J with
O(L) non-zeros) and solved by conjugate gradients (or BiCG, as in the
paper; "dense" for testing). A body's system (tens of rows) is assembled
on dense arrays with W kept as its (L, 6, 6) blocks: the same arithmetic
and the same Krylov solver, without scipy.sparse's per-call overhead.

Two integrators share that equation:

* ``'kinematic'`` (paper §2.3, the variant it settled on): ``q̇ = W Q``,
  ``q ← q + Δt q̇`` with the constraint force added, iterated until the
  pose is stationary. Soft constraints are springs ``Q = S (g − x)`` toward
  goals (the Kalman filters' estimates, stiffness S from their inverse
  covariance; rest pose, joint-limit and gravity terms). We take as the
  "mass" of each link the stiffness of its own springs plus a small
  regularising mass, ``W = (Aᵀ S A + μ M)⁻¹`` (block-diagonal because
  every spring acts on one link), so with ``Δt = 1`` each iteration is the
  exact Gauss–Newton / KKT step of "minimise spring energy subject to
  c(q) = 0". Goals that depend on other links (rest pose relative to the
  parent) are re-evaluated each iteration (the paper's "control law as a
  time-varying potential field"). The loop ends with a pure projection
  ``δq = −W Jᵀ (J W Jᵀ)⁻¹ c`` until ``‖c‖ < tol``.
* ``'dynamic'`` (paper §2.1): state q and q̇, physical masses M (mass and
  inertia per link), viscous damping B. Springs are integrated
  linearly-implicitly, which keeps W block-diagonal:
  ``W = (M + Δt B + Δt² K)⁻¹``, ``Q = F(q) − (Δt K + B) q̇``; then
  ``q̇ ← q̇ + Δt W (Q + Jᵀλ)``, ``q ← q ⊕ Δt q̇`` and the same drift
  projection (position and velocity).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla
from scipy.spatial.transform import Rotation

from .errors import InputError
from .lie import cross, skew

# ---------------------------------------------------------------------------- SO(3) helpers


def exp_so3(w: np.ndarray) -> np.ndarray:
    """Rotation vectors (..., 3) rad -> rotation matrices (..., 3, 3) (Rodrigues)."""
    w = np.asarray(w, dtype=float)
    theta = np.linalg.norm(w, axis=-1)[..., None, None]
    K = skew(w)
    small = theta < 1e-8
    th = np.where(small, 1.0, theta)
    a = np.where(small, 1.0 - theta**2 / 6.0, np.sin(th) / th)
    b = np.where(small, 0.5 - theta**2 / 24.0, (1.0 - np.cos(th)) / th**2)
    return np.eye(3) + a * K + b * (K @ K)


def log_so3(R: np.ndarray) -> np.ndarray:
    """Rotation matrices (..., 3, 3) -> rotation vectors (..., 3), |w| ≤ π."""
    R = np.asarray(R, dtype=float)
    flat = R.reshape(-1, 3, 3)
    vee = 0.5 * np.stack(
        [flat[:, 2, 1] - flat[:, 1, 2], flat[:, 0, 2] - flat[:, 2, 0], flat[:, 1, 0] - flat[:, 0, 1]], axis=1
    )
    cos = np.clip(0.5 * (np.trace(flat, axis1=1, axis2=2) - 1.0), -1.0, 1.0)
    sin = np.linalg.norm(vee, axis=1)
    theta = np.arctan2(sin, cos)
    scale = np.where(sin > 1e-12, theta / np.maximum(sin, 1e-300), 1.0 + theta**2 / 6.0)
    w = vee * scale[:, None]
    near_pi = cos < -0.99  # axis from vee is ill-conditioned there: use scipy
    if np.any(near_pi):
        w[near_pi] = Rotation.from_matrix(flat[near_pi]).as_rotvec()
    return w.reshape(*R.shape[:-2], 3)


def left_jacobian_inverse(e: np.ndarray) -> np.ndarray:
    """Rotation vectors (..., 3) -> (..., 3, 3) ``J_l⁻¹(e)``: ``log(exp(δ) exp(e)) ≈ e + J_l⁻¹ δ``."""
    e = np.asarray(e, dtype=float)
    theta = np.linalg.norm(e, axis=-1)[..., None, None]
    K = skew(e)
    small = theta < 1e-6
    th = np.where(small, 1.0, theta)
    coef = np.where(small, 1.0 / 12.0, 1.0 / th**2 - (1.0 + np.cos(th)) / (2.0 * th * np.sin(th)))
    return np.eye(3) - 0.5 * K + coef * (K @ K)


def retract(p: np.ndarray, R: np.ndarray, nu: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Apply twists nu (L, 6) [δp, δω] (world frame): ``p + δp``, ``exp(δω) R``."""
    nu = np.asarray(nu, dtype=float).reshape(-1, 6)
    return p + nu[:, :3], exp_so3(nu[:, 3:]) @ R


# ---------------------------------------------------------------------------- constraints


class Constraint:
    """A hard constraint ``c(q) = 0`` of ``n_rows`` rows on links ``links``."""

    n_rows: int = 0
    links: tuple[int, ...] = ()

    def residual(self, p: np.ndarray, R: np.ndarray) -> np.ndarray:  # pragma: no cover - interface
        """c(q): (n_rows,)."""
        raise NotImplementedError

    def jacobian(self, p: np.ndarray, R: np.ndarray) -> list[tuple[int, np.ndarray]]:  # pragma: no cover
        """∂c/∂ν as [(link, (n_rows, 6) block)] for each non-world link."""
        raise NotImplementedError

    def residual_and_triplets(
        self, p: np.ndarray, R: np.ndarray
    ) -> tuple[np.ndarray, tuple[np.ndarray, np.ndarray, np.ndarray]]:
        """(:meth:`residual`, :meth:`triplets`) in one call (constraints sharing terms override it)."""
        return self.residual(p, R), self.triplets(p, R)

    def triplets(self, p: np.ndarray, R: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """∂c/∂ν as COO (rows, cols, values), rows local to this constraint."""
        rr, cc = _block_pattern(self.n_rows)
        blocks = self.jacobian(p, R)
        if not blocks:
            return np.zeros(0, int), np.zeros(0, int), np.zeros(0)
        rows = np.concatenate([rr for _ in blocks])
        cols = np.concatenate([cc + 6 * link for link, _ in blocks])
        vals = np.concatenate([b.ravel() for _, b in blocks])
        return rows, cols, vals


def _point(p: np.ndarray, R: np.ndarray, link: int, local: np.ndarray) -> np.ndarray:
    """World position of a link-frame point (link -1: ``local`` is already in the world)."""
    if link < 0:
        return local
    return p[link] + R[link] @ local


@dataclass
class PointCoincidence(Constraint):
    """``x_b − x_a = 0`` with ``x = p + R r`` (ball joint; 3 rows). link_a = -1: world anchor."""

    link_a: int
    point_a: np.ndarray
    link_b: int
    point_b: np.ndarray
    n_rows: int = 3

    def __post_init__(self):
        self.point_a = np.asarray(self.point_a, dtype=float).reshape(3)
        self.point_b = np.asarray(self.point_b, dtype=float).reshape(3)
        self.links = tuple(k for k in (self.link_a, self.link_b) if k >= 0)

    def residual(self, p, R):
        return _point(p, R, self.link_b, self.point_b) - _point(p, R, self.link_a, self.point_a)

    def jacobian(self, p, R):
        blocks = []
        for link, local, sign in ((self.link_a, self.point_a, -1.0), (self.link_b, self.point_b, 1.0)):
            if link < 0:
                continue
            r = R[link] @ local
            blocks.append((link, sign * np.hstack([np.eye(3), -skew(r)])))
        return blocks


@dataclass
class HingeAxis(Constraint):
    """Direction ``w = R_b u_b`` equal to ``u = R_a u_a`` (2 rows). Together with a
    PointCoincidence at the joint this is a hinge about u.

    The residual is the rotation vector ``φ = θ (u × w)/|u × w|`` that turns u onto w
    (θ = ∠(u, w)), expressed on two directions of link a orthogonal to u; unlike the
    plain ``e_k · w`` form it vanishes only for w = +u (not for the flipped hinge).
    """

    link_a: int
    axis_a: np.ndarray
    link_b: int
    axis_b: np.ndarray
    n_rows: int = 2

    def __post_init__(self):
        u = np.asarray(self.axis_a, dtype=float).reshape(3)
        u = u / np.linalg.norm(u)
        self.axis_a = u
        self.axis_b = np.asarray(self.axis_b, dtype=float).reshape(3)
        self.axis_b = self.axis_b / np.linalg.norm(self.axis_b)
        helper = np.eye(3)[int(np.argmin(np.abs(u)))]
        e1 = cross(u, helper)
        e1 /= np.linalg.norm(e1)
        self.perp_a = np.stack([e1, cross(u, e1)])  # (2, 3) in link a's frame
        self.links = tuple(k for k in (self.link_a, self.link_b) if k >= 0)

    def _terms(self, R):
        u = R[self.link_a] @ self.axis_a if self.link_a >= 0 else self.axis_a
        w = R[self.link_b] @ self.axis_b if self.link_b >= 0 else self.axis_b
        E = self.perp_a @ R[self.link_a].T if self.link_a >= 0 else self.perp_a
        v = cross(u, w)
        s, co = float(np.linalg.norm(v)), float(u @ w)
        theta = float(np.arctan2(s, co))
        g = theta / s if s > 1e-9 else (1.0 if co > 0 else np.pi / 1e-9)
        return u, w, E, v, s, co, theta, g

    def residual(self, p, R):
        _, _, E, v, _, _, _, g = self._terms(R)
        return E @ (g * v)

    def jacobian(self, p, R):
        u, w, E, v, s, co, theta, g = self._terms(R)
        phi = g * v
        D_u, D_w = -skew(u), -skew(w)  # δu = D_u δω_a, δw = D_w δω_b
        out = {}
        for link, Dv, Dco in (
            (self.link_a, -skew(w) @ D_u, w @ D_u),
            (self.link_b, skew(u) @ D_w, u @ D_w),
        ):
            if link < 0:
                continue
            if s > 1e-6:
                Ds = (v / s) @ Dv
                Dtheta = co * Ds - s * Dco  # s² + co² = 1
                Dg = (Dtheta - g * Ds) / s
                Dphi = g * Dv + np.outer(v, Dg)
            else:
                Dphi = g * Dv
            out[link] = out.get(link, np.zeros((2, 3))) + E @ Dphi
        if self.link_a >= 0:
            out[self.link_a] = out[self.link_a] + cross(E, phi[None])  # δe_k · φ = δω_a · (e_k × φ)
        return [(link, np.hstack([np.zeros((2, 3)), block])) for link, block in out.items()]


def _blocks_from_triplets(n_rows, rows, cols, vals) -> list[tuple[int, np.ndarray]]:
    """COO triplets -> [(link, (n_rows, 6) block)]."""
    out: dict[int, np.ndarray] = {}
    for link in np.unique(cols // 6):
        sel = cols // 6 == link
        block = np.zeros((n_rows, 6))
        np.add.at(block, (rows[sel], cols[sel] % 6), vals[sel])
        out[int(link)] = block
    return list(out.items())


class BallJoints(Constraint):
    """Many ``PointCoincidence`` constraints evaluated at once (3 rows each, joint j
    owning rows 3j..3j+2): ``p_b + R_b r_b − p_a − R_a r_a = 0``. link_a, link_b: (n,)
    link indices (no world anchors); point_a, point_b: (n, 3) link-frame points."""

    def __init__(self, link_a, point_a, link_b, point_b):
        self.link_a = np.asarray(link_a, int).reshape(-1)
        self.link_b = np.asarray(link_b, int).reshape(-1)
        self.point_a = np.asarray(point_a, float).reshape(-1, 3)
        self.point_b = np.asarray(point_b, float).reshape(-1, 3)
        n = self.link_a.size
        if np.any(self.link_a < 0) or np.any(self.link_b < 0) or self.point_a.shape != (n, 3):
            raise InputError("constraints: BallJoints needs (n,) link indices >= 0 and (n, 3) points")
        self.n_rows = 3 * n
        self.links = tuple(sorted(set(self.link_a.tolist()) | set(self.link_b.tolist())))
        j = np.arange(n)
        self._rows = np.concatenate(
            [(3 * j[:, None, None] + np.arange(3)[None, :, None] + np.zeros(6, int)[None, None, :]).ravel()]
            * 2
        )
        self._cols = np.concatenate(
            [
                (6 * links[:, None, None] + np.arange(6)[None, None, :] + np.zeros((1, 3, 1), int)).ravel()
                for links in (self.link_a, self.link_b)
            ]
        )
        self._eye = np.broadcast_to(np.eye(3), (n, 3, 3))

    def _lever(self, R):
        ra = np.einsum("nij,nj->ni", R[self.link_a], self.point_a)
        rb = np.einsum("nij,nj->ni", R[self.link_b], self.point_b)
        return ra, rb

    def residual(self, p, R):
        return self._residual(p, *self._lever(R))

    def _residual(self, p, ra, rb):
        """c from the lever arms (:meth:`_lever`): the two anchor points' difference."""
        return (p[self.link_b] + rb - p[self.link_a] - ra).ravel()

    def jacobian(self, p, R):
        return _blocks_from_triplets(self.n_rows, *self.triplets(p, R))

    def triplets(self, p, R):
        return self.residual_and_triplets(p, R)[1]

    def residual_and_triplets(self, p, R):
        ra, rb = self._lever(R)
        Ja = -np.concatenate([self._eye, -skew(ra)], axis=2)
        Jb = np.concatenate([self._eye, -skew(rb)], axis=2)
        return self._residual(p, ra, rb), (self._rows, self._cols, np.concatenate([Ja.ravel(), Jb.ravel()]))


class HingeAxes(Constraint):
    """Many ``HingeAxis`` constraints evaluated at once (2 rows each)."""

    def __init__(self, link_a, axis_a, link_b, axis_b):
        self.items = [
            HingeAxis(int(a), ua, int(b), ub)
            for a, ua, b, ub in zip(
                np.asarray(link_a, int).reshape(-1),
                np.asarray(axis_a, float).reshape(-1, 3),
                np.asarray(link_b, int).reshape(-1),
                np.asarray(axis_b, float).reshape(-1, 3),
                strict=True,
            )
        ]
        if any(h.link_a < 0 or h.link_b < 0 for h in self.items):
            raise InputError("constraints: HingeAxes needs link indices >= 0")
        self.link_a = np.array([h.link_a for h in self.items], int)
        self.link_b = np.array([h.link_b for h in self.items], int)
        self.u_a = np.array([h.axis_a for h in self.items]).reshape(-1, 3)
        self.u_b = np.array([h.axis_b for h in self.items]).reshape(-1, 3)
        self.perp = np.array([h.perp_a for h in self.items]).reshape(-1, 2, 3)
        self.n_rows = 2 * len(self.items)
        self.links = tuple(sorted(set(self.link_a.tolist()) | set(self.link_b.tolist())))
        n = len(self.items)
        self._rows = np.concatenate(
            [
                (
                    2 * np.arange(n)[:, None, None]
                    + np.arange(2)[None, :, None]
                    + np.zeros(6, int)[None, None, :]
                ).ravel()
            ]
            * 2
        )
        self._cols = np.concatenate(
            [
                (
                    6 * self.link_a[:, None, None] + np.arange(6)[None, None, :] + np.zeros((1, 2, 1), int)
                ).ravel(),
                (
                    6 * self.link_b[:, None, None] + np.arange(6)[None, None, :] + np.zeros((1, 2, 1), int)
                ).ravel(),
            ]
        )

    def _terms(self, R):
        Ra, Rb = R[self.link_a], R[self.link_b]
        u = np.einsum("nij,nj->ni", Ra, self.u_a)
        w = np.einsum("nij,nj->ni", Rb, self.u_b)
        E = self.perp @ np.swapaxes(Ra, 1, 2)  # (n, 2, 3) world
        v = cross(u, w)
        s = np.linalg.norm(v, axis=1)
        co = np.einsum("ni,ni->n", u, w)
        theta = np.arctan2(s, co)
        g = np.where(s > 1e-9, theta / np.maximum(s, 1e-300), np.where(co > 0, 1.0, np.pi / 1e-9))
        return u, w, E, v, s, co, g

    def residual(self, p, R):
        _, _, E, v, _, _, g = self._terms(R)
        return self._residual(E, g[:, None] * v)

    @staticmethod
    def _residual(E, phi):
        """c from :meth:`_terms`: the misalignment rotation vector phi (n, 3) on the two rows of E."""
        return np.einsum("nki,ni->nk", E, phi).ravel()

    def jacobian(self, p, R):
        return _blocks_from_triplets(self.n_rows, *self.triplets(p, R))

    def triplets(self, p, R):
        return self.residual_and_triplets(p, R)[1]

    def residual_and_triplets(self, p, R):
        u, w, E, v, s, co, g = self._terms(R)
        n = len(self.items)
        phi = g[:, None] * v
        Su, Sw = skew(u), skew(w)
        Dv_a = Sw @ Su  # −[w]× (−[u]×)
        Dv_b = -Su @ Sw  # [u]× (−[w]×)
        Dco_a = -np.einsum("ni,nij->nj", w, Su)
        Dco_b = -np.einsum("ni,nij->nj", u, Sw)
        big = s > 1e-6
        sv = np.where(big, s, 1.0)
        vh = v / sv[:, None]
        blocks = []
        for Dv, Dco in ((Dv_a, Dco_a), (Dv_b, Dco_b)):
            Ds = np.einsum("ni,nij->nj", vh, Dv)
            Dth = co[:, None] * Ds - s[:, None] * Dco
            Dg = (Dth - g[:, None] * Ds) / sv[:, None]
            Dphi = g[:, None, None] * Dv + np.where(big[:, None, None], v[:, :, None] * Dg[:, None, :], 0.0)
            blocks.append(E @ Dphi)
        blocks[0] = blocks[0] + cross(E, phi[:, None, :])
        full = [np.concatenate([np.zeros((n, 2, 3)), b], axis=2) for b in blocks]
        return self._residual(E, phi), (self._rows, self._cols, np.concatenate([full[0].ravel(), full[1].ravel()]))


@dataclass
class PointDistance(Constraint):
    """``‖x_b − x_a‖ − length = 0`` (1 row), e.g. a bone between two point masses."""

    link_a: int
    point_a: np.ndarray
    link_b: int
    point_b: np.ndarray
    length: float
    n_rows: int = 1

    def __post_init__(self):
        self.point_a = np.asarray(self.point_a, dtype=float).reshape(3)
        self.point_b = np.asarray(self.point_b, dtype=float).reshape(3)
        self.links = tuple(k for k in (self.link_a, self.link_b) if k >= 0)

    def residual(self, p, R):
        d = _point(p, R, self.link_b, self.point_b) - _point(p, R, self.link_a, self.point_a)
        return np.array([np.linalg.norm(d) - self.length])

    def jacobian(self, p, R):
        d = _point(p, R, self.link_b, self.point_b) - _point(p, R, self.link_a, self.point_a)
        n = d / max(np.linalg.norm(d), 1e-12)
        blocks = []
        for link, local, sign in ((self.link_a, self.point_a, -1.0), (self.link_b, self.point_b, 1.0)):
            if link < 0:
                continue
            r = R[link] @ local
            blocks.append((link, sign * np.concatenate([n, cross(r, n)])[None]))
        return blocks


# ---------------------------------------------------------------------------- soft terms


@dataclass
class PointGoal:
    """Spring pulling link point ``point`` (link frame, m) to ``target`` (world, m):
    energy ½ eᵀ S e, e = x − target; ``stiffness`` S (3, 3) N/m (e.g. α Σ⁻¹)."""

    link: int
    point: np.ndarray
    target: np.ndarray
    stiffness: np.ndarray


@dataclass
class OrientationGoal:
    """Torsional spring pulling ``R_link`` to ``target`` (3, 3) world_from_link:
    energy ½ eᵀ S e with e = log(R Rₜᵀ) (world rotation vector); S (3, 3) N·m/rad
    or a scalar."""

    link: int
    target: np.ndarray
    stiffness: np.ndarray | float


@dataclass
class Force:
    """Constant applied force (3,) N (world) at link point ``point`` (link frame), e.g. gravity."""

    link: int
    point: np.ndarray
    force: np.ndarray


SoftTerm = PointGoal | OrientationGoal | Force


@dataclass(frozen=True)
class PackedTerms:
    """Soft terms as arrays by kind, what :func:`soft_energy_terms` evaluates: point goals
    (links (n,), link-frame points (n, 3), targets (n, 3), stiffnesses (n, 3, 3)),
    orientation goals (links, targets (n, 3, 3), stiffnesses (n, 3, 3)) and forces
    (links, points (n, 3), forces (n, 3)). Built once by :func:`pack_terms` and joined
    with ``+``, so a solver iterating on fixed goals does not rebuild them."""

    goal_link: np.ndarray
    goal_point: np.ndarray
    goal_target: np.ndarray
    goal_stiffness: np.ndarray
    orient_link: np.ndarray
    orient_target: np.ndarray
    orient_stiffness: np.ndarray
    force_link: np.ndarray
    force_point: np.ndarray
    force_force: np.ndarray

    def __add__(self, other: PackedTerms) -> PackedTerms:
        def join(a: np.ndarray, b: np.ndarray) -> np.ndarray:
            return a if not b.size else b if not a.size else np.concatenate([a, b])

        return PackedTerms(*(join(getattr(self, f), getattr(other, f)) for f in self.__dataclass_fields__))

    def __len__(self) -> int:
        return self.goal_link.size + self.orient_link.size + self.force_link.size


def orientation_goals(links: np.ndarray, targets: np.ndarray, stiffness: np.ndarray | float) -> PackedTerms:
    """Packed torsional springs: links (n,), targets (n, 3, 3), stiffness scalar, (n,) or (n, 3, 3)."""
    links = np.asarray(links, int).reshape(-1)
    S = np.asarray(stiffness, float)
    if S.ndim < 3:
        S = np.broadcast_to(S.reshape(-1, 1, 1), (links.size, 1, 1)) * np.eye(3)
    return PackedTerms(
        np.zeros(0, int), np.zeros((0, 3)), np.zeros((0, 3)), np.zeros((0, 3, 3)),
        links, np.asarray(targets, float).reshape(-1, 3, 3), S,
        np.zeros(0, int), np.zeros((0, 3)), np.zeros((0, 3)),
    )  # fmt: skip


def pack_terms(terms: Sequence[SoftTerm] | PackedTerms) -> PackedTerms:
    """A sequence of soft terms -> :class:`PackedTerms` (InputError on an unknown term)."""
    if isinstance(terms, PackedTerms):
        return terms
    goals = [t for t in terms if isinstance(t, PointGoal)]
    orients = [t for t in terms if isinstance(t, OrientationGoal)]
    forces = [t for t in terms if isinstance(t, Force)]
    if len(goals) + len(orients) + len(forces) != len(terms):
        bad = next(t for t in terms if not isinstance(t, PointGoal | OrientationGoal | Force))
        raise InputError(f"constraints: unknown soft term {type(bad).__name__}")
    return PackedTerms(
        np.array([t.link for t in goals], int),
        np.array([t.point for t in goals], float).reshape(-1, 3),
        np.array([t.target for t in goals], float).reshape(-1, 3),
        np.array([t.stiffness for t in goals], float).reshape(-1, 3, 3),
        np.array([t.link for t in orients], int),
        np.array([t.target for t in orients], float).reshape(-1, 3, 3),
        np.array(
            [np.eye(3) * float(t.stiffness) if np.ndim(t.stiffness) == 0 else t.stiffness for t in orients],
            float,
        ).reshape(-1, 3, 3),
        np.array([t.link for t in forces], int),
        np.array([t.point for t in forces], float).reshape(-1, 3),
        np.array([t.force for t in forces], float).reshape(-1, 3),
    )


SoftTerms = Sequence[SoftTerm] | PackedTerms | Callable[[np.ndarray, np.ndarray], Sequence[SoftTerm] | PackedTerms]


def _curvature(f: np.ndarray, r: np.ndarray) -> np.ndarray:
    """(3, 3) Hessian of ``f · exp([ω]×) r`` in ω at 0: ½ (f rᵀ + r fᵀ) − (f · r) I."""
    return 0.5 * (np.outer(f, r) + np.outer(r, f)) - float(f @ r) * np.eye(3)


def soft_energy_terms(
    n_links: int,
    p: np.ndarray,
    R: np.ndarray,
    terms: Sequence[SoftTerm] | PackedTerms,
    second_order: bool = False,
) -> tuple[np.ndarray, np.ndarray, float]:
    """Generalised force Q (L, 6) = −∂E/∂ν, stiffness K (L, 6, 6) and energy E.

    K is the Gauss–Newton stiffness AᵀSA; with ``second_order`` the rotational
    curvature of the point springs (lever arm × residual force) is added, giving
    the exact Hessian of E (possibly indefinite far from the goals).
    """
    t = pack_terms(terms)
    Q = np.zeros((n_links, 6))
    K = np.zeros((n_links, 6, 6))
    energy = 0.0
    if t.goal_link.size:  # springs on link points
        i = t.goal_link
        r = np.einsum("nij,nj->ni", R[i], t.goal_point)
        e = p[i] + r - t.goal_target
        S = t.goal_stiffness
        Se = np.einsum("nij,nj->ni", S, e)
        A = np.concatenate([np.broadcast_to(np.eye(3), (i.size, 3, 3)), -skew(r)], axis=2)  # ∂x/∂ν
        At = np.swapaxes(A, 1, 2)
        np.add.at(Q, i, -np.einsum("nij,nj->ni", At, Se))
        Kg = At @ S @ A
        if second_order:
            fr = Se[:, :, None] * r[:, None, :]
            Kg[:, 3:, 3:] += 0.5 * (fr + np.swapaxes(fr, 1, 2)) - np.einsum("ni,ni->n", Se, r)[
                :, None, None
            ] * np.eye(3)
        np.add.at(K, i, Kg)
        energy += 0.5 * float(np.einsum("ni,ni->", e, Se))
    if t.orient_link.size:  # torsional springs
        i = t.orient_link
        e = log_so3(R[i] @ np.swapaxes(t.orient_target, 1, 2))
        S = t.orient_stiffness
        Se = np.einsum("nij,nj->ni", S, e)
        Jr = left_jacobian_inverse(e)
        Jrt = np.swapaxes(Jr, 1, 2)
        np.add.at(Q[:, 3:], i, -np.einsum("nij,nj->ni", Jrt, Se))
        np.add.at(K[:, 3:, 3:], i, Jrt @ S @ Jr)
        energy += 0.5 * float(np.einsum("ni,ni->", e, Se))
    if t.force_link.size:  # constant forces
        i = t.force_link
        r = np.einsum("nij,nj->ni", R[i], t.force_point)
        f = t.force_force
        np.add.at(Q[:, :3], i, f)
        np.add.at(Q[:, 3:], i, cross(r, f))
        energy -= float(np.einsum("ni,ni->", f, p[i] + r))
    return Q, K, energy


# ---------------------------------------------------------------------------- sparse assembly


_PATTERNS: dict[int, tuple[np.ndarray, np.ndarray]] = {}


def _block_pattern(n_rows: int) -> tuple[np.ndarray, np.ndarray]:
    """Row and column indices (n_rows * 6,) of a dense (n_rows, 6) block, row-major."""
    if n_rows not in _PATTERNS:
        _PATTERNS[n_rows] = (np.repeat(np.arange(n_rows), 6), np.tile(np.arange(6), n_rows))
    return _PATTERNS[n_rows]


def assemble(
    constraints: Sequence[Constraint], p: np.ndarray, R: np.ndarray, dense: bool = False
) -> tuple[np.ndarray, sp.csr_matrix | np.ndarray]:
    """Stack all constraints: c (m,) and J = ∂c/∂ν as a sparse (m, 6L) CSR matrix, or with
    ``dense`` as an ndarray (the same entries; small bodies are faster without sparse overhead)."""
    n_links = p.shape[0]
    rows, cols, vals, cs = [], [], [], []
    offset = 0
    for con in constraints:
        c_k, (rr, cc, vv) = con.residual_and_triplets(p, R)
        cs.append(c_k)
        rows.append(rr + offset)
        cols.append(cc)
        vals.append(vv)
        offset += con.n_rows
    c = np.concatenate(cs) if cs else np.zeros(0)
    if dense:
        J = np.zeros((offset, 6 * n_links))
        if rows:
            np.add.at(J, (np.concatenate(rows), np.concatenate(cols)), np.concatenate(vals))
    elif rows:
        J = sp.coo_matrix(
            (np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=(offset, 6 * n_links)
        ).tocsr()
    else:
        J = sp.csr_matrix((0, 6 * n_links))
    return c, J


def block_inverse(blocks: np.ndarray, as_blocks: bool = False) -> sp.csr_matrix | np.ndarray:
    """(L, 6, 6) SPD blocks -> their block-diagonal inverse (6L, 6L) as a sparse matrix, or with
    ``as_blocks`` as the (L, 6, 6) inverse blocks (see :func:`apply_block_diagonal`)."""
    inv = np.linalg.inv(blocks)
    inv = 0.5 * (inv + np.swapaxes(inv, 1, 2))
    return inv if as_blocks else sp.block_diag(list(inv), format="csr")


def apply_block_diagonal(W: sp.spmatrix | np.ndarray, x: np.ndarray) -> np.ndarray:
    """``W x`` (6L,) for W a sparse (6L, 6L) matrix or its (L, 6, 6) diagonal blocks."""
    if isinstance(W, np.ndarray) and W.ndim == 3:
        return np.einsum("nij,nj->ni", W, x.reshape(-1, W.shape[1])).ravel()
    return W @ x


def _sandwich(J: sp.spmatrix | np.ndarray, W: sp.spmatrix | np.ndarray) -> sp.csr_matrix | np.ndarray:
    """``J W Jᵀ``: dense when J is an ndarray (W then sparse or (L, 6, 6) blocks), else sparse."""
    if isinstance(J, np.ndarray):
        m = J.shape[0]
        if isinstance(W, np.ndarray) and W.ndim == 3:
            L, k = W.shape[0], W.shape[1]
            JW = np.einsum("mni,nij->mnj", J.reshape(m, L, k), W).reshape(m, L * k)
        else:
            JW = np.asarray((W.T @ J.T).T)  # W is symmetric block-diagonal: (W Jᵀ)ᵀ = J W
        return JW @ J.T
    if isinstance(W, np.ndarray):
        W = sp.block_diag(list(W), format="csr")
    return (J @ W @ J.T).tocsr()


#: systems with at most this many rows are solved on dense matrices (speed only)
_DENSE_OPERATOR_ROWS = 256


class _DenseSymmetricOperator(spla.LinearOperator):
    """A dense symmetric matrix for scipy's ``cg``, with ``matvec`` the bare product ``A @ x``.

    Speed only: scipy wraps an ndarray in an operator whose ``matvec`` checks and reshapes its
    argument on every call, and ``cg`` makes two such calls an iteration (the matrix and the identity
    preconditioner): on a 54-row system ~1.3 µs of a ~6.8 µs iteration. The products are the same,
    so are the iterates (tested)."""

    def __init__(self, A: np.ndarray):
        super().__init__(A.dtype, A.shape)
        self.A = A

    def _matvec(self, x: np.ndarray) -> np.ndarray:
        return self.A @ x

    _rmatvec = matvec = _matvec  # symmetric; matvec without LinearOperator's checks


class _IdentityOperator(spla.LinearOperator):
    """The identity as ``cg``'s preconditioner, ``matvec`` returning its argument (as scipy's own
    identity operator does, without the argument checks); see :class:`_DenseSymmetricOperator`."""

    def __init__(self, n: int, dtype):
        super().__init__(dtype, (n, n))

    def _matvec(self, x: np.ndarray) -> np.ndarray:
        return x

    _rmatvec = matvec = _matvec


def solve_multipliers(
    J: sp.spmatrix | np.ndarray,
    W: sp.spmatrix | np.ndarray,
    b: np.ndarray,
    method: str = "cg",
    rtol: float = 1e-13,
    x0: np.ndarray | None = None,
) -> np.ndarray:
    """Solve ``(J W Jᵀ) λ = b`` for λ (m,).

    J: (m, 6L) sparse or dense; W: sparse (6L, 6L) or its (L, 6, 6) diagonal blocks.
    method: 'cg' (conjugate gradients, Jacobi-preconditioned), 'bicg' (biconjugate
    gradients, as in the paper) or 'dense' (numpy; tests). A tiny diagonal shift keeps
    redundant (rank-deficient) constraint sets solvable.
    """
    m = J.shape[0]
    if m == 0:
        return np.zeros(0)
    A = _sandwich(J, W)
    diag = A.diagonal().copy()
    shift = 1e-14 * max(float(diag.max()), 1e-300)
    if isinstance(A, np.ndarray):
        A[np.diag_indices(m)] += shift
    else:
        A = A + shift * sp.identity(m, format="csr")
    diag += shift
    if method == "dense":
        return np.linalg.solve(A if isinstance(A, np.ndarray) else A.toarray(), b)
    if not np.any(b):
        return np.zeros(m)
    solver = {"cg": spla.cg, "bicg": spla.bicg}.get(method)
    if solver is None:
        raise InputError(f"constraints: unknown linear solver method {method!r} (cg, bicg, dense)")
    if x0 is not None and (x0.shape != b.shape or not np.all(np.isfinite(x0))):
        x0 = None
    if m <= _DENSE_OPERATOR_ROWS:
        # Same Krylov iteration on a dense matrix (tiny systems run faster so). Jacobi
        # preconditioning as the symmetric scaling D^-1/2 A D^-1/2 (the same iterates as
        # preconditioning with D^-1), which spares the preconditioner's per-iteration call.
        s = 1.0 / np.sqrt(np.maximum(diag, 1e-300))
        A = A.toarray() if not isinstance(A, np.ndarray) else A
        As = s[:, None] * A * s[None, :]
        if method == "cg":
            y, info = solver(_DenseSymmetricOperator(As), s * b, x0=None if x0 is None else x0 / s, rtol=rtol,
                             atol=0.0, maxiter=20 * m + 50, M=_IdentityOperator(m, As.dtype))
        else:
            y, info = solver(As, s * b, x0=None if x0 is None else x0 / s, rtol=rtol, atol=0.0, maxiter=20 * m + 50)
        lam = s * y
    else:
        M = sp.diags(1.0 / np.maximum(diag, 1e-300))
        lam, info = solver(A, b, x0=x0, rtol=rtol, atol=0.0, maxiter=20 * m + 50, M=M)
    if info != 0:  # not converged: fall back to a direct solve
        lam = np.linalg.lstsq(A, b, rcond=None)[0] if isinstance(A, np.ndarray) else spla.spsolve(A.tocsc(), b)
    return np.asarray(lam, dtype=float)


# ---------------------------------------------------------------------------- solver


@dataclass
class SolveResult:
    """Solver output: poses p (L, 3), R (L, 3, 3); twists nu (L, 6) (dynamic: velocity
    [v, ω] m/s, rad/s; kinematic: the last increment); diagnostics."""

    p: np.ndarray
    R: np.ndarray
    nu: np.ndarray
    iterations: int
    constraint_norm: float
    converged: bool
    energy: float = 0.0
    lam: np.ndarray = field(default_factory=lambda: np.zeros(0))


class ConstraintSolver:
    """Virtual-work solver for L free rigid bodies with hard ``constraints``.

    masses: (L,) kg; inertias: (L, 3, 3) inertia tensors about the centre of mass in
    link axes, kg·m² (default: a 0.1 m sphere of that mass); centres_of_mass: (L, 3)
    link-frame centre of mass, m (default: the link origin). ``method``: 'cg' | 'bicg' |
    'dense' for ``(J W Jᵀ) λ = b``.
    """

    def __init__(
        self,
        n_links: int,
        constraints: Sequence[Constraint],
        masses: np.ndarray | None = None,
        inertias: np.ndarray | None = None,
        method: str = "cg",
        centres_of_mass: np.ndarray | None = None,
    ):
        self.n_links = int(n_links)
        self.constraints = list(constraints)
        for con in self.constraints:
            if any(k >= self.n_links for k in con.links):
                raise InputError(f"constraints: {type(con).__name__} refers to link >= {self.n_links}")
        self.masses = np.ones(self.n_links) if masses is None else np.asarray(masses, dtype=float)
        if self.masses.shape != (self.n_links,) or np.any(self.masses <= 0):
            raise InputError(
                f"constraints: masses must be ({self.n_links},) positive, got {self.masses.shape}"
            )
        if inertias is None:
            inertias = (0.4 * self.masses * 0.1**2)[:, None, None] * np.eye(3)[None]
        self.inertias = np.asarray(inertias, dtype=float)
        if self.inertias.shape != (self.n_links, 3, 3):
            raise InputError(
                f"constraints: inertias must be ({self.n_links}, 3, 3), got {self.inertias.shape}"
            )
        self.com = (
            np.zeros((self.n_links, 3)) if centres_of_mass is None else np.asarray(centres_of_mass, float)
        )
        if self.com.shape != (self.n_links, 3):
            raise InputError(
                f"constraints: centres_of_mass must be ({self.n_links}, 3), got {self.com.shape}"
            )
        self.method = method
        #: trial steps: plain, then with the second-order correction (projection) if rejected
        self._corrections = (False, True)
        self.n_rows = sum(c.n_rows for c in self.constraints)
        #: small systems (a body) are assembled as dense arrays and W kept as its (L, 6, 6)
        #: blocks: the same arithmetic without scipy.sparse's per-call overhead
        self._dense = self.n_rows <= _DENSE_OPERATOR_ROWS and self.n_links <= _DENSE_OPERATOR_ROWS

    # -- pieces -------------------------------------------------------------
    def _check(self, p: np.ndarray, R: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        p = np.array(p, dtype=float)
        R = np.array(R, dtype=float)
        if p.shape != (self.n_links, 3) or R.shape != (self.n_links, 3, 3):
            raise InputError(
                f"constraints: poses must be p ({self.n_links}, 3), R ({self.n_links}, 3, 3); "
                f"got {p.shape}, {R.shape}"
            )
        return p, R

    def mass_blocks(self, R: np.ndarray) -> np.ndarray:
        """(L, 6, 6) generalised mass about each link origin, world frame:
        ``m AᵀA + blockdiag(0, R I_c Rᵀ)`` with ``A = [I, −[c]×]`` (c = R com)."""
        c = np.einsum("nij,nj->ni", R, self.com)
        A = np.concatenate([np.broadcast_to(np.eye(3), (self.n_links, 3, 3)), -skew(c)], axis=2)
        M = self.masses[:, None, None] * (np.swapaxes(A, 1, 2) @ A)
        M[:, 3:, 3:] += R @ self.inertias @ np.swapaxes(R, 1, 2)
        return M

    def velocity_forces(self, R: np.ndarray, nu: np.ndarray) -> np.ndarray:
        """(L, 6) centripetal / gyroscopic terms b(q, q̇) of ``M q̈ + b = Q`` (Newton–Euler
        about the link origin)."""
        c = np.einsum("nij,nj->ni", R, self.com)
        w = nu[:, 3:]
        Ic = R @ self.inertias @ np.swapaxes(R, 1, 2)
        cent = self.masses[:, None] * cross(w, cross(w, c))
        gyro = cross(w, np.einsum("nij,nj->ni", Ic, w)) + cross(c, cent)
        return np.concatenate([cent, gyro], axis=1)

    def residual(self, p: np.ndarray, R: np.ndarray) -> np.ndarray:
        """c(q): (m,)."""
        if not self.constraints:
            return np.zeros(0)
        return np.concatenate([con.residual(p, R) for con in self.constraints])

    def jacobian(self, p: np.ndarray, R: np.ndarray) -> sp.csr_matrix:
        """J = ∂c/∂ν: sparse (m, 6L)."""
        return assemble(self.constraints, p, R)[1]

    def _assemble(self, p: np.ndarray, R: np.ndarray) -> tuple[np.ndarray, sp.csr_matrix | np.ndarray]:
        return assemble(self.constraints, p, R, dense=self._dense)

    def _weights(self, blocks: np.ndarray) -> sp.csr_matrix | np.ndarray:
        """W from the (L, 6, 6) blocks it inverts, in the form this solver's systems use."""
        return block_inverse(blocks, as_blocks=self._dense)

    def project(
        self,
        p: np.ndarray,
        R: np.ndarray,
        W: sp.spmatrix | np.ndarray | None = None,
        tol: float = 1e-9,
        max_iterations: int = 50,
    ) -> tuple[np.ndarray, np.ndarray, float, int]:
        """Drift removal: repeat ``δq = −W Jᵀ (J W Jᵀ)⁻¹ c`` (the W-weighted least change)
        until ‖c‖ < tol. W: sparse (6L, 6L) or its (L, 6, 6) blocks (default: the inverse
        link masses). Returns (p, R, ‖c‖, iterations)."""
        p, R = self._check(p, R)
        if W is None:
            W = self._weights(self.mass_blocks(R))
        c, J = self._assemble(p, R)
        norm = float(np.linalg.norm(c)) if c.size else 0.0
        it = 0
        while norm >= tol and it < max_iterations:
            lam = solve_multipliers(J, W, -c, self.method, rtol=1e-11)
            p, R = retract(p, R, apply_block_diagonal(W, J.T @ lam))
            c, J = self._assemble(p, R)
            norm = float(np.linalg.norm(c))
            it += 1
        return p, R, norm, it

    # -- kinematic ------------------------------------------------------------
    def _constraint_curvature(self, p: np.ndarray, R: np.ndarray, lam: np.ndarray) -> np.ndarray:
        """(L, 6, 6) Σ λ_k ∂²c_k/∂ν² of the point-coincidence constraints (rotational part)."""
        H = np.zeros((self.n_links, 6, 6))
        if lam.size != self.n_rows:
            return H
        offset = 0
        for con in self.constraints:
            if isinstance(con, PointCoincidence):
                lk = lam[offset : offset + 3]
                for link, local, sign in ((con.link_a, con.point_a, -1.0), (con.link_b, con.point_b, 1.0)):
                    if link >= 0:
                        H[link, 3:, 3:] += sign * _curvature(lk, R[link] @ local)
            elif isinstance(con, BallJoints):
                lk = lam[offset : offset + con.n_rows].reshape(-1, 3)
                ra, rb = con._lever(R)
                for links, r, sign in ((con.link_a, ra, -1.0), (con.link_b, rb, 1.0)):
                    fr = lk[:, :, None] * r[:, None, :]
                    curv = 0.5 * (fr + np.swapaxes(fr, 1, 2)) - np.einsum("ni,ni->n", lk, r)[
                        :, None, None
                    ] * np.eye(3)
                    np.add.at(H, (links, slice(3, 6), slice(3, 6)), sign * curv)
            offset += con.n_rows
        return H

    @staticmethod
    def _convexify(K: np.ndarray) -> np.ndarray:
        """Clip each (6, 6) block's eigenvalues at 0."""
        K = 0.5 * (K + np.swapaxes(K, 1, 2))
        vals, vecs = np.linalg.eigh(K)
        return (vecs * np.maximum(vals, 0.0)[:, None, :]) @ np.swapaxes(vecs, 1, 2)

    def solve_kinematic(
        self,
        p: np.ndarray,
        R: np.ndarray,
        terms: SoftTerms,
        max_iterations: int = 30,
        tol: float = 1e-9,
        step_tol: float = 1e-7,
        mass_weight: float = 1e-3,
        max_rotation_step: float = 0.5,
        second_order: bool = True,
        newton_radius: float = 0.05,
    ) -> SolveResult:
        """Kinematic variant: iterate ``q̇ = W (Q + Jᵀλ)``, ``q ← q ⊕ q̇`` (Δt = 1) with
        ``(J W Jᵀ) λ = −J W Q − c`` and ``W = (K + μ M)⁻¹`` (K the springs' Gauss–Newton
        stiffness, M the link masses), then project to ‖c‖ < tol. With ``second_order``
        K also holds the rotational curvature of the springs and of the ball-joint
        constraint forces (the Lagrangian's Hessian, eigenvalues clipped at 0 per link),
        which restores fast convergence when the goals cannot all be met; it is used
        once the previous step was smaller than ``newton_radius`` (m or rad), far from
        the solution plain Gauss–Newton is more robust.

        A rejected trial step is first retried after a few projection iterations back
        onto ``c(q) = 0`` (a second-order correction: "projected Gauss–Newton"). μ
        starts at ``mass_weight`` and is adapted Levenberg–Marquardt style: a step is
        accepted only if it lowers the exact-penalty merit ``E + ρ‖c‖₁`` (ρ = 2‖λ‖∞),
        otherwise μ grows tenfold (a heavier, more cautious body). Pose-dependent
        terms are re-evaluated at each trial pose, so the merit is one function of q.

        p (L, 3), R (L, 3, 3): starting poses (world_from_link); terms: soft terms or a
        callable (p, R) -> soft terms re-evaluated at every accepted iterate. step_tol:
        stop when the largest increment (m or rad) is below it. max_rotation_step: rad,
        per iteration (larger increments are scaled down).
        """
        p, R = self._check(p, R)
        nu = np.zeros((self.n_links, 6))
        lam = np.zeros(self.n_rows)
        mu = mass_weight
        W = None
        iterations = 0
        newton = False
        current = terms(p, R) if callable(terms) else terms
        Qf, K, energy = soft_energy_terms(self.n_links, p, R, current)
        c, J = self._assemble(p, R)
        for iterations in range(1, max_iterations + 1):  # noqa: B007 - reported below
            M = self.mass_blocks(R)
            if newton:
                K = self._convexify(K - self._constraint_curvature(p, R, lam))
            accepted = False
            for trial in range(12):
                W = self._weights(K + mu * M)
                WQ = apply_block_diagonal(W, Qf.ravel())
                lam = solve_multipliers(J, W, -(J @ WQ) - c, self.method, rtol=1e-9, x0=lam)
                nu = (WQ + apply_block_diagonal(W, J.T @ lam)).reshape(-1, 6)
                rot = float(np.max(np.linalg.norm(nu[:, 3:], axis=1))) if self.n_links else 0.0
                nu *= min(1.0, max_rotation_step / max(rot, 1e-300))
                rho = 2.0 * float(np.max(np.abs(lam))) if lam.size else 0.0
                merit = energy + rho * float(np.sum(np.abs(c)))
                p_t, R_t = retract(p, R, nu)
                newton_t = second_order and float(np.max(np.abs(nu))) < newton_radius  # (if accepted)
                # the second-order correction on the first trial only: on a damped retry (larger mu)
                # it was never what got accepted (seed 3: 0 of ~1100 retries), and costs a projection
                for correction in self._corrections if trial == 0 else self._corrections[:1]:
                    if correction:
                        if not self.n_rows:
                            break
                        # Second-order correction: back onto c(q) = 0 (avoids the Maratos effect).
                        p_t, R_t, _, _ = self.project(p_t, R_t, W, tol=1e-10, max_iterations=3)
                    # Pose-dependent terms are re-evaluated at the trial pose, so the merit is one
                    # function of q (its gradient is only approximated by the lagged terms).
                    trial_terms = terms(p_t, R_t) if callable(terms) else terms
                    # (the next iteration's forces and stiffness, kept if the step is accepted)
                    Q_t, K_t, E_t = soft_energy_terms(self.n_links, p_t, R_t, trial_terms, newton_t)
                    c_t = self.residual(p_t, R_t) if self.n_rows else c
                    merit_t = E_t + rho * float(np.sum(np.abs(c_t)))
                    if merit_t <= merit + 1e-12 * (1.0 + abs(merit)):
                        accepted = True
                        break
                if accepted:
                    mu = max(mu / 3.0, 1e-3 * mass_weight)
                    break
                if float(np.max(np.abs(nu))) < step_tol:
                    break  # converged: an accepted step this small would end the iteration too
                mu *= 10.0
            if not accepted:
                break
            p, R = p_t, R_t
            newton, Qf, K, energy = newton_t, Q_t, K_t, E_t
            c, J = self._assemble(p, R)
            if float(np.max(np.abs(nu))) < step_tol:
                break
        p, R, norm, _ = self.project(p, R, W, tol=tol)
        converged = norm < tol
        return SolveResult(p, R, nu, iterations, norm, converged, energy, lam)

    # -- dynamic --------------------------------------------------------------
    def step_dynamic(
        self,
        p: np.ndarray,
        R: np.ndarray,
        nu: np.ndarray,
        dt: float,
        terms: SoftTerms,
        linear_damping: float = 0.0,
        angular_damping: float = 0.0,
        k_s: float | None = None,
        k_d: float | None = None,
        tol: float = 1e-9,
        project: bool = True,
        stiffness_damping: float = 0.0,
    ) -> SolveResult:
        """Full-dynamics step (paper Eq. 1–5): ``q̈ = W (Q + Jᵀλ)`` with
        ``(J W Jᵀ) λ = −J W Q − J̇ q̇ − k_s c − k_d ċ``; springs linearly implicit
        (``W = (M + Δt B + Δt² K)⁻¹``), symplectic Euler, then drift projection of
        positions and velocities when ``project``.

        nu: (L, 6) twists [v, ω] (m/s, rad/s, world); dt: s; damping B: N·s/m and
        N·m·s/rad (multiplied by each link's mass / inertia); ``stiffness_damping`` β (s) adds
        stiffness-proportional (Rayleigh) damping ``β K``, which damps each spring mode in proportion
        to its frequency (a light link on a stiff spring, e.g. a hand's spin on its rest-pose spring,
        is otherwise almost undamped). k_s, k_d default to the critically damped 1/dt², 2/dt.
        """
        p, R = self._check(p, R)
        nu = np.array(nu, dtype=float).reshape(self.n_links, 6)
        if not dt > 0:
            raise InputError(f"constraints: dt must be > 0, got {dt}")
        k_s = 1.0 / dt**2 if k_s is None else k_s
        k_d = 2.0 / dt if k_d is None else k_d
        current = terms(p, R) if callable(terms) else terms
        F, K, energy = soft_energy_terms(self.n_links, p, R, current)
        M = self.mass_blocks(R)
        B = np.zeros_like(M)
        B[:, :3, :3] = linear_damping * M[:, :3, :3]
        B[:, 3:, 3:] = angular_damping * M[:, 3:, 3:]
        if stiffness_damping > 0:
            B = B + stiffness_damping * K
        W = self._weights(M + dt * B + dt * dt * K)
        Qv = (F - self.velocity_forces(R, nu) - np.einsum("nij,nj->ni", dt * K + B, nu)).ravel()
        c, J = self._assemble(p, R)
        qd = nu.ravel()
        cdot = J @ qd
        # J̇ q̇ by a directional finite difference of J along q̇.
        h = 1e-6 / max(float(np.max(np.abs(qd))), 1.0)
        p_h, R_h = retract(p, R, h * nu)
        Jdot_qd = (self._assemble(p_h, R_h)[1] @ qd - cdot) / h if c.size else c
        WQ = apply_block_diagonal(W, Qv)
        lam = solve_multipliers(J, W, -(J @ WQ) - Jdot_qd - k_s * c - k_d * cdot, self.method)
        qdd = WQ + apply_block_diagonal(W, J.T @ lam)
        nu = (qd + dt * qdd).reshape(-1, 6)
        p, R = retract(p, R, dt * nu)
        norm = float(np.linalg.norm(self.residual(p, R))) if self.n_rows else 0.0
        if project and self.n_rows:
            Wm = self._weights(M)
            p, R, norm, _ = self.project(p, R, Wm, tol=tol)
            _, J = self._assemble(p, R)
            lam_v = solve_multipliers(J, Wm, -(J @ nu.ravel()), self.method)
            nu = (nu.ravel() + apply_block_diagonal(Wm, J.T @ lam_v)).reshape(-1, 6)
        return SolveResult(p, R, nu, 1, norm, norm < tol or not project, energy, lam)
