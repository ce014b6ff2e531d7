"""The body model fitted to 3-D blobs by bounded least squares (ALGORITHMS.md §1, the raw tracker).

:func:`fit_pose` fits theta to point targets (a 3-D blob's centre on its link, whitened by its
information), link goals (the edge statistics' soft link constraints, ALGORITHMS.md §2 "Fusion"),
the floor contact (:class:`GroundContact`), upright segments (:class:`UprightSegment`) and weak
rest / previous-pose priors, within the joint limits (``scipy.optimize.least_squares``). How the
estimators use it (the baseline each frame, the kinematic filters' outlier test and orientation
goals, the left/right exchange screens) is described in ``artrack.baseline_estimator``
and ``artrack.kalman_skeleton``.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy.optimize import least_squares

from .body_model import BodyModel
from .errors import InputError
from .lie import inverse_se3, log_se3, skew


@dataclass
class PointTarget:
    """A fit target: link point ``local`` (link frame, m) should be at ``y`` (world, m)
    with information ``info`` (3, 3) m⁻² (inverse covariance)."""

    link: int
    local: np.ndarray
    y: np.ndarray
    info: np.ndarray


@dataclass
class LinkGoals:
    """Soft constraints on link motions for :func:`fit_pose`: for links (G,), the reference
    poses' inverses (G, 4, 4) (link_from_world at the reference), the measured motions
    xi_hat (G, 6) in the link frames and whiteners sqrt_information (G, 6, 6) (Sᵀ S = C)."""

    links: np.ndarray
    inverse_reference: np.ndarray
    xi_hat: np.ndarray
    sqrt_information: np.ndarray

    @classmethod
    def from_edges(cls, stats, sigma_px: float, min_found: int = 0) -> LinkGoals:
        """From combined :class:`artrack.edge_fusion.LinkEdgeStatistics`; the information is
        scaled by 1/sigma_px² (the edge measurement noise, px)."""
        use = np.flatnonzero(stats.measured & (stats.samples_found >= min_found))
        xi = stats.xi_hat()[use]
        S = _whitener(np.array([stats.information[i] / sigma_px**2 for i in use]).reshape(-1, 6, 6))
        return cls(use, inverse_se3(stats.reference[use]), xi, S)


@dataclass
class GroundContact:
    """Soft floor contact for :func:`fit_pose`: the body's lowest points at rest (``links`` (F,),
    ``local`` (F, 3) link frame, e.g. the ankles) stand ``height`` (F,) m above the floor at rest.
    A person standing or walking on the floor z = ``floor_z`` (world, m) keeps at least one of them
    there, and none below: residuals ``(min_k (z_k − h_k) − floor_z) / sigma`` and
    ``min(z_k − h_k − floor_z, 0) / sigma`` per point (sigma, m)."""

    links: np.ndarray
    local: np.ndarray
    height: np.ndarray
    floor_z: float
    sigma: float

    @classmethod
    def from_body(cls, body: BodyModel, sigma: float, floor_z: float = 0.0, tolerance_m: float = 0.05
                  ) -> GroundContact:
        """The output joints within ``tolerance_m`` of the lowest one at the rest pose (the body
        model's rest pose stands on z = 0: the ankles), at their rest heights."""
        z = body.joint_positions(body.rest_pose())[:, 2]
        low = np.flatnonzero(z <= z.min() + tolerance_m)
        return cls(body.joint_links[low], body.joint_points[low], z[low], float(floor_z), float(sigma))

    def heights(self, world_from_link: np.ndarray) -> np.ndarray:
        """(..., F) each point's height above its rest height over the floor, for poses (..., L, 4, 4), m."""
        return BodyModel.transform_points(world_from_link, self.links, self.local)[..., 2] - self.height - self.floor_z

    def residuals(self, world_from_link: np.ndarray) -> np.ndarray:
        """(..., F + 1) whitened residuals for poses (..., L, 4, 4)."""
        z = self.heights(world_from_link)
        return np.concatenate([z.min(axis=-1, keepdims=True), np.minimum(z, 0.0)], axis=-1) / self.sigma

    def jacobian(self, body: BodyModel, theta: np.ndarray, world_from_link: np.ndarray,
                 twists: tuple[np.ndarray, np.ndarray] | None = None) -> np.ndarray:
        """(F + 1, n_dof) Jacobian of :meth:`residuals` at theta (n_dof,) with poses world_from_link (L, 4, 4)
        (``twists``: :meth:`BodyModel.dof_twists` there, if already computed)."""
        z = self.heights(world_from_link)
        dz = body.point_jacobian(theta, self.links, self.local, world_from_link, twists)[:, 2, :]
        return np.vstack([dz[int(np.argmin(z))][None], np.where((z < 0.0)[:, None], dz, 0.0)]) / self.sigma


@dataclass
class UprightSegment:
    """A soft upright body segment for :func:`fit_pose`, one of the soft priors of ALGORITHMS.md §1
    ("Soft constraints": gravity, rest pose, joint limits): residuals ``(x_top − x_bottom)_xy / sigma``,
    the horizontal offset (m) of a top point from a bottom one (link points), world z up; sigma m. Same
    interface as :class:`GroundContact`. The trunk (pelvis → thorax, ``fit.upright_sigma_m``): with one
    view, a trunk leaning towards or away from the camera looks the same, and a standing or walking
    person keeps it near vertical. The head (its link's axis, :meth:`link_axis`,
    ``fit.upright_head_sigma_m``): the head's blob (the face) sits a few cm from the neck pivot and
    barely observes its pitch, and a person keeps the head near upright."""

    links: np.ndarray  # (2,) link of bottom, top
    local: np.ndarray  # (2, 3) their points in the link frames
    sigma: float

    @classmethod
    def from_body(cls, body: BodyModel, sigma: float, bottom: str = "pelvis", top: str = "thorax") -> UprightSegment:
        names = list(body.joint_names)
        for n in (bottom, top):
            if n not in names:
                raise InputError(f"skeleton: an upright segment ({bottom} -> {top}) needs joint '{n}', "
                                 "which the body model has not")
        k = [names.index(bottom), names.index(top)]
        return cls(np.asarray(body.joint_links)[k], np.asarray(body.joint_points, float)[k], float(sigma))

    @classmethod
    def link_axis(cls, body: BodyModel, sigma: float, link: str, joint: str) -> UprightSegment:
        """The link's own z axis upright (the body model's rest pose stands every link's z axis
        vertical): from the link's origin to the height of the output joint ``joint`` on it."""
        if link not in body.link_names or joint not in body.joint_names:
            raise InputError(f"skeleton: an upright {link} needs link '{link}' and joint '{joint}', "
                             "which the body model has not")
        i, j = body.link_names.index(link), body.joint_names.index(joint)
        if int(body.joint_links[j]) != i:
            raise InputError(f"skeleton: an upright {link}: joint '{joint}' is not on link '{link}'")
        h = float(np.asarray(body.joint_points, float)[j][2])
        return cls(np.array([i, i]), np.array([[0.0, 0.0, 0.0], [0.0, 0.0, h]]), float(sigma))

    def residuals(self, world_from_link: np.ndarray) -> np.ndarray:
        """(..., 2) whitened residuals for poses (..., L, 4, 4)."""
        x = BodyModel.transform_points(world_from_link, self.links, self.local)
        return (x[..., 1, :2] - x[..., 0, :2]) / self.sigma

    def jacobian(self, body: BodyModel, theta: np.ndarray, world_from_link: np.ndarray,
                 twists: tuple[np.ndarray, np.ndarray] | None = None) -> np.ndarray:
        """(2, n_dof) Jacobian of :meth:`residuals` at theta."""
        J = body.point_jacobian(theta, self.links, self.local, world_from_link, twists)
        return (J[1, :2, :] - J[0, :2, :]) / self.sigma


class BodyTerms:
    """Several :class:`GroundContact`-like soft terms given to :func:`fit_pose` as one (its ``ground``)."""

    def __init__(self, terms: Sequence[Any]):
        self.terms = list(terms)

    def residuals(self, world_from_link: np.ndarray) -> np.ndarray:
        return np.concatenate([t.residuals(world_from_link) for t in self.terms], axis=-1)

    def jacobian(self, body: BodyModel, theta: np.ndarray, world_from_link: np.ndarray,
                 twists: tuple[np.ndarray, np.ndarray] | None = None) -> np.ndarray:
        return np.vstack([t.jacobian(body, theta, world_from_link, twists) for t in self.terms])


def _whitener(info: np.ndarray) -> np.ndarray:
    """U with Uᵀ U = info (so ‖U e‖² = eᵀ info e); eigenvalues floored. info: (n, n) or a stack
    (..., n, n) of them (one batched ``eigh``)."""
    info = np.asarray(info, float)
    w, V = np.linalg.eigh(0.5 * (info + np.swapaxes(info, -1, -2)))
    return np.ascontiguousarray(np.swapaxes(V * np.sqrt(np.maximum(w, 1e-12))[..., None, :], -1, -2))


def fit_pose(
    body: BodyModel,
    theta0: np.ndarray,
    targets: Sequence[PointTarget],
    rest: np.ndarray | None = None,
    rest_sigma: float | np.ndarray = 1.0,
    previous: np.ndarray | None = None,
    previous_sigma: float = 1.0,
    max_nfev: int = 40,
    robust_scale: float = 0.0,
    link_goals: LinkGoals | None = None,
    ground: GroundContact | None = None,
    jacobian: str = "analytic",
    tolerance: float = 1e-8,
    free_dofs: np.ndarray | None = None,
    evaluate_only: bool = False,
    abandon: tuple[int, float] | None = None,
) -> tuple[np.ndarray, float, np.ndarray]:
    """Bounded least-squares fit of theta to 3-D point targets (and, optionally, link motions).

    Minimises ``½ Σ ‖U_k (x_k(θ) − y_k)‖² + ½ Σ_j ((θ_j − rest_j)/σ_r)² + ½ Σ_j ((θ_j −
    prev_j)/σ_p)²`` (regularisers on the non-root dofs j) subject to the joint limits
    (``scipy.optimize.least_squares``, 'trf'). jacobian: ``'analytic'`` (default) —
    :meth:`BodyModel.point_jacobian` / :meth:`BodyModel.link_twist_jacobian` (exact for the point,
    floor and regulariser residuals; for link goals the log map's Jacobian is taken to first order
    in the link's motion ξ from its reference, ``J_r⁻¹(ξ) ≈ I + ½ ad(ξ)``, error O(|ξ|²)) — or ``'numeric'``: forward
    differences, all dofs in one batched FK call (the same fits, tested). tolerance: scipy's ftol = xtol
    = gtol (``fit.tolerance``; most frames stop on it, the others at max_nfev). rest_sigma: scalar or
    per-dof (n_dof,) rad. robust_scale > 0: Cauchy loss
    on the whitened residuals with this scale (sigmas), so that a grossly wrong target (a
    mislabelled blob) pulls little; it applies to every residual, the regularisers' too (scipy's
    ``loss``); 0: plain least squares. link_goals: soft constraints on
    link poses, ``½ Σ_i ‖S_i (log(E_ref,i⁻¹ E_i(θ)) − ξ̂_i)‖²`` (the edge statistics of
    ALGORITHMS.md §2 as information ``S_iᵀ S_i`` on each link's motion, in the link frame).
    ground: soft floor contact (:class:`GroundContact`), whitened residuals like the others.
    free_dofs: indices of the dofs to fit, the others held at theta0 (a conditional fit; the
    cost still counts every residual, so conditional costs of fits that share the held dofs
    compare). Returns (theta (n_dof,), cost, cov_theta (n_dof, n_dof) = (JᵀJ)⁺ at the solution,
    robust weights included; zero rows and columns for held dofs). evaluate_only: no fit, the cost at
    theta0 (as clipped into the limits; scipy's cost, the loss included) with a zero covariance.
    abandon: (k, c): stop after iteration k if the cost is still above c (a screen that cannot
    pass; the cost returned is then that iteration's, above c).
    """
    lo, hi = body.lower, body.upper
    span = np.maximum(hi - lo, 1e-9)
    x0 = np.clip(np.asarray(theta0, float), lo + 1e-7 * span, hi - 1e-7 * span)
    links = np.array([t.link for t in targets], int)
    local = np.array([t.local for t in targets], float).reshape(-1, 3)
    y = np.array([t.y for t in targets], float).reshape(-1, 3)
    U = _whitener(np.array([t.info for t in targets], float).reshape(-1, 3, 3))
    jd = np.arange(6, body.n_dof)
    reg_w, reg_c = [], []
    rest_sigma = np.broadcast_to(np.asarray(rest_sigma, float), (body.n_dof,))[jd]
    if rest is not None and np.all(rest_sigma > 0):
        reg_w.append(1.0 / rest_sigma)
        reg_c.append(np.asarray(rest, float)[jd])
    if previous is not None and previous_sigma > 0:
        reg_w.append(np.full(jd.size, 1.0 / previous_sigma))
        reg_c.append(np.asarray(previous, float)[jd])

    # The link poses of the last single theta evaluated: scipy asks for the Jacobian where it has
    # just evaluated the residuals, so the analytic Jacobian reuses them.
    last = {}

    def poses(theta: np.ndarray) -> np.ndarray:
        if theta.ndim == 1 and "theta" in last and np.array_equal(theta, last["theta"]):
            return last["T"]
        T = body.forward_kinematics(theta)
        if theta.ndim == 1:
            last["theta"], last["T"] = theta.copy(), T
        return T

    def residuals(theta: np.ndarray) -> np.ndarray:
        T = poses(theta)
        x = body.transform_points(T, links, local)
        r = [np.einsum("pij,...pj->...pi", U, x - y).reshape(*x.shape[:-2], -1)]
        if link_goals is not None and len(link_goals.links):
            g = link_goals
            xi = log_se3(np.einsum("gij,...gjk->...gik", g.inverse_reference, T[..., g.links, :, :]))
            r.append(np.einsum("gij,...gj->...gi", g.sqrt_information, xi - g.xi_hat).reshape(*x.shape[:-2], -1))
        if ground is not None:
            r.append(ground.residuals(T))
        for w, c in zip(reg_w, reg_c, strict=True):
            r.append(np.broadcast_to(w * (theta[..., jd] - c), (*x.shape[:-2], jd.size)))
        return np.concatenate(r, axis=-1)

    h = 1e-6
    reg_rows = [np.zeros((jd.size, body.n_dof)) for _ in reg_w]
    for rows, w in zip(reg_rows, reg_w, strict=True):
        rows[np.arange(jd.size), jd] = w

    def jac_numeric(theta):
        batch = theta[None] + h * np.eye(body.n_dof)
        batch = np.vstack([theta[None], batch])
        r = residuals(batch)
        return ((r[1:] - r[0]) / h).T

    def jac_analytic(theta):
        T = poses(theta)
        twists = body.dof_twists(theta, T)
        J_points = body.point_jacobian(theta, links, local, T, twists)
        out = [np.einsum("pij,pjd->pid", U, J_points).reshape(-1, body.n_dof)]
        if link_goals is not None and len(link_goals.links):
            g = link_goals
            xi = log_se3(g.inverse_reference @ T[g.links])
            ad = np.zeros((len(xi), 6, 6))  # ad(xi) = [[skew(w), skew(v)], [0, skew(w)]]
            ad[:, :3, :3] = ad[:, 3:, 3:] = skew(xi[:, 3:])
            ad[:, :3, 3:] = skew(xi[:, :3])
            dlog = np.eye(6) + 0.5 * ad
            B = body.link_twist_jacobian(theta, g.links, T, twists)
            out.append(np.einsum("gij,gjk,gkd->gid", g.sqrt_information, dlog, B).reshape(-1, body.n_dof))
        if ground is not None:
            out.append(ground.jacobian(body, theta, T, twists))
        out.extend(reg_rows)
        return np.concatenate(out, axis=0)

    if jacobian not in ("analytic", "numeric"):
        raise ValueError(f"fit_pose: jacobian must be 'analytic' or 'numeric', got {jacobian!r}")
    fun, jac = residuals, (jac_analytic if jacobian == "analytic" else jac_numeric)

    if len(targets) == 0 and not reg_w and (link_goals is None or not len(link_goals.links)):
        return x0, 0.0, np.eye(body.n_dof)
    free = np.arange(body.n_dof) if free_dofs is None else np.asarray(free_dofs, int)

    def expand(x):  # the held dofs stay at x0
        theta = x0.copy()
        theta[free] = x
        return theta

    def fit_fun(x):
        return fun(expand(x))

    def fit_jac(x):
        return jac(expand(x))[:, free]

    loss = ("cauchy", float(robust_scale)) if robust_scale > 0 else ("linear", 1.0)
    if evaluate_only:
        r2 = np.square(fit_fun(x0[free]))
        c = robust_scale ** 2 * np.log1p(r2 / robust_scale ** 2) if robust_scale > 0 else r2
        return x0, 0.5 * float(np.sum(c)), np.zeros((body.n_dof, body.n_dof))
    callback = None
    if abandon is not None:
        iterations = [0]

        def callback(intermediate_result):
            iterations[0] += 1
            if iterations[0] == abandon[0] and intermediate_result.cost > abandon[1]:
                raise StopIteration

    res = least_squares(fit_fun, x0[free], jac=fit_jac, bounds=(lo[free], hi[free]), method="trf",
                        max_nfev=max_nfev, x_scale=1.0, loss=loss[0], f_scale=loss[1], ftol=tolerance,
                        xtol=tolerance, gtol=tolerance, callback=callback)
    J = res.jac
    cov = np.zeros((body.n_dof, body.n_dof))
    cov[np.ix_(free, free)] = np.linalg.pinv(J.T @ J, rcond=1e-10, hermitian=True)
    return expand(res.x), float(res.cost), cov


def exchange_sides(body: BodyModel, theta: np.ndarray, labels) -> np.ndarray:
    """theta with the joints of each l_/r_ link pair among ``labels`` (link names) exchanged and
    mirrored across the body's sagittal plane (the link frames' x-z plane at rest, body model
    convention: x forward, y left): a ball joint's rotation vector (x, y, z) becomes (-x, y, -z),
    a hinge angle keeps its sign when the mirrored axis is the other side's axis and flips it
    when it is opposite. Clipped to the joint limits."""
    out = np.array(theta, float)
    mirror = np.diag([1.0, -1.0, 1.0])
    names = set(body.link_names)
    for left in sorted(lab for lab in labels if lab.startswith("l_") and lab in names and mirror_label(lab) in names):
        a, b = body.link(left), body.link(mirror_label(left))
        if a.joint != b.joint or a.n_dof != b.n_dof or a.joint not in ("ball", "hinge"):
            continue
        ta, tb = theta[a.dof_slice].copy(), theta[b.dof_slice].copy()
        if a.joint == "ball":
            out[a.dof_slice], out[b.dof_slice] = -mirror @ tb, -mirror @ ta
        else:
            sign = 1.0 if float(-mirror @ a.axis @ b.axis) >= 0.0 else -1.0
            out[a.dof_slice], out[b.dof_slice] = sign * tb, sign * ta
    return body.clip(out)


def mirror_label(label: str) -> str:
    """'l_hand' <-> 'r_hand'; other labels unchanged."""
    if label.startswith("l_"):
        return "r_" + label[2:]
    if label.startswith("r_"):
        return "l_" + label[2:]
    return label
