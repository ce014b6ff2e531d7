"""Loose-limbed body: graph over parts and frames, PAMPAS-style non-parametric BP (ALGORITHMS.md §4 Inference).

Graph: one node per (frame, part); directed edges between adjacent parts within
a frame (SPATIAL_EDGES, both directions) and between the same part in
consecutive frames (both directions) — a 3-frame window has 30 nodes and 94
directed edges.

Messages are kernel mixtures built from weighted particles: the message
``m_ij(X_j) = ∫ ψ_ij(X_i, X_j) φ_i(X_i) Π_{k∈A_i\\j} m_ki(X_i) dX_i`` is estimated by
importance sampling X_i from a stratified proposal and then represented as
``Σ_n w_n ψ_ij(X_i^n, X_j)`` — for a mixture potential, one diagonal Gaussian
kernel per (particle, component). Strata:

* belief — the product of all incoming messages,
* exclusive — the product of the incoming messages other than the receiver's (one per receiver),
* shouter — the bottom-up proposal Q; share 0.5 in the first iteration,
  halving every iteration.

All samples of a node form one pool, weighted for each target (the belief
φ Π m, or the message target φ Π_{k≠j} m) by multiple importance sampling
against the mixture of the strata (balance heuristic); each product stratum's
density is normalised by its integral, estimated by importance sampling.
Message weights use the proposal density floored at its 10 % quantile
(``proposal_floor_quantile``): where a receiver's own message dominates the
proposal (a leaf has no exclusive stratum), dividing by it would let samples
in its tails dominate and the beliefs drift.

One addition to the paper's graph: a weak unary prior keeps the torso
upright (``NBPConfig.upright_kappa``): with a symmetric cylinder model the
silhouette cannot tell an upright torso from an upside-down one.

Products of two or more mixtures are sampled by Gibbs sampling over the
mixture labels (Sudderth et al.), in the tangent space of a reference
rotation (positions exact, rotations by their rotation vectors about the
reference), vectorised over the chains. Everything is vectorised over particles.

The estimate (:class:`MapAssembler`). The mode of each part's marginal belief
alone is not a body: an upper arm from one mode and a forearm from another
need not meet at the elbow, and a mode found in an early iteration can be lost
in a later one. The body reported is instead the joint MAP over candidate part
poses: every belief sample of every iteration is a candidate (the best
``MapConfig.candidates`` per part by their likelihood are kept), and the
configuration maximising ``Σ_i log φ_i(X_i) + Σ_(i,j) log ψ_ij(X_i, X_j)`` over the
spatial tree (root: the torso; one potential per undirected edge, parent ->
child) is found exactly by max-product dynamic programming over the candidates
(Viterbi on the tree: O(edges × candidates²)), then refined by a few rounds of
local coordinate ascent (random perturbations of one part at a time, each kept
if it raises the same objective). Measured on the bench's first 5 initialisation
scenes (bench/loose_limbed.py section 1): the true pose scored higher than every
combination of the final belief particles, so the marginal modes had lost poses
that the model preferred.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial.transform import Rotation
from scipy.special import logsumexp

from .body_parts import PART_NAMES, SPATIAL_EDGES, PartGeometry, joints_from_parts
from .part_likelihood import PartLikelihood, ViewEvidence
from .part_potentials import LooseLimbedModel, PoseGMM, relative_pose, rot_residual

_LOG2PI = float(np.log(2.0 * np.pi))
Node = tuple[int, int]  # (frame in the window, part index)


@dataclass
class Particles:
    """Weighted part poses: pos (N, 3) m, quat (N, 4) xyzw, logw (N,) normalised log weights."""

    pos: np.ndarray
    quat: np.ndarray
    logw: np.ndarray

    def __len__(self) -> int:
        return len(self.pos)

    @staticmethod
    def around(pos: np.ndarray, quat: np.ndarray, n: int, sd_pos: float, sd_rot: float,
               rng: np.random.Generator) -> Particles:
        """n equally weighted particles scattered about one pose (pos (3,), quat (4,))."""
        p = pos + rng.standard_normal((n, 3)) * sd_pos
        q = (Rotation.from_quat(quat) * Rotation.from_rotvec(rng.standard_normal((n, 3)) * sd_rot)).as_quat()
        return Particles(p, q, np.full(n, -np.log(n)))

    def estimate(self, radius: float = 0.1, bandwidth: float = 0.05) -> tuple[np.ndarray, np.ndarray]:
        """Mode estimate: the particle of highest weighted kernel density (Gaussian, ``bandwidth`` m, on
        positions), then the weighted mean of the particles within ``radius`` m of it."""
        w_all = np.exp(self.logw - self.logw.max())
        d2 = np.sum((self.pos[:, None, :] - self.pos[None, :, :]) ** 2, axis=2)
        k = int(np.argmax(np.exp(-0.5 * d2 / bandwidth**2) @ w_all))
        near = np.linalg.norm(self.pos - self.pos[k], axis=1) < radius
        w = np.exp(self.logw[near] - self.logw[near].max())
        w /= w.sum()
        return w @ self.pos[near], Rotation.from_quat(self.quat[near]).mean(weights=w).as_quat()


@dataclass
class KernelMixture:
    """m(X) = Σ_k w_k N(p; pos_k, diag var_k[:3]) N(log(q_k⁻¹ q); 0, diag var_k[3:]) (world position,
    rotation residual in the kernel's local frame). logw (K,) normalised, pos (K, 3), quat (K, 4), var (K, 6)."""

    logw: np.ndarray
    pos: np.ndarray
    quat: np.ndarray
    var: np.ndarray

    def __len__(self) -> int:
        return len(self.logw)

    def logpdf(self, pos: np.ndarray, quat: np.ndarray) -> np.ndarray:
        """(N,) log density at poses pos (N, 3), quat (N, 4)."""
        dp = pos[:, None, :] - self.pos[None, :, :]  # (N, K, 3)
        rq = pairwise_rot_residual(self.quat, quat)  # (N, K, 3)
        r = np.concatenate([dp, rq], axis=2)
        lp = -0.5 * (np.sum(r * r / self.var[None], axis=2) + np.sum(np.log(self.var), axis=1)[None] + 6 * _LOG2PI)
        return logsumexp(lp + self.logw[None], axis=1)

    def sample(self, n: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
        """n poses (pos (n, 3), quat (n, 4)) drawn from the mixture."""
        k = rng.choice(len(self.logw), size=n, p=_probs(self.logw))
        eps = rng.standard_normal((n, 6)) * np.sqrt(self.var[k])
        q = (Rotation.from_quat(self.quat[k]) * Rotation.from_rotvec(eps[:, 3:])).as_quat()
        return self.pos[k] + eps[:, :3], q


def pairwise_rot_residual(q_mean: np.ndarray, q: np.ndarray) -> np.ndarray:
    """log(q_mean_k⁻¹ q_n) for all pairs: q_mean (K, 4), q (N, 4) xyzw -> (N, K, 3) rad.

    Same as part_potentials.rot_residual on every pair, written with broadcast
    quaternion algebra because scipy's Rotation has no outer product (this is
    the inner loop of every message evaluation).
    """
    a = q_mean[None, :, :]
    b = q[:, None, :]
    av, aw = -a[..., :3], a[..., 3:]  # conjugate of q_mean
    bv, bw = b[..., :3], b[..., 3:]
    w = aw * bw - np.sum(av * bv, axis=-1, keepdims=True)
    v = aw * bv + bw * av + np.cross(av, bv)
    v = np.where(w < 0, -v, v)
    w = np.abs(w)
    nv = np.linalg.norm(v, axis=-1, keepdims=True)
    angle = 2.0 * np.arctan2(nv, w)
    scale = np.where(nv > 1e-12, angle / np.maximum(nv, 1e-12), 2.0 / np.maximum(w, 1e-12))
    return v * scale


def _probs(logw: np.ndarray) -> np.ndarray:
    p = np.exp(logw - logw.max())
    return p / p.sum()


def _normalise(logw: np.ndarray) -> np.ndarray:
    return logw - logsumexp(logw)


def systematic_resample(logw: np.ndarray, n: int, rng: np.random.Generator) -> np.ndarray:
    """n indices drawn by systematic resampling of normalised log weights."""
    c = np.cumsum(_probs(logw))
    c[-1] = 1.0
    return np.searchsorted(c, (rng.random() + np.arange(n)) / n)


def message_from_particles(particles: Particles, potential: PoseGMM, n_keep: int,
                           rng: np.random.Generator) -> KernelMixture:
    """The message Σ_n w_n ψ(X_i^n, ·) of weighted sender particles through a mixture potential.

    The particles are resampled to ``n_keep`` (systematic); each kernel's
    world position variance is the diagonal of R_i diag(σ²) R_iᵀ.
    """
    idx = systematic_resample(particles.logw, n_keep, rng)
    p, q = particles.pos[idx], particles.quat[idx]
    logw_c, mt, mq, var = potential.all_components()
    keep = np.isfinite(logw_c)
    logw_c, mt, mq, var = logw_c[keep], mt[keep], mq[keep], var[keep]
    n, c = len(idx), len(logw_c)
    R = Rotation.from_quat(q)
    Rm = R.as_matrix()  # (n, 3, 3)
    pos = (p[:, None, :] + np.einsum("nab,cb->nca", Rm, mt)).reshape(-1, 3)
    quat = (Rotation.from_quat(np.repeat(q, c, axis=0)) * Rotation.from_quat(np.tile(mq, (n, 1)))).as_quat()
    vpos = np.einsum("nab,cb->nca", Rm**2, var[:, :3]).reshape(-1, 3)
    vrot = np.tile(var[:, 3:], (n, 1))
    logw = (np.full((n, 1), -np.log(n)) + logw_c[None, :]).reshape(-1)
    return KernelMixture(_normalise(logw), pos, quat, np.hstack([vpos, vrot]))


def product_sample(mixtures: Sequence[KernelMixture], n: int, rng: np.random.Generator,
                   n_sweeps: int = 3) -> tuple[np.ndarray, np.ndarray]:
    """n samples of the normalised product Π_k m_k(X) by Gibbs sampling over the kernel labels.

    Rotations are linearised about the heaviest kernel of the first mixture;
    n chains run in parallel. One mixture: direct sampling.
    """
    if len(mixtures) == 1:
        return mixtures[0].sample(n, rng)
    q_ref = mixtures[0].quat[int(np.argmax(mixtures[0].logw))]
    mus, vs, lws = [], [], []
    for m in mixtures:
        rv = rot_residual(np.tile(q_ref, (len(m), 1)), m.quat)
        mus.append(np.hstack([m.pos, rv]))
        vs.append(m.var)
        lws.append(m.logw)
    d = len(mixtures)
    lab = np.stack([rng.choice(len(lw), size=n, p=_probs(lw)) for lw in lws], axis=1)  # (n, d)
    for _ in range(n_sweeps):
        for k in range(d):
            prec = np.zeros((n, 6))
            eta = np.zeros((n, 6))
            for j in range(d):
                if j != k:
                    v = vs[j][lab[:, j]]
                    prec += 1.0 / v
                    eta += mus[j][lab[:, j]] / v
            vo = 1.0 / prec
            mo = eta * vo
            s = vs[k][None, :, :] + vo[:, None, :]  # (n, K, 6)
            r = mus[k][None, :, :] - mo[:, None, :]
            logp = lws[k][None, :] - 0.5 * np.sum(r * r / s + np.log(s), axis=2)
            lab[:, k] = np.argmax(logp + rng.gumbel(size=logp.shape), axis=1)
    prec = np.zeros((n, 6))
    eta = np.zeros((n, 6))
    for j in range(d):
        v = vs[j][lab[:, j]]
        prec += 1.0 / v
        eta += mus[j][lab[:, j]] / v
    x = eta / prec + rng.standard_normal((n, 6)) / np.sqrt(prec)
    q = (Rotation.from_quat(q_ref) * Rotation.from_rotvec(x[:, 3:])).as_quat()
    return x[:, :3], q


# ------------------------------------------------------------------------ graph
@dataclass
class LooseLimbedGraph:
    """Nodes (frame, part) of an ``n_frames`` window and the directed edges with their potential kind."""

    n_frames: int
    n_parts: int = len(PART_NAMES)
    edges: list[tuple[Node, Node, str]] = field(init=False)

    def __post_init__(self) -> None:
        idx = {n: k for k, n in enumerate(PART_NAMES)}
        self.edges = []
        for f in range(self.n_frames):
            for a, b in SPATIAL_EDGES:
                self.edges.append(((f, idx[a]), (f, idx[b]), "spatial"))
                self.edges.append(((f, idx[b]), (f, idx[a]), "spatial"))
            if f + 1 < self.n_frames:
                for p in range(self.n_parts):
                    self.edges.append(((f, p), (f + 1, p), "next"))
                    self.edges.append(((f + 1, p), (f, p), "prev"))

    @property
    def nodes(self) -> list[Node]:
        return [(f, p) for f in range(self.n_frames) for p in range(self.n_parts)]

    def out_edges(self, node: Node) -> list[tuple[Node, str]]:
        return [(d, k) for s, d, k in self.edges if s == node]

    def in_nodes(self, node: Node) -> list[Node]:
        return [s for s, d, _ in self.edges if d == node]


@dataclass
class NBPConfig:
    """Sample counts and schedule of the belief propagation."""

    n_particles: int = 100     #: belief samples per node and iteration
    n_exclusive: int = 50      #: samples from the product excluding the receiver, per outgoing edge
    n_message: int = 40        #: particles kept per message (× mixture components = kernels)
    gibbs_sweeps: int = 3
    shouter_fraction: float = 0.5  #: share of shouter samples in the first iteration (halves each iteration)
    proposal_floor_quantile: float = 0.1  #: message weights use the mixture proposal density floored here
    upright_kappa: float = 4.0  #: torso prior log p = κ (cos tilt − 1) (people stand; 0 switches it off)


@dataclass
class BPResult:
    """Beliefs per node after the last iteration and the messages (for warm starts)."""

    beliefs: dict[Node, Particles]
    messages: dict[tuple[Node, Node], KernelMixture]


class LooseLimbedBP:
    """PAMPAS-style NBP over a LooseLimbedGraph (see module docstring)."""

    def __init__(self, model: LooseLimbedModel, geometry: PartGeometry, likelihood: PartLikelihood,
                 config: NBPConfig | None = None, seed: int = 0):
        self.model = model
        self.geometry = geometry
        self.likelihood = likelihood
        self.config = config or NBPConfig()
        self.rng = np.random.default_rng(seed)
        #: seconds spent per stage in the last run: likelihood, products, messages
        self.timing: dict[str, float] = {}

    def _potential(self, kind: str, src: Node, dst: Node) -> PoseGMM:
        return self.model.potential(kind, PART_NAMES[src[1]], PART_NAMES[dst[1]])

    def unary(self, part: int, pos: np.ndarray, quat: np.ndarray, views: Sequence[ViewEvidence]) -> np.ndarray:
        """(N,) log φ of part ``part`` at poses pos (N, 3), quat (N, 4): the image likelihood, plus for the
        torso the upright prior (``NBPConfig.upright_kappa``)."""
        ll = self.likelihood.log_likelihood(part, pos, quat, views)
        if part == 0 and self.config.upright_kappa > 0:
            up = Rotation.from_quat(quat).apply(self.geometry.axis[0])[:, 2]
            ll = ll + self.config.upright_kappa * (up - 1.0)
        return ll

    def spatial_log_potential(self, parent: int, child: int, pos_p: np.ndarray, quat_p: np.ndarray,
                              pos_c: np.ndarray, quat_c: np.ndarray) -> np.ndarray:
        """(N,) log ψ of the spatial edge parent -> child (part indices) for pose pairs (N, 3), (N, 4) each."""
        t, q = relative_pose(pos_p, quat_p, pos_c, quat_c)
        return self.model.potential("spatial", PART_NAMES[parent], PART_NAMES[child]).logpdf(t, q)

    def run(self, graph: LooseLimbedGraph, views: Sequence[Sequence[ViewEvidence]], n_iter: int,
            shouts: Sequence[dict[int, KernelMixture]] | None = None,
            fixed: dict[Node, Particles] | None = None,
            callback: Callable[[int, dict[Node, Particles]], None] | None = None) -> BPResult:
        """Run ``n_iter`` synchronous iterations.

        views[f]: the evidence of window frame f; shouts[f]: part index ->
        shouter proposal Q (KernelMixture) for that frame; fixed: nodes whose
        belief is given (e.g. the previous frame while tracking) — they only send.
        callback(iteration, beliefs) after every iteration, with the beliefs
        formed from that iteration's messages.
        """
        shouts = shouts or [{} for _ in range(graph.n_frames)]
        fixed = fixed or {}
        msgs: dict[tuple[Node, Node], KernelMixture] = {}
        beliefs: dict[Node, Particles] = {}
        self.timing = {"likelihood": 0.0, "products": 0.0, "messages": 0.0}
        in_nodes = {nd: graph.in_nodes(nd) for nd in graph.nodes}
        out_edges = {nd: graph.out_edges(nd) for nd in graph.nodes}
        for it in range(n_iter + 1):
            last = it == n_iter  # the final pass forms beliefs from the last messages only
            f_s = self.config.shouter_fraction * 0.5**it
            new: dict[tuple[Node, Node], KernelMixture] = {}
            beliefs = {}
            for node in graph.nodes:
                if node in fixed:
                    beliefs[node] = fixed[node]
                    if not last:
                        t0 = time.perf_counter()
                        for dst, kind in out_edges[node]:
                            new[(node, dst)] = message_from_particles(
                                fixed[node], self._potential(kind, node, dst), self.config.n_message, self.rng)
                        self.timing["messages"] += time.perf_counter() - t0
                    continue
                inc = {s: msgs[(s, node)] for s in in_nodes[node] if (s, node) in msgs}
                Q = shouts[node[0]].get(node[1])
                if not inc and Q is None:
                    continue
                belief, out = self._update_node(node, inc, Q, f_s, views[node[0]], [] if last else out_edges[node])
                beliefs[node] = belief
                new.update(out)
            if last:
                break
            msgs = new
            if callback is not None and it > 0:
                callback(it - 1, beliefs)
        if callback is not None and n_iter > 0:
            callback(n_iter - 1, beliefs)
        return BPResult(beliefs=beliefs, messages=msgs)

    def _update_node(self, node: Node, inc: dict[Node, KernelMixture], Q: KernelMixture | None, f_s: float,
                     views: Sequence[ViewEvidence], out_edges: list[tuple[Node, str]]
                     ) -> tuple[Particles, dict[tuple[Node, Node], KernelMixture]]:
        """One node's belief and its outgoing messages from the incoming messages (module docstring)."""
        cfg = self.config
        rng = self.rng
        t0 = time.perf_counter()
        n_s = 0 if Q is None else (cfg.n_particles if not inc else int(round(cfg.n_particles * f_s)))
        n_b = cfg.n_particles - n_s if inc else 0
        pools: dict[str, tuple[np.ndarray, np.ndarray]] = {}
        if n_b:
            pools["B"] = product_sample(list(inc.values()), n_b, rng, cfg.gibbs_sweeps)
        if n_s:
            pools["S"] = Q.sample(n_s, rng)
        for dst, _ in out_edges:
            ex = [m for s, m in inc.items() if s != dst]
            if ex and len(ex) < len(inc):
                pools[f"E{dst}"] = product_sample(ex, cfg.n_exclusive, rng, cfg.gibbs_sweeps)
        t1 = time.perf_counter()
        self.timing["products"] += t1 - t0
        keys = list(pools)
        allp = np.concatenate([pools[k][0] for k in keys])
        allq = np.concatenate([pools[k][1] for k in keys])
        ll_all = self.unary(node[1], allp, allq, views)
        t2 = time.perf_counter()
        self.timing["likelihood"] += t2 - t1
        # Multiple importance sampling (balance heuristic): the whole pool is one sample of the mixture
        # of the strata, q_mix = Σ_s (n_s / M) q_s, with each product stratum normalised by its Z.
        m_tot = len(allp)
        logm = {s: m.logpdf(allp, allq) for s, m in inc.items()}
        sum_all = sum(logm.values()) if inc else np.zeros(m_tot)
        comps = []
        for k in keys:
            n_k = len(pools[k][0])
            if k == "B":
                lq = sum_all - log_product_normaliser(list(inc.values()), rng)
            elif k == "S":
                lq = Q.logpdf(allp, allq)
            else:
                dst = _node_of(k)
                ex = [m for s, m in inc.items() if s != dst]
                lq = sum_all - logm[dst] - log_product_normaliser(ex, rng)
            comps.append(np.log(n_k / m_tot) + lq)
        log_qmix = logsumexp(np.stack(comps), axis=0)
        everything = Particles(allp, allq, np.zeros(m_tot))
        belief = _weighted(everything, ll_all + sum_all - log_qmix)
        out: dict[tuple[Node, Node], KernelMixture] = {}
        # messages divide by m_ji where no exclusive stratum covers the tails: floor the proposal density
        floored = np.maximum(log_qmix, np.quantile(log_qmix, cfg.proposal_floor_quantile))
        for dst, kind in out_edges:
            w = ll_all + sum_all - floored
            if dst in logm:
                w = w - logm[dst]
            out[(node, dst)] = message_from_particles(_weighted(everything, w), self._potential(kind, node, dst),
                                                      cfg.n_message, rng)
        self.timing["messages"] += time.perf_counter() - t2
        return belief, out


def _weighted(p: Particles, logw: np.ndarray) -> Particles:
    return Particles(p.pos, p.quat, _normalise(logw))


def _node_of(key: str) -> Node:
    """The receiver node of an exclusive-stratum key 'E(f, p)'."""
    f, p = key[2:-1].split(",")
    return int(f), int(p)


def log_product_normaliser(mixtures: Sequence[KernelMixture], rng: np.random.Generator, n: int = 256) -> float:
    """log ∫ Π_k m_k(X) dX, estimated by importance sampling from the equal mixture of the m_k.

    (The rotation part is a density over rotation vectors, as in KernelMixture.logpdf.)
    """
    if len(mixtures) == 1:
        return 0.0
    d = len(mixtures)
    per = max(n // d, 8)
    xs = [m.sample(per, rng) for m in mixtures]
    p = np.concatenate([x[0] for x in xs])
    q = np.concatenate([x[1] for x in xs])
    lm = np.stack([m.logpdf(p, q) for m in mixtures])  # (d, n)
    log_prop = logsumexp(lm, axis=0) - np.log(d)
    return float(logsumexp(lm.sum(axis=0) - log_prop) - np.log(len(p)))


def estimate_parts(beliefs: dict[Node, Particles], frame: int, n_parts: int = len(PART_NAMES)
                   ) -> tuple[np.ndarray, np.ndarray]:
    """Point estimates (pos (P, 3), quat (P, 4)) of one window frame; NaN for parts without a belief."""
    pos = np.full((n_parts, 3), np.nan)
    quat = np.tile([0.0, 0.0, 0.0, 1.0], (n_parts, 1))
    for p in range(n_parts):
        b = beliefs.get((frame, p))
        if b is not None:
            pos[p], quat[p] = b.estimate()
    return pos, quat


def joints_estimate(geometry: PartGeometry, beliefs: dict[Node, Particles], frame: int) -> np.ndarray:
    """(J, 3) output joints of a window frame (NaN where the part has no belief yet)."""
    pos, quat = estimate_parts(beliefs, frame, geometry.n_parts)
    return joints_from_parts(geometry, pos, quat)


@dataclass
class MapConfig:
    """Sizes of the joint MAP estimate (:class:`MapAssembler`)."""

    candidates: int = 100       #: candidate poses kept per part (best by log φ over all iterations)
    refine_rounds: int = 2      #: rounds of local coordinate ascent after the dynamic programme (0: none)
    refine_samples: int = 48    #: perturbations tried per part and round
    refine_sd_pos: float = 0.03  #: m, first round (× 0.6 per round)
    refine_sd_rot: float = 0.25  #: rad, first round (× 0.6 per round)
    #: estimate after every BP iteration and keep the (refined) estimate among the candidates, so the
    #: local refinement continues from it in the next iteration (False: one estimate after the last)
    every_iteration: bool = True


class MapAssembler:
    """The body as the joint MAP over candidate part poses (module docstring, "The estimate").

    ``add(beliefs, frame, views)`` after every BP iteration adds that frame's belief samples to the
    candidates (each part keeps the ``candidates`` best by log φ); ``estimate(views)`` returns the part
    poses (pos (P, 3), quat (P, 4)) maximising ``Σ log φ_i + Σ log ψ_ij`` over the spatial tree — exactly
    over the candidates by max-product dynamic programming, then refined locally — and that score.
    ``estimate`` is a function of the candidates alone (its refinement draws from a generator seeded
    afresh on every call), so it can be called after every iteration (the bench's per-iteration error)
    without changing the last call, the tracker's answer. Parts without candidates are NaN (and, with
    their subtrees, left out of the score).
    """

    def __init__(self, bp: LooseLimbedBP, config: MapConfig | None = None):
        self.bp = bp
        self.config = config or MapConfig()
        self.seed = int(bp.rng.integers(2**32))  # of the refinement
        n = bp.geometry.n_parts
        idx = {name: k for k, name in enumerate(PART_NAMES)}
        self.children: dict[int, list[int]] = {p: [] for p in range(n)}
        self.parent: dict[int, int] = {}
        for a, b in SPATIAL_EDGES:
            self.children[idx[a]].append(idx[b])
            self.parent[idx[b]] = idx[a]
        self.pos = [np.zeros((0, 3)) for _ in range(n)]
        self.quat = [np.zeros((0, 4)) for _ in range(n)]
        self.score = [np.zeros(0) for _ in range(n)]
        #: the last estimate (pos (P, 3), quat (P, 4)), or None
        self.last: tuple[np.ndarray, np.ndarray] | None = None

    def add(self, beliefs: dict[Node, Particles], frame: int, views: Sequence[ViewEvidence]) -> None:
        """Add the belief samples of window frame ``frame`` as candidates (scored by log φ)."""
        keep = self.config.candidates
        for p in range(len(self.pos)):
            b = beliefs.get((frame, p))
            if b is None or not len(b):
                continue
            pos = np.vstack([self.pos[p], b.pos])
            quat = np.vstack([self.quat[p], b.quat])
            score = np.concatenate([self.score[p], self.bp.unary(p, b.pos, b.quat, views)])
            best = np.argsort(-score, kind="stable")[:keep]
            self.pos[p], self.quat[p], self.score[p] = pos[best], quat[best], score[best]

    def _subtree(self, p: int, best_child: dict[tuple[int, int], np.ndarray]) -> np.ndarray:
        """(C_p,) the best score of p's subtree for each candidate of p (max-product upwards)."""
        total = self.score[p].copy()
        for c in self.children[p]:
            if not len(self.score[c]):
                continue
            below = self._subtree(c, best_child)
            n, m = len(total), len(below)
            pair = self.bp.spatial_log_potential(
                p, c, np.repeat(self.pos[p], m, axis=0), np.repeat(self.quat[p], m, axis=0),
                np.tile(self.pos[c], (n, 1)), np.tile(self.quat[c], (n, 1))).reshape(n, m) + below[None, :]
            best_child[(p, c)] = np.argmax(pair, axis=1)
            total += pair.max(axis=1)
        return total

    def _local_score(self, p: int, pos: np.ndarray, quat: np.ndarray, P: np.ndarray, Q: np.ndarray,
                     views: Sequence[ViewEvidence]) -> np.ndarray:
        """(N,) the terms of the objective that involve part p, for its poses P (N, 3), Q (N, 4)."""
        out = self.bp.unary(p, P, Q, views)
        n = len(P)
        for c in self.children[p]:
            if np.all(np.isfinite(pos[c])):
                out = out + self.bp.spatial_log_potential(p, c, P, Q, np.tile(pos[c], (n, 1)), np.tile(quat[c], (n, 1)))
        q = self.parent.get(p)
        if q is not None and np.all(np.isfinite(pos[q])):
            out = out + self.bp.spatial_log_potential(q, p, np.tile(pos[q], (n, 1)), np.tile(quat[q], (n, 1)), P, Q)
        return out

    def keep(self, pos: np.ndarray, quat: np.ndarray, views: Sequence[ViewEvidence]) -> None:
        """Add one configuration (pos (P, 3), quat (P, 4); NaN rows skipped) to the candidates."""
        for p in np.flatnonzero(np.all(np.isfinite(pos), axis=1)):
            self.pos[p] = np.vstack([self.pos[p], pos[p][None]])
            self.quat[p] = np.vstack([self.quat[p], quat[p][None]])
            self.score[p] = np.append(self.score[p], self.bp.unary(p, pos[p][None], quat[p][None], views))

    def estimate(self, views: Sequence[ViewEvidence]) -> tuple[np.ndarray, np.ndarray, float]:
        """The joint MAP part poses pos (P, 3), quat (P, 4) (NaN pos: no candidate) and its score."""
        n = len(self.pos)
        pos = np.full((n, 3), np.nan)
        quat = np.tile([0.0, 0.0, 0.0, 1.0], (n, 1))
        roots = [p for p in range(n) if p not in self.parent or not len(self.score[self.parent[p]])]
        best_child: dict[tuple[int, int], np.ndarray] = {}
        total = 0.0
        for r in roots:
            if not len(self.score[r]):
                continue
            tree = self._subtree(r, best_child)
            pick = {r: int(np.argmax(tree))}
            total += float(tree[pick[r]])
            stack = [r]
            while stack:
                p = stack.pop()
                pos[p], quat[p] = self.pos[p][pick[p]], self.quat[p][pick[p]]
                for c in self.children[p]:
                    if (p, c) in best_child:
                        pick[c] = int(best_child[(p, c)][pick[p]])
                        stack.append(c)
        cfg, rng = self.config, np.random.default_rng(self.seed)
        found = np.flatnonzero(np.all(np.isfinite(pos), axis=1))
        for k in range(cfg.refine_rounds):
            sd_p, sd_r = cfg.refine_sd_pos * 0.6**k, cfg.refine_sd_rot * 0.6**k
            for p in rng.permutation(found):
                m = cfg.refine_samples
                P = np.vstack([pos[p], pos[p] + rng.standard_normal((m, 3)) * sd_p])
                Q = np.vstack([quat[p], (Rotation.from_quat(quat[p])
                                         * Rotation.from_rotvec(rng.standard_normal((m, 3)) * sd_r)).as_quat()])
                local = self._local_score(p, pos, quat, P, Q, views)
                j = int(np.argmax(local))
                total += float(local[j] - local[0])
                pos[p], quat[p] = P[j], Q[j]
        self.last = (pos, quat)
        return pos, quat, total


@dataclass
class TrackerConfig:
    """Iterations of the loose-limbed tracker."""

    init_iterations: int = 10   #: BP iterations on one frame when (re-)initialising
    track_iterations: int = 3   #: BP iterations per frame while tracking (window: previous frame fixed + current)
    use_shouters: bool = True
    #: lost when the mean part log-likelihood of the estimate falls below this (None: never);
    #: the next frame is then found again from no prior pose (recovery)
    lost_score: float | None = None
    #: the estimate: the joint MAP over the belief samples of all iterations (:class:`MapAssembler`);
    #: None: each part's marginal mode alone (:func:`estimate_parts`)
    map: MapConfig | None = field(default_factory=MapConfig)


class LooseLimbedTracker:
    """Frame-by-frame loose-limbed tracking (ALGORITHMS.md §4): initialise from shouters alone, then
    a 2-frame window per frame — the previous frame's beliefs (fixed) send temporal messages to the
    current frame's parts, which iterate with the spatial messages and the shouters.

    After each step ``parts`` holds the estimate's part poses (pos (P, 3), quat (P, 4); NaN pos where a
    part was not found), ``score`` its mean part log-likelihood, ``lost`` whether that fell below
    ``lost_score`` and ``map_seconds`` the time spent on the joint MAP estimate (wall clock).
    """

    def __init__(self, bp: LooseLimbedBP, shouter=None, config: TrackerConfig | None = None):
        self.bp = bp
        self.shouter = shouter
        self.config = config or TrackerConfig()
        self.previous: dict[int, Particles] | None = None
        self.parts: tuple[np.ndarray, np.ndarray] | None = None
        self.map_seconds = 0.0
        #: mean part log-likelihood of the last estimate, and whether it was found lost
        self.score = float("nan")
        self.lost = False

    def _shouts(self, views: Sequence[ViewEvidence]) -> dict[int, KernelMixture]:
        return self.shouter.shout(views) if (self.shouter is not None and self.config.use_shouters) else {}

    def initialise(self, views: Sequence[ViewEvidence],
                   callback: Callable[[int, dict[Node, Particles], MapAssembler | None], None] | None = None,
                   shouts: dict[int, KernelMixture] | None = None) -> np.ndarray:
        """Find the body from no prior pose (one frame, shouters only); returns the (J, 3) joints.

        callback(iteration, beliefs, assembler) after every BP iteration, the iteration's candidates
        already added to ``assembler`` (None without ``TrackerConfig.map``); shouts: the shouters'
        proposals if already computed (default: shout now)."""
        if shouts is None:
            shouts = self.shouter.shout(views) if self.shouter is not None else {}
        return self._infer(LooseLimbedGraph(1), [views], self.config.init_iterations, [shouts], {}, 0, callback)

    def start_at(self, pos: np.ndarray, quat: np.ndarray, n: int = 100, sd_pos: float = 0.02,
                 sd_rot: float = 0.05) -> None:
        """Start tracking from known part poses pos (P, 3), quat (P, 4) (particles scattered about them)."""
        rng = self.bp.rng
        self.previous = {p: Particles.around(pos[p], quat[p], n, sd_pos, sd_rot, rng) for p in range(len(pos))}

    def step(self, views: Sequence[ViewEvidence]) -> np.ndarray:
        """Track one frame; initialises first if there is no previous belief. Returns the (J, 3) joints."""
        if not self.previous:
            return self.initialise(views)
        fixed = {(0, p): b for p, b in self.previous.items()}
        return self._infer(LooseLimbedGraph(2), [[], views], self.config.track_iterations,
                           [{}, self._shouts(views)], fixed, 1, None)

    def _infer(self, graph: LooseLimbedGraph, views: list, n_iter: int, shouts: list, fixed: dict, frame: int,
               callback) -> np.ndarray:
        """BP on ``graph``; the beliefs of window frame ``frame`` become ``previous``, the estimate ``parts``."""
        assembler = MapAssembler(self.bp, self.config.map) if self.config.map is not None else None
        self.map_seconds = 0.0

        def after_iteration(it: int, beliefs: dict[Node, Particles]) -> None:
            if assembler is not None:
                t0 = time.perf_counter()
                assembler.add(beliefs, frame, views[frame])
                if assembler.config.every_iteration:
                    assembler.keep(*assembler.estimate(views[frame])[:2], views[frame])
                self.map_seconds += time.perf_counter() - t0
            if callback is not None:
                callback(it, beliefs, assembler)

        res = self.bp.run(graph, views, n_iter, shouts, fixed=fixed, callback=after_iteration)
        n_parts = self.bp.geometry.n_parts
        self.previous = {p: res.beliefs[(frame, p)] for p in range(n_parts) if (frame, p) in res.beliefs}
        if assembler is not None:
            t0 = time.perf_counter()
            every = assembler.config.every_iteration and assembler.last is not None
            pos, quat = assembler.last if every else assembler.estimate(views[frame])[:2]
            self.map_seconds += time.perf_counter() - t0
        else:
            pos, quat = estimate_parts(res.beliefs, frame, n_parts)
        self.parts = (pos, quat)
        self._check_lost(views[frame], pos, quat)
        return joints_from_parts(self.bp.geometry, pos, quat)

    def _check_lost(self, views: Sequence[ViewEvidence], pos: np.ndarray, quat: np.ndarray) -> None:
        ok = np.all(np.isfinite(pos), axis=1)
        self.score = float(np.mean([self.bp.likelihood.log_likelihood(p, pos[p:p + 1], quat[p:p + 1], views)[0]
                                    for p in np.flatnonzero(ok)])) if ok.any() else -np.inf
        self.lost = self.config.lost_score is not None and self.score < self.config.lost_score
        if self.lost:
            self.previous = None
