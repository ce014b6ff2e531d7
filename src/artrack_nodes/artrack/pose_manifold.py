"""The pose manifold M = {F(θ) | θ ∈ Θ} of a kinematic sub-tree and the projection onto it
(ALGORITHMS.md §3, eqs. (2)–(4)).

The particle filter of §3 tracks only the *active* links' joint angles θ (d,)
(default: torso, head, both upper arms and elbows; the root and the legs stay
at a fixed base pose). F maps θ to P spatial end points (world, m): the distal
end of every point link, except the hands, whose point is the grip (the
centre of the hand's first shape), because that is what holds an object.

Forward kinematics here runs over the needed chain only (the point links and
their ancestors, 9 of the body's 15 links by default) for any batch of poses;
it equals :meth:`BodyModel.forward_kinematics` (tested) and is several times
cheaper, which matters for the rejection sampler of ``p_kkb`` (millions of
poses per frame). The Jacobian dF/dθ is analytic: a ball joint's rotation
vector r turns its sub-tree about the world axes ω_k = R_parent J_l(r) e_k
(J_l the left Jacobian of SO(3)), a hinge about R_parent a; a point p moves
by ω × (p − joint origin).

Projection (eq. (4)): θ̂ = argmin_θ Σ_p w_p² ‖x_p − F_p(θ)‖² s.t. θ ∈ Θ,
solved for all particles at once by a batched Levenberg–Marquardt with a
projected (active-set) step and clipping to the box (:meth:`PoseManifold.project`),
or, as a library reference, by one bounded ``scipy.optimize.least_squares``
problem with a block-diagonal sparse Jacobian (:meth:`PoseManifold.project_scipy`).
Weights w_p > 1 express a smaller prior variance of point p (the Σ⁻¹ metric).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import scipy.sparse
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from .body_model import BodyModel
from .lie import left_jacobian_so3, skew

__all__ = [
    "DEFAULT_ACTIVE_LINKS",
    "DEFAULT_POINT_LINKS",
    "PoseManifold",
    "ProjectionInfo",
    "left_jacobian_so3",
]

#: links whose joint angles the §3 tracker estimates (the rest stays at the base pose)
DEFAULT_ACTIVE_LINKS = ("torso", "head", "l_upper_arm", "l_forearm", "r_upper_arm", "r_forearm")
#: links whose end points span R^{3P} (hands: their grip point)
DEFAULT_POINT_LINKS = ("torso", "head", "l_upper_arm", "l_forearm", "l_hand", "r_upper_arm", "r_forearm",
                       "r_hand")
HAND_LINKS = ("l_hand", "r_hand")


def _rotate(rotvec: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Rodrigues: vectors v (n, 3) rotated by rotation vectors (n, 3)."""
    th = np.sqrt(np.einsum("ni,ni->n", rotvec, rotvec))[:, None]
    k = rotvec / np.where(th > 1e-12, th, 1.0)
    c, s = np.cos(th), np.sin(th)
    kv = np.einsum("ni,ni->n", k, v)[:, None]
    kx, ky, kz = k[:, 0], k[:, 1], k[:, 2]
    vx, vy, vz = v[:, 0], v[:, 1], v[:, 2]
    cross = np.stack([ky * vz - kz * vy, kz * vx - kx * vz, kx * vy - ky * vx], axis=1)
    return v * c + cross * s + k * (kv * (1.0 - c))


@dataclass
class ProjectionInfo:
    """Outcome of a batched projection: iterations run, final cost ½Σ w²‖x − F‖² (n,)."""

    iterations: int
    cost: np.ndarray


class PoseManifold:
    """End points F(θ) (n, P, 3) of a body sub-tree over the active dofs θ (n, d), with
    Jacobian and projection (module docstring).

    body: the body model; base_theta: (n_dof,) full pose supplying the inactive
    dofs (root, legs, hands); active_links / point_links: link names.
    Attributes: cols (d,) columns of the active dofs in the full theta,
    lower / upper (d,) their box limits, point_names (P,), hand_points (2,)
    indices of the left / right grip points in the P points (-1 if absent).
    """

    def __init__(self, body: BodyModel, base_theta: np.ndarray,
                 active_links: Sequence[str] = DEFAULT_ACTIVE_LINKS,
                 point_links: Sequence[str] = DEFAULT_POINT_LINKS):
        self.body = body
        self.active_links = [body.link_index(n) for n in active_links]
        for i in self.active_links:
            if body.links[i].joint == "free":
                raise ValueError("pose_manifold: the root (free joint) cannot be an active link")
        self.cols = np.concatenate([np.arange(body.links[i].dof_slice.start, body.links[i].dof_slice.stop)
                                    for i in self.active_links]).astype(int)
        self.d = len(self.cols)
        self.lower = body.lower[self.cols].copy()
        self.upper = body.upper[self.cols].copy()
        self.point_link_idx = np.array([body.link_index(n) for n in point_links], int)
        self.point_names = list(point_links)
        pts = []
        for n in point_links:
            lk = body.link(n)
            pts.append(lk.shapes[0].centre.copy() if n in HAND_LINKS and lk.shapes else lk.end.copy())
        self.point_local = np.array(pts, float).reshape(-1, 3)
        self.P = len(self.point_local)
        self.hand_points = np.array([self.point_names.index(h) if h in self.point_names else -1
                                     for h in HAND_LINKS], int)
        # The chain: point links and all their ancestors, in topological order.
        need: set[int] = set()
        for i in self.point_link_idx:
            j = int(i)
            while j >= 0:
                need.add(j)
                j = int(body.parent_index[j])
        self.chain = sorted(need)
        self._pos_in_chain = {link: k for k, link in enumerate(self.chain)}
        self._point_chain = np.array([self._pos_in_chain[int(i)] for i in self.point_link_idx], int)
        # per active link: column offset in θ and joint type
        self._active_info = []
        c = 0
        for i in self.active_links:
            lk = body.links[i]
            self._active_info.append((i, c, lk.joint, lk.axis.copy()))
            c += lk.n_dof
        # which points each active link moves (descendant-or-self)
        anc = {}
        for p, li in enumerate(self.point_link_idx):
            j, chain_up = int(li), set()
            while j >= 0:
                chain_up.add(j)
                j = int(body.parent_index[j])
            anc[p] = chain_up
        self._moves = [np.array([p for p in range(self.P) if i in anc[p]], int) for i, *_ in self._active_info]
        self.set_base(base_theta)

    # ------------------------------------------------------------------ base pose
    def set_base(self, base_theta: np.ndarray) -> None:
        """Set the inactive dofs (root, legs, hands) from a full pose (n_dof,)."""
        base_theta = np.asarray(base_theta, float).reshape(self.body.n_dof).copy()
        self.base_theta = base_theta
        T = self.body.forward_kinematics(base_theta)
        active = set(self.active_links)
        self._fixed_world: dict[int, tuple[np.ndarray, np.ndarray]] = {}
        self._fixed_local: dict[int, np.ndarray] = {}
        moving: set[int] = set()
        for i in self.chain:
            p = int(self.body.parent_index[i])
            if i in active or p in moving:
                moving.add(i)
            if i not in moving:
                self._fixed_world[i] = (T[i, :3, :3].copy(), T[i, :3, 3].copy())
            if i not in active and p >= 0:
                self._fixed_local[i] = T[p, :3, :3].T @ T[i, :3, :3]

    def full_theta(self, theta: np.ndarray) -> np.ndarray:
        """Full poses (..., n_dof): the base pose with the active dofs θ (..., d) filled in."""
        theta = np.asarray(theta, float)
        out = np.broadcast_to(self.base_theta, theta.shape[:-1] + (self.body.n_dof,)).copy()
        out[..., self.cols] = theta
        return out

    def active(self, theta_full: np.ndarray) -> np.ndarray:
        """The active dofs (..., d) of full poses (..., n_dof)."""
        return np.asarray(theta_full, float)[..., self.cols].copy()

    def clip(self, theta: np.ndarray) -> np.ndarray:
        """θ (..., d) clipped to the box Θ."""
        return np.clip(theta, self.lower, self.upper)

    # ------------------------------------------------------------------ kinematics
    def frames(self, theta: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """World frames of the chain links for θ (n, d).

        Returns (R (n, C, 3, 3) world_from_link rotations, o (n, C, 3) link
        origins in the world (m), local (n, A, 3, 3) parent_from_link rotations
        of the active links), C = len(self.chain).
        """
        theta = np.asarray(theta, float).reshape(-1, self.d)
        n = len(theta)
        C = len(self.chain)
        R = np.empty((n, C, 3, 3))
        o = np.empty((n, C, 3))
        local_active = np.empty((n, len(self._active_info), 3, 3))
        local_of: dict[int, np.ndarray] = {}
        for a, (i, c, joint, axis) in enumerate(self._active_info):
            if joint == "ball":
                loc = Rotation.from_rotvec(theta[:, c:c + 3]).as_matrix()
            else:
                K = skew(axis)
                s = np.sin(theta[:, c])[:, None, None]
                co = np.cos(theta[:, c])[:, None, None]
                loc = np.eye(3) + s * K + (1.0 - co) * (K @ K)
            local_active[:, a] = loc
            local_of[i] = loc
        for k, i in enumerate(self.chain):
            if i in self._fixed_world:
                R[:, k], o[:, k] = self._fixed_world[i]
                continue
            kp = self._pos_in_chain[int(self.body.parent_index[i])]
            loc = local_of[i] if i in local_of else self._fixed_local[i]
            R[:, k] = R[:, kp] @ loc
            o[:, k] = o[:, kp] + R[:, kp] @ self.body.links[i].offset
        return R, o, local_active

    def end_points(self, theta: np.ndarray) -> np.ndarray:
        """F(θ): (n, P, 3) world end points (m) for θ (n, d)."""
        R, o, _ = self.frames(theta)
        return self._points(R, o)

    def _points(self, R: np.ndarray, o: np.ndarray) -> np.ndarray:
        k = self._point_chain
        return np.einsum("npij,pj->npi", R[:, k], self.point_local) + o[:, k]

    def hands(self, theta: np.ndarray) -> np.ndarray:
        """(n, 2, 3) world grip points of the left and right hand for θ (n, d).

        Evaluated point-wise up the chain (v ← offset + R_local v, rotation vectors
        applied by Rodrigues' formula), without building the links' frames: ~20×
        cheaper than :meth:`end_points`, for the millions of draws of ``p_kkb``.
        """
        if np.any(self.hand_points < 0):
            raise ValueError("pose_manifold: both hands must be point links")
        theta = np.asarray(theta, float).reshape(-1, self.d)
        return np.stack([self._point_up_chain(theta, int(p)) for p in self.hand_points], axis=1)

    def _point_up_chain(self, theta: np.ndarray, p: int) -> np.ndarray:
        """World position (n, 3) of end point p for θ (n, d), applied link by link up the tree."""
        active = {i: (c, joint, axis) for i, c, joint, axis in self._active_info}
        v = np.broadcast_to(self.point_local[p], (len(theta), 3))
        j = int(self.point_link_idx[p])
        while j not in self._fixed_world:
            if j in active:
                c, joint, axis = active[j]
                if joint == "ball":
                    v = _rotate(theta[:, c:c + 3], v)
                else:  # hinge: Rodrigues about the fixed unit axis
                    a = theta[:, c:c + 1]
                    co, si = np.cos(a), np.sin(a)
                    v = v * co + np.cross(axis, v) * si + np.outer(v @ axis, axis) * (1.0 - co)
            else:
                v = v @ self._fixed_local[j].T
            v = self.body.links[j].offset + v
            j = int(self.body.parent_index[j])
        R, o = self._fixed_world[j]
        return v @ R.T + o

    def jacobian(self, theta: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(F(θ) (n, P, 3), dF/dθ (n, P, 3, d)) for θ (n, d)."""
        theta = np.asarray(theta, float).reshape(-1, self.d)
        R, o, _ = self.frames(theta)
        X = self._points(R, o)
        n = len(theta)
        J = np.zeros((n, self.P, 3, self.d))
        for a, (i, c, joint, axis) in enumerate(self._active_info):
            k = self._pos_in_chain[i]
            Rp = R[:, self._pos_in_chain[int(self.body.parent_index[i])]]
            if joint == "ball":
                omega = Rp @ left_jacobian_so3(theta[:, c:c + 3])      # (n, 3, 3) columns = axes
                omegas = [omega[:, :, m] for m in range(3)]
            else:
                omegas = [Rp @ axis]
            pts = self._moves[a]
            arm = X[:, pts] - o[:, k][:, None, :]                         # (n, q, 3)
            for m, w in enumerate(omegas):
                J[:, pts, :, c + m:c + m + 1] = np.cross(w[:, None, :], arm)[..., None]
        return X, J

    # ------------------------------------------------------------------ projection
    def project(self, x: np.ndarray, theta0: np.ndarray, weights: np.ndarray | None = None,
                reg: float = 0.0, max_iter: int = 30, tol: float = 1e-10) -> tuple[np.ndarray, ProjectionInfo]:
        """Project spatial samples x (n, P, 3) onto M (eq. (4)), all particles at once.

        theta0: (n, d) start (clipped into Θ); weights: (P,) or (n, P) point weights
        (default 1); reg: m/rad, adds reg²‖θ − θ0‖² to the cost (0: eq. (4) exactly; a small
        value makes directions that move no end point, e.g. the twist of a straight arm,
        stay at the start instead of drifting). Batched Levenberg–Marquardt: per particle damping λ, steps
        restricted to the dofs not pinned at a bound by the gradient, then
        clipped into Θ; a step is kept only if it lowers the cost. Stops when no
        particle's cost drops by more than ``tol`` (relative) or after max_iter.
        Returns (θ̂ (n, d) inside Θ, ProjectionInfo).
        """
        x = np.asarray(x, float).reshape(-1, self.P, 3)
        n = len(x)
        w = np.ones((n, self.P)) if weights is None else np.broadcast_to(np.asarray(weights, float), (n, self.P))
        w3 = np.repeat(w, 3, axis=1)                                          # (n, 3P)
        theta = self.clip(np.asarray(theta0, float).reshape(n, self.d))
        start = np.asarray(theta0, float).reshape(n, self.d)
        lam = np.full(n, 1e-2)
        reg = float(reg)

        def residual(th, idx):
            r = w3[idx] * (self.end_points(th) - x[idx]).reshape(len(idx), -1)
            return np.concatenate([r, reg * (th - start[idx])], axis=1) if reg > 0 else r

        r = residual(theta, np.arange(n))
        cost = 0.5 * np.sum(r * r, axis=1)
        iterations = 0
        eye = np.eye(self.d)
        run = np.arange(n)  # particles still improving
        for iterations in range(1, max_iter + 1):  # noqa: B007 (reported after the loop)
            th, rr, lm = theta[run], r[run], lam[run]
            _, J = self.jacobian(th)
            J = w3[run, :, None] * J.reshape(len(run), 3 * self.P, self.d)
            if reg > 0:
                J = np.concatenate([J, np.broadcast_to(reg * eye, (len(run), self.d, self.d))], axis=1)
            g = np.einsum("nmd,nm->nd", J, rr)
            H = np.einsum("nmd,nme->nde", J, J)
            pinned = ((th <= self.lower + 1e-12) & (g > 0)) | ((th >= self.upper - 1e-12) & (g < 0))
            free = ~pinned
            mask = free[:, :, None] & free[:, None, :]
            diag = np.einsum("ndd->nd", H)
            floor = 1e-3 * diag.max(axis=1, keepdims=True) + 1e-12
            A = (np.where(mask, H, 0.0) + eye * (lm[:, None] * np.maximum(diag, floor))[:, None, :]
                 + eye * pinned[:, None, :])
            step = -np.linalg.solve(A, np.where(free, g, 0.0)[..., None])[..., 0]
            cand = self.clip(th + step)
            r_new = residual(cand, run)
            cost_new = 0.5 * np.sum(r_new * r_new, axis=1)
            better = cost_new < cost[run]
            gain = np.where(better, cost[run] - cost_new, 0.0)
            theta[run[better]] = cand[better]
            r[run[better]] = r_new[better]
            cost[run[better]] = cost_new[better]
            lam[run] = np.clip(np.where(better, lm / 10.0, lm * 4.0), 1e-7, 1e9)
            done = (better & (gain <= tol * np.maximum(cost[run], 1e-12))) | (~better & (lam[run] > 1e4)) \
                | (np.abs(step).max(axis=1) < 1e-12)
            run = run[~done]
            if len(run) == 0:
                break
        return theta, ProjectionInfo(iterations=iterations, cost=cost)

    def project_scipy(self, x: np.ndarray, theta0: np.ndarray, weights: np.ndarray | None = None,
                      reg: float = 0.0, **kwargs) -> tuple[np.ndarray, ProjectionInfo]:
        """The same projection (same cost, ``reg`` included) as one bounded
        ``scipy.optimize.least_squares`` problem over all particles (block-diagonal sparse
        Jacobian, method 'trf'); a library reference for :meth:`project` (slower).
        Returns (θ̂ (n, d), ProjectionInfo)."""
        x = np.asarray(x, float).reshape(-1, self.P, 3)
        n = len(x)
        w = np.ones((n, self.P)) if weights is None else np.broadcast_to(np.asarray(weights, float), (n, self.P))
        w3 = np.repeat(w, 3, axis=1)
        start = np.asarray(theta0, float).reshape(n, self.d)
        reg = float(reg)
        m = 3 * self.P + (self.d if reg > 0 else 0)
        rows = np.broadcast_to(np.arange(n)[:, None, None] * m + np.arange(m)[None, :, None], (n, m, self.d)).ravel()
        cols = np.broadcast_to(np.arange(n)[:, None, None] * self.d + np.arange(self.d)[None, None, :],
                               (n, m, self.d)).ravel()

        def resid(th):
            r = w3 * (self.end_points(th) - x).reshape(n, -1)
            return np.concatenate([r, reg * (th - start)], axis=1) if reg > 0 else r

        def jac(z):
            _, J = self.jacobian(z.reshape(n, self.d))
            J = w3[:, :, None] * J.reshape(n, 3 * self.P, self.d)
            if reg > 0:
                J = np.concatenate([J, np.broadcast_to(reg * np.eye(self.d), (n, self.d, self.d))], axis=1)
            return scipy.sparse.csr_matrix((J.ravel(), (rows, cols)), shape=(n * m, n * self.d))

        span = self.upper - self.lower
        x0 = np.clip(start, self.lower + 1e-9 * span, self.upper - 1e-9 * span)
        opts = {"xtol": 1e-12, "ftol": 1e-12, "gtol": 1e-12, "max_nfev": 200}
        opts.update(kwargs)
        sol = least_squares(lambda z: resid(z.reshape(n, self.d)).ravel(), x0.ravel(), jac=jac,
                            bounds=(np.tile(self.lower, n), np.tile(self.upper, n)),
                            method="trf", tr_solver="lsmr", x_scale="jac", **opts)
        th = sol.x.reshape(n, self.d)
        r = resid(th)
        return th, ProjectionInfo(iterations=int(sol.nfev), cost=0.5 * np.sum(r * r, axis=1))
