"""Edge statistics per camera for the skeleton — ALGORITHMS.md §2 "Fusion" with §1.

Each camera's edge stage tracks the body's contour edges in its own view from the
*predicted* pose (:class:`artrack.edge_tracker.EdgeTracker.step`: ``iterations`` cycles of
contour samples, normal search with edge polarity, robust per-link statistics (eqs. 7-10)
with the damping prior, and Algorithm 1's articulated update), then measures the edges once
more at the pose it reached, and hands the skeleton one Gaussian per link in information
form, in the link's own frame about the prediction (``E = E_ref exp(xi)``, see :mod:`artrack.lie`):

    C_i  (6, 6)   information of the link's motion from this camera's edges at the pose reached
                  (px⁻² per m², rad²; no damping prior)
    eta_i (6,)    C_i xi_hat_i, xi_hat_i the motion from the prediction to the pose reached plus
                  the residual motion measured there (tangent spaces at the prediction and at
                  the pose reached identified: first order in the residual)

A single linearisation at the prediction recovers only part of a frame's motion — a swinging
limb moves further than one re-weighted step follows — and in the closed loop from a correct
pose, blobs with it were no better than blobs alone (seeds 1-3: 200 against 157 mm); iterated
per view, blobs + edges beat blobs alone from the automatic start (default scene seeds 1-26, limbs
38.1 -> 28.7 mm, stop 71; docs/MEASUREMENTS.md). From a correct pose (``bench/closed_loop.py
--true-start 60``, seeds 1-6) they do on 2 of 6 only: with the arms overhead the arms' edges can
spin the trunk's yaw (docs/HISTORY.md, stop 71).
The appearance (edge polarity colours) is learnt at the first prediction and again whenever the
skeleton is (re-)initialised (:meth:`EdgeStage.step` with ``status``; :meth:`EdgeStage.relearn`).

Cameras combine by summing (all share ``xi`` per link, §2); the skeleton then uses
``(xi_i - xi_hat_i)ᵀ C_i (xi_i - xi_hat_i) / sigma²`` as a soft constraint on each link
(:func:`artrack.body_fit.fit_pose`, ``link_goals``). No damping prior is included here:
links and directions the edges do not see carry zero information and are left to the blobs
and the body model.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from .body_model import BodyModel
from .cameras import Camera
from .edge_tracker import STAGES, EdgeTracker, EdgeTrackerConfig
from .lie import inverse_se3, log_se3
from .types import STATUS_TRACKING

__all__ = ["EdgeStage", "LinkEdgeStatistics", "combine"]


@dataclass
class LinkEdgeStatistics:
    """Per-link edge information about ``reference`` (L = number of body links).

    reference: (L, 4, 4) world_from_link at which the motions are measured (the prediction);
    information: (L, 6, 6) C_i; information_vector: (L, 6) eta_i = C_i xi_hat_i;
    samples_found: (L,) edges found per link; cameras: the views summed in.
    """

    reference: np.ndarray
    information: np.ndarray
    information_vector: np.ndarray
    samples_found: np.ndarray
    cameras: tuple[str, ...] = ()

    @property
    def measured(self) -> np.ndarray:
        """(L,) bool: links with any edge information."""
        return np.any(self.information != 0, axis=(1, 2))

    def xi_hat(self) -> np.ndarray:
        """(L, 6) the MAP motion of each measured link alone (pseudo-inverse; zero where unmeasured)."""
        out = np.zeros_like(self.information_vector)
        for i in np.flatnonzero(self.measured):
            out[i] = np.linalg.lstsq(self.information[i], self.information_vector[i], rcond=1e-9)[0]
        return out


def combine(stats: Sequence[LinkEdgeStatistics]) -> LinkEdgeStatistics | None:
    """Sum the statistics of several cameras (the same reference pose); None for none."""
    stats = [s for s in stats if s is not None]
    if not stats:
        return None
    ref = stats[0].reference
    for s in stats[1:]:
        if s.reference.shape != ref.shape or not np.allclose(s.reference, ref, atol=1e-9):
            raise ValueError("edge statistics about different reference poses cannot be combined")
    return LinkEdgeStatistics(
        ref.copy(),
        np.sum([s.information for s in stats], axis=0),
        np.sum([s.information_vector for s in stats], axis=0),
        np.sum([s.samples_found for s in stats], axis=0),
        tuple(c for s in stats for c in s.cameras),
    )


class EdgeStage:
    """One camera's edge statistics about the predicted pose (the offline form of the
    ``edge_features`` node; module docstring).

    Warm-up (``warmup_frames`` > 0): a new track (the reference's ``status`` became TRACKING) is
    used only from its ``warmup_frames`` + 1-th reference on, and references of a body not
    TRACKING not at all; :meth:`step` returns None for them (no statistics). The
    start-up pose is often wrong for the first second (a hand label on the wrong skin, the legs
    swapped), and edges measured from it would hold it there: the appearance (the edge-polarity
    colours, :meth:`EdgeTracker.learn_appearance`) learnt at a wrong pose rejects the right edges
    and the search starts far from them. So the appearance is learnt at the first reference after
    the warm-up, when the blobs have pulled the body right, and again after the next new track.
    :meth:`relearn` marks the next reference as trusted (the benches' correct start): it is
    learnt there, without warm-up. References without a status (None) are always used."""

    def __init__(self, camera: Camera, body: BodyModel, config: EdgeTrackerConfig | None = None):
        self.camera = camera
        self.tracker = EdgeTracker(body, [camera], config)
        self.n_links = len(body.links)
        self.timings_ms: dict[str, float] = {}
        self.status: int | None = None  # of the last reference given
        self.tracked_frames = 0  # consecutive TRACKING references given in this track
        self._trusted = False  # relearn() was called: the next reference needs no warm-up

    def relearn(self) -> None:
        """Forget the appearance: it is learnt again at the next reference (a new, trusted pose:
        no warm-up)."""
        self.tracker.appearance = None
        self._trusted = True

    def step(self, image_bgr: np.ndarray, reference: np.ndarray,
             status: int | None = None) -> LinkEdgeStatistics | None:
        """Statistics of one image about ``reference`` (L, 4, 4) world_from_link (module docstring);
        ``status`` of the body the reference comes from (TrackedBody status, None: not known).
        None during a new track's warm-up (class docstring)."""
        cam, tr = self.camera, self.tracker
        E = np.asarray(reference, dtype=float)
        if E.shape != (self.n_links, 4, 4):
            raise ValueError(f"edge stage '{cam.name}': reference must be ({self.n_links}, 4, 4), got {E.shape}")
        if status is not None:
            if status != STATUS_TRACKING:
                self.tracked_frames = 0
            elif self._trusted:
                self.tracked_frames = tr.config.warmup_frames + 1
            elif self.status is not None and self.status != STATUS_TRACKING:  # a new track
                tr.appearance = None
                self.tracked_frames = 1
            else:
                self.tracked_frames += 1
            self.status = int(status)
            if tr.config.warmup_frames and self.tracked_frames <= tr.config.warmup_frames:
                tr.appearance = None
                return None
        self._trusted = False
        if tr.config.polarity and tr.appearance is None:
            tr.learn_appearance({cam.name: image_bgr}, E)
        timings = dict.fromkeys(STAGES, 0.0)
        t0 = time.perf_counter()
        grads = {cam.name: tr.prepare(cam, image_bgr)}
        timings["gradients"] = (time.perf_counter() - t0) * 1e3
        reached, _, _ = tr.track(grads, E, timings)
        xi_res, C, _ = tr.measure(grads, reached, timings)  # no damping prior: unseen directions carry none
        xi_hat = log_se3(np.einsum("lij,ljk->lik", inverse_se3(E), reached)) + xi_res
        measured = np.any(C != 0, axis=(1, 2))
        eta = np.einsum("nij,nj->ni", C, np.where(measured[:, None], xi_hat, 0.0))
        m = tr.last_measurements.get(cam.name)
        found = np.zeros(self.n_links, dtype=np.int64)
        if m is not None:
            np.add.at(found, m.samples.link[m.found], 1)
        self.timings_ms = timings
        return LinkEdgeStatistics(E.copy(), 0.5 * (C + np.swapaxes(C, 1, 2)), eta, found, (cam.name,))
