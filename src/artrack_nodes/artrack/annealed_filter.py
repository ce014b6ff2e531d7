"""Kinematic-tree baseline: annealed particle filter over joint angles (ALGORITHMS.md §4, the paper's comparison).

Deutscher-style annealing: per frame, L layers; at layer m the weights are
w ∝ exp(β_m log L(θ)) with β_m chosen by bisection so that the effective
sample size is ``survival`` × N (the particle survival rate), the set is
resampled and diffused with Gaussian noise whose per-dof standard deviation
shrinks geometrically (``noise_decay`` per layer). The likelihood is the
loose-limbed part likelihood summed over the 10 parts (same evidence); the
hand and foot dofs, which no part observes, are held at their rest values.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from scipy.special import logsumexp

from .body_model import BodyModel
from .body_parts import PartGeometry, parts_from_theta
from .loose_limbed import systematic_resample
from .part_likelihood import PartLikelihood, ViewEvidence


@dataclass
class AnnealingConfig:
    """Layers, particles and noise of the annealed filter."""

    n_layers: int = 10
    n_particles: int = 200
    survival: float = 0.5        #: target effective-sample-size fraction per layer
    sd_root_pos: float = 0.05    #: m, first-layer noise of the root position
    sd_angle: float = 0.15       #: rad, first-layer noise of every observed joint angle and the root rotation
    noise_decay: float = 0.8     #: noise multiplier per layer


def _beta_for_survival(ll: np.ndarray, survival: float) -> float:
    """β such that ESS(exp(β ll)) ≈ survival · N (bisection on log β)."""
    n = len(ll)
    lo, hi = 1e-4, 1e3
    for _ in range(40):
        mid = np.sqrt(lo * hi)
        lw = mid * ll
        lw = lw - logsumexp(lw)
        ess = 1.0 / np.sum(np.exp(2 * lw))
        if ess > survival * n:
            lo = mid
        else:
            hi = mid
    return float(np.sqrt(lo * hi))


class AnnealedParticleFilter:
    """Annealed particle filter over theta (n_dof,) of the body model."""

    def __init__(self, body: BodyModel, geometry: PartGeometry, likelihood: PartLikelihood,
                 config: AnnealingConfig | None = None, seed: int = 0):
        self.body = body
        self.geometry = geometry
        self.likelihood = likelihood
        self.config = config or AnnealingConfig()
        self.rng = np.random.default_rng(seed)
        cfg = self.config
        sd = np.full(body.n_dof, cfg.sd_angle)
        sd[:3] = cfg.sd_root_pos
        for name in ("l_hand", "r_hand", "l_foot", "r_foot"):
            sd[body.dof_slice(name)] = 0.0
        self.sd = sd
        self.particles: np.ndarray | None = None

    def log_likelihood(self, theta: np.ndarray, views: Sequence[ViewEvidence]) -> np.ndarray:
        """(N,) summed part log-likelihoods of poses theta (N, n_dof)."""
        pos, quat = parts_from_theta(self.body, self.geometry, theta)
        return self.likelihood.log_likelihood_parts(pos, quat, views).sum(axis=1)

    def start_at(self, theta: np.ndarray) -> None:
        """All particles at theta (n_dof,)."""
        self.particles = np.tile(np.asarray(theta, float), (self.config.n_particles, 1))

    def step(self, views: Sequence[ViewEvidence]) -> np.ndarray:
        """Anneal through the layers for one frame; returns the weighted-mean theta (n_dof,)."""
        if self.particles is None:
            raise RuntimeError("AnnealedParticleFilter.step before start_at")
        cfg = self.config
        x = self.particles
        n = len(x)
        lw = np.zeros(n)
        for m in range(cfg.n_layers):
            x = x + self.rng.standard_normal(x.shape) * self.sd * cfg.noise_decay**m
            x = _clip_joints(self.body, x)
            ll = self.log_likelihood(x, views)
            beta = _beta_for_survival(ll, cfg.survival)
            lw = beta * ll
            lw -= logsumexp(lw)
            if m < cfg.n_layers - 1:
                x = x[systematic_resample(lw, n, self.rng)]
        est = np.exp(lw) @ x
        self.particles = x[systematic_resample(lw, n, self.rng)]
        return est


def _clip_joints(body: BodyModel, x: np.ndarray) -> np.ndarray:
    """Clip every dof but the root pose (6) to the joint limits."""
    out = body.clip(x)
    out[:, :6] = x[:, :6]
    return out
