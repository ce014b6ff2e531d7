"""Learned potentials of the loose-limbed body: pose Gaussian mixtures fitted by EM (ALGORITHMS.md §4 Potentials).

``ψ_ij(X_i, X_j) = λ₀ N(X_j; outlier) + (1 − λ₀) Σ_m δ_m N(X_j; F_m(X_i), G_m)``: the pose of
part j expressed in part i's frame (translation t = R_iᵀ(p_j − p_i), rotation
q = q_i⁻¹ q_j) follows a mixture of M Gaussians with diagonal covariance. The
quaternion part is handled in a local linearisation: component m has a mean
rotation q_m and the residual is the rotation vector log(q_m⁻¹ q) (local
frame), so a component is a 6-D diagonal Gaussian over (t − μ_m, log(q_m⁻¹ q)).
The outlier term is one broad Gaussian of the same form (the pooled data, its
standard deviations times ``OUTLIER_SCALE``).

EM starts from k-means (scipy.cluster.vq.kmeans2) on (t, rotation vector about
the data's mean rotation); the M-step updates q_m by the weighted mean
residual (one Gauss–Newton step of the rotation mean per EM iteration).

Potentials exist for each directed spatial edge (child in the parent's frame
and parent in the child's frame) and for each part over time (t+1 given t:
"next"; t−1 given t: "prev"). The model file (YAML, ``config/loose_limbed_model.yaml``)
carries ``version``, training provenance and every mixture.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import yaml
from scipy.cluster.vq import kmeans2
from scipy.spatial.transform import Rotation
from scipy.special import logsumexp

from .body_model import BodyModel
from .body_parts import PART_NAMES, SPATIAL_EDGES, PartGeometry, parts_from_theta
from .config import parse_yaml, yaml_error_text
from .errors import InputError

MODEL_VERSION = 1
MODEL_NAME = "loose_limbed_model.yaml"
OUTLIER_SCALE = 3.0
_LOG2PI = float(np.log(2.0 * np.pi))


def relative_pose(p_i: np.ndarray, q_i: np.ndarray, p_j: np.ndarray, q_j: np.ndarray
                  ) -> tuple[np.ndarray, np.ndarray]:
    """Pose of j in i's frame: t (N, 3) = R_iᵀ(p_j − p_i), q (N, 4) = q_i⁻¹ q_j (xyzw)."""
    Ri = Rotation.from_quat(q_i)
    t = Ri.inv().apply(p_j - p_i)
    q = (Ri.inv() * Rotation.from_quat(q_j)).as_quat()
    return t, q


def compose(p_i: np.ndarray, q_i: np.ndarray, t: np.ndarray, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """World pose of j from i's pose and j's pose in i's frame (inverse of relative_pose)."""
    Ri = Rotation.from_quat(q_i)
    return p_i + Ri.apply(t), (Ri * Rotation.from_quat(q)).as_quat()


def rot_residual(q_mean: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Rotation vectors log(q_mean⁻¹ q) (N, 3) rad, local frame of q_mean (both (N, 4) or broadcastable (4,))."""
    q_mean = np.broadcast_to(q_mean, np.shape(q))
    return (Rotation.from_quat(q_mean).inv() * Rotation.from_quat(q)).as_rotvec()


def _diag_logpdf(r: np.ndarray, var: np.ndarray) -> np.ndarray:
    """log N(r; 0, diag(var)) summed over the last axis."""
    return -0.5 * (np.sum(r * r / var + np.log(var), axis=-1) + r.shape[-1] * _LOG2PI)


@dataclass
class PoseGMM:
    """Mixture over a relative pose (t, q) — see the module docstring.

    weights (M,) sum to 1; mean_t (M, 3) m; mean_q (M, 4) xyzw; var (M, 6)
    (3 translation m², 3 rotation rad², local frame); outlier_weight λ₀ and the
    outlier Gaussian (out_t (3,), out_q (4,), out_var (6,)).
    """

    weights: np.ndarray
    mean_t: np.ndarray
    mean_q: np.ndarray
    var: np.ndarray
    outlier_weight: float
    out_t: np.ndarray
    out_q: np.ndarray
    out_var: np.ndarray

    @property
    def n_components(self) -> int:
        return len(self.weights)

    def all_components(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """(log weights (M+1,), mean_t (M+1, 3), mean_q (M+1, 4), var (M+1, 6)), outlier last."""
        w = np.concatenate([(1.0 - self.outlier_weight) * self.weights, [self.outlier_weight]])
        with np.errstate(divide="ignore"):
            logw = np.log(w)
        return (logw, np.vstack([self.mean_t, self.out_t]), np.vstack([self.mean_q, self.out_q]),
                np.vstack([self.var, self.out_var]))

    def logpdf(self, t: np.ndarray, q: np.ndarray) -> np.ndarray:
        """(N,) log density of relative poses t (N, 3), q (N, 4) (translation density × rotation-vector density)."""
        logw, mt, mq, var = self.all_components()
        out = np.empty((len(t), len(logw)))
        for m in range(len(logw)):
            r = np.hstack([t - mt[m], rot_residual(mq[m], q)])
            out[:, m] = logw[m] + _diag_logpdf(r, var[m])
        return logsumexp(out, axis=1)

    def sample(self, n: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
        """n relative poses (t (n, 3), q (n, 4)) drawn from the mixture (outlier included)."""
        logw, mt, mq, var = self.all_components()
        m = rng.choice(len(logw), size=n, p=np.exp(logw))
        eps = rng.standard_normal((n, 6)) * np.sqrt(var[m])
        q = (Rotation.from_quat(mq[m]) * Rotation.from_rotvec(eps[:, 3:])).as_quat()
        return mt[m] + eps[:, :3], q

    # ----------------------------------------------------------------- I/O
    def to_dict(self) -> dict[str, Any]:
        def r(a):
            return np.round(np.asarray(a, float), 9).tolist()
        return {"weights": r(self.weights), "mean_t": r(self.mean_t), "mean_q": r(self.mean_q),
                "var": r(self.var), "outlier_weight": float(self.outlier_weight),
                "outlier": {"mean_t": r(self.out_t), "mean_q": r(self.out_q), "var": r(self.out_var)}}

    @staticmethod
    def from_dict(d: dict[str, Any], where: str) -> PoseGMM:
        try:
            g = PoseGMM(weights=np.asarray(d["weights"], float), mean_t=np.asarray(d["mean_t"], float),
                        mean_q=np.asarray(d["mean_q"], float), var=np.asarray(d["var"], float),
                        outlier_weight=float(d["outlier_weight"]),
                        out_t=np.asarray(d["outlier"]["mean_t"], float),
                        out_q=np.asarray(d["outlier"]["mean_q"], float),
                        out_var=np.asarray(d["outlier"]["var"], float))
        except (KeyError, TypeError, ValueError) as exc:
            raise InputError(f"{where}: missing or malformed field ({exc})") from exc
        m = len(g.weights)
        shapes_ok = (g.mean_t.shape == (m, 3) and g.mean_q.shape == (m, 4) and g.var.shape == (m, 6)
                     and g.out_t.shape == (3,) and g.out_q.shape == (4,) and g.out_var.shape == (6,))
        if not shapes_ok or m == 0:
            raise InputError(f"{where}: inconsistent mixture shapes")
        if not (np.all(g.var > 0) and np.all(g.out_var > 0) and 0.0 <= g.outlier_weight < 1.0
                and np.all(g.weights >= 0) and abs(g.weights.sum() - 1.0) < 1e-6):
            raise InputError(f"{where}: variances must be positive, weights a distribution")
        g.mean_q /= np.linalg.norm(g.mean_q, axis=1, keepdims=True)
        g.out_q /= np.linalg.norm(g.out_q)
        return g


def fit_pose_gmm(t: np.ndarray, q: np.ndarray, n_components: int = 3, outlier_weight: float = 0.02,
                 var_floor: tuple[float, float] = (1e-4, 1e-3), n_iter: int = 60, seed: int = 0,
                 tol: float = 1e-6) -> tuple[PoseGMM, list[float]]:
    """EM for the relative-pose mixture, k-means start (ALGORITHMS.md §4 Potentials).

    t (N, 3) m, q (N, 4) xyzw; var_floor: (translation m², rotation rad²) lower
    bound of every variance (the looseness of the joints). Returns the mixture
    and the mean log-likelihood after each iteration (non-decreasing up to the
    variance floor).
    """
    t = np.asarray(t, float)
    q = np.asarray(q, float)
    n = len(t)
    if n < 2 * n_components:
        raise ValueError(f"fit_pose_gmm: {n} samples are too few for {n_components} components")
    floor = np.array([var_floor[0]] * 3 + [var_floor[1]] * 3)
    q_all = Rotation.from_quat(q).mean()
    rv = (q_all.inv() * Rotation.from_quat(q)).as_rotvec()
    feats = np.hstack([t, rv])
    scale = feats.std(axis=0) + 1e-9
    _, labels = kmeans2(feats / scale, n_components, minit="++", seed=seed)
    resp = np.zeros((n, n_components))
    resp[np.arange(n), labels] = 1.0
    mean_t = np.zeros((n_components, 3))
    mean_q = np.tile(q_all.as_quat(), (n_components, 1))
    var = np.tile(floor, (n_components, 1))
    weights = np.full(n_components, 1.0 / n_components)
    history: list[float] = []
    for it in range(n_iter + 1):
        if it > 0:  # E-step
            logp = np.empty((n, n_components))
            for m in range(n_components):
                r = np.hstack([t - mean_t[m], rot_residual(mean_q[m], q)])
                logp[:, m] = np.log(max(weights[m], 1e-300)) + _diag_logpdf(r, var[m])
            ll = logsumexp(logp, axis=1)
            history.append(float(ll.mean()))
            resp = np.exp(logp - ll[:, None])
            if it > 2 and abs(history[-1] - history[-2]) < tol:
                break
        # M-step
        nk = resp.sum(axis=0) + 1e-12
        weights = nk / n
        for m in range(n_components):
            w = resp[:, m] / nk[m]
            mean_t[m] = w @ t
            if it == 0:  # k-means start: the cluster's rotation mean
                if np.any(w > 0):
                    mean_q[m] = Rotation.from_quat(q[w > 0]).mean().as_quat()
            else:
                step = w @ rot_residual(mean_q[m], q)  # local linearisation of the rotation mean
                mean_q[m] = (Rotation.from_quat(mean_q[m]) * Rotation.from_rotvec(step)).as_quat()
            r = np.hstack([t - mean_t[m], rot_residual(mean_q[m], q)])
            var[m] = np.maximum(w @ (r * r), floor)
    out_q = q_all.as_quat()
    r_all = np.hstack([t - t.mean(axis=0), rot_residual(out_q, q)])
    out_var = np.maximum(r_all.var(axis=0), floor) * OUTLIER_SCALE**2
    return PoseGMM(weights=weights, mean_t=mean_t.copy(), mean_q=mean_q.copy(), var=var.copy(),
                   outlier_weight=outlier_weight, out_t=t.mean(axis=0), out_q=out_q, out_var=out_var), history


# ------------------------------------------------------------------- the model
@dataclass
class LooseLimbedModel:
    """All potentials: ``spatial[(i, j)]`` = pose of part j in part i's frame (both
    directions of every SPATIAL_EDGES pair), ``next[p]`` = part p at t+1 in its
    frame at t, ``prev[p]`` = part p at t−1 in its frame at t. ``fps`` the frame
    rate the temporal potentials were learned at; ``provenance`` free text."""

    spatial: dict[tuple[str, str], PoseGMM]
    next: dict[str, PoseGMM]
    prev: dict[str, PoseGMM]
    fps: float
    provenance: dict[str, Any] = field(default_factory=dict)

    def potential(self, kind: str, i: str, j: str) -> PoseGMM:
        """The potential for sending from part i to part j ('spatial', 'next' or 'prev'; temporal: i == j)."""
        return self.spatial[(i, j)] if kind == "spatial" else getattr(self, kind)[j]


def save_model(model: LooseLimbedModel, path: str | os.PathLike) -> None:
    """Write the model YAML (atomic: temp file + rename)."""
    data = {"version": MODEL_VERSION, "fps": float(model.fps), "provenance": model.provenance,
            "spatial": [{"from": i, "to": j, **g.to_dict()} for (i, j), g in model.spatial.items()],
            "next": {p: g.to_dict() for p, g in model.next.items()},
            "prev": {p: g.to_dict() for p, g in model.prev.items()}}
    path = Path(path)
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.write_text("# Loose-limbed body potentials (artrack/part_potentials.py); generated by\n"
                   "#   python bench/loose_limbed.py --retrain\n"
                   + yaml.safe_dump(data, sort_keys=False, width=200))
    tmp.replace(path)


def default_model_path() -> Path:
    """config/loose_limbed_model.yaml (config.config_dir: ``ARTRACK_CONFIG_DIR``, source tree or installed)."""
    from .config import config_dir

    return config_dir() / MODEL_NAME


def load_model(path: str | os.PathLike | None = None) -> LooseLimbedModel:
    """Read a model YAML; InputError naming the file and field when it is malformed or of another version."""
    path = Path(path) if path is not None else default_model_path()
    try:
        data = parse_yaml(path.read_text())
    except OSError as exc:
        raise InputError(f"{path}: cannot read the loose-limbed model ({exc.strerror})") from exc
    except yaml.YAMLError as exc:
        raise InputError(f"{path}: not valid YAML ({yaml_error_text(exc)})") from exc
    if not isinstance(data, dict) or data.get("version") != MODEL_VERSION:
        got = data.get("version") if isinstance(data, dict) else None
        raise InputError(f"{path}: field 'version' must be {MODEL_VERSION}, got {got!r}")
    spatial = {}
    for k, e in enumerate(data.get("spatial") or []):
        spatial[(str(e.get("from")), str(e.get("to")))] = PoseGMM.from_dict(e, f"{path}: spatial[{k}]")
    want = {(a, b) for a, b in SPATIAL_EDGES} | {(b, a) for a, b in SPATIAL_EDGES}
    if set(spatial) != want:
        raise InputError(f"{path}: field 'spatial' must hold both directions of {len(SPATIAL_EDGES)} edges")
    temporal = {}
    for kind in ("next", "prev"):
        d = data.get(kind) or {}
        if set(d) != set(PART_NAMES):
            raise InputError(f"{path}: field '{kind}' must hold one mixture per part")
        temporal[kind] = {p: PoseGMM.from_dict(d[p], f"{path}: {kind}.{p}") for p in PART_NAMES}
    return LooseLimbedModel(spatial=spatial, next=temporal["next"], prev=temporal["prev"],
                            fps=float(data.get("fps", 30.0)), provenance=dict(data.get("provenance") or {}))


# ------------------------------------------------------------------- training
def training_motion(body: BodyModel, motion: str, seed: int, fps: float = 30.0, duration_s: float = 10.0,
                    amplitude: float = 0.3) -> np.ndarray:
    """(T, n_dof) a varied training sequence: motion.pose_at(motion) plus, per joint dof, a seeded
    smooth perturbation (3 random sinusoids, 0.1–1.2 Hz, total amplitude ≲ ``amplitude`` rad) and a
    random heading, clipped to the joint limits."""
    from .motion import pose_at

    rng = np.random.default_rng([seed, 7])
    times = np.arange(int(round(duration_s * fps))) / fps
    base = np.stack([pose_at(motion, float(t), body) for t in times])
    n_dof = body.n_dof
    freq = rng.uniform(0.1, 1.2, (3, n_dof))
    phase = rng.uniform(0, 2 * np.pi, (3, n_dof))
    amp = rng.uniform(0.0, amplitude / 2.0, (3, n_dof))
    pert = np.sum(amp[None] * np.sin(2 * np.pi * freq[None] * times[:, None, None] + phase[None]), axis=1)
    pert[:, :6] = 0.0
    theta = body.clip(base + pert)
    heading = Rotation.from_rotvec([0.0, 0.0, rng.uniform(-np.pi, np.pi)])
    root = Rotation.from_rotvec(base[:, 3:6])
    theta[:, 3:6] = (heading * root).as_rotvec()
    theta[:, :3] = heading.apply(base[:, :3]) + np.array([*rng.uniform(-0.5, 0.5, 2), 0.0])
    return theta


def train_model(body: BodyModel, geometry: PartGeometry, sequences: list[np.ndarray], fps: float,
                n_components: int = 3, outlier_weight: float = 0.02, seed: int = 0,
                spatial_floor: tuple[float, float] = (9e-4, 1e-2),
                temporal_floor: tuple[float, float] = (4e-4, 4e-3),
                provenance: dict[str, Any] | None = None,
                spatial_sequences: list[np.ndarray] = ()) -> LooseLimbedModel:
    """Fit every potential from training sequences [(T_k, n_dof)] at ``fps``; ``spatial_sequences``
    (poses (T_k, n_dof)) enter the spatial potentials only (poses that cover the joints' range, whose
    motion is not a person's)."""
    pos_l, quat_l, nxt_p, nxt_q = [], [], [], []
    for seq in sequences:
        pos, quat = parts_from_theta(body, geometry, seq)
        pos_l.append(pos)
        quat_l.append(quat)
        nxt_p.append(pos[1:])
        nxt_q.append(quat[1:])
    cur_p = np.concatenate([p[:-1] for p in pos_l])
    cur_q = np.concatenate([q[:-1] for q in quat_l])
    nxt_p = np.concatenate(nxt_p)
    nxt_q = np.concatenate(nxt_q)
    for seq in spatial_sequences:
        pos, quat = parts_from_theta(body, geometry, seq)
        pos_l.append(pos)
        quat_l.append(quat)
    pos = np.concatenate(pos_l)
    quat = np.concatenate(quat_l)
    idx = {n: k for k, n in enumerate(PART_NAMES)}
    spatial = {}
    for a, b in SPATIAL_EDGES:
        for i, j in ((a, b), (b, a)):
            t, q = relative_pose(pos[:, idx[i]], quat[:, idx[i]], pos[:, idx[j]], quat[:, idx[j]])
            spatial[(i, j)] = fit_pose_gmm(t, q, n_components, outlier_weight, spatial_floor, seed=seed)[0]
    nxt, prv = {}, {}
    for p in PART_NAMES:
        k = idx[p]
        t, q = relative_pose(cur_p[:, k], cur_q[:, k], nxt_p[:, k], nxt_q[:, k])
        nxt[p] = fit_pose_gmm(t, q, n_components, outlier_weight, temporal_floor, seed=seed)[0]
        t, q = relative_pose(nxt_p[:, k], nxt_q[:, k], cur_p[:, k], cur_q[:, k])
        prv[p] = fit_pose_gmm(t, q, n_components, outlier_weight, temporal_floor, seed=seed)[0]
    return LooseLimbedModel(spatial=spatial, next=nxt, prev=prv, fps=fps, provenance=provenance or {})
