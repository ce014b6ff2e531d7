"""The loose_limbed node's frame step (ALGORITHMS.md §4 in the graph), ROS-free.

Per camera a background model (``background.BackgroundModel``: the median of the
first ``background_seed_frames`` sampled frames) turns images into the
foreground/edge evidence of ``part_likelihood``; once every camera's
background is seeded, each frame goes through the ``LooseLimbedTracker``
(shouters + NBP). ``reinitialise()`` drops the tracker's belief so the next
frame is found again from no prior pose (what the node does at start and
whenever the skeleton reports itself lost). Output: a ``BodyEstimate`` with
the 15 output joints and one LinkEstimate per part (no blobs).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from .background import BackgroundModel
from .blob_config import BlobTrackerConfig
from .body_model import BodyModel
from .body_parts import part_geometry
from .cameras import Camera
from .errors import InputError
from .loose_limbed import LooseLimbedBP, LooseLimbedTracker, NBPConfig, TrackerConfig
from .part_likelihood import LikelihoodConfig, PartLikelihood, view_evidence
from .part_potentials import LooseLimbedModel
from .shouters import Shouter, ShouterConfig
from .types import STATUS_INITIALIZING, STATUS_LOST, STATUS_TRACKING, BodyEstimate, LinkEstimate


@dataclass
class StageConfig:
    """Sizes of the node's inference (defaults as in bench/loose_limbed.py's initialisation)."""

    init_iterations: int = 10
    track_iterations: int = 2
    n_particles: int = 100
    use_shouters: bool = True
    seed: int = 0
    background_seed_frames: int = 11   #: frames in the background median (blob_config.BlobTrackerConfig)
    background_seed_stride: int = 4    #: one seed frame every this many frames
    #: no body when the estimate's mean part log-likelihood (LooseLimbedTracker.score) is below this (the
    #: tracker's lost_score: the next frame is found again from no prior pose); None: always a body.
    #: Measured with the joint MAP estimate (the node's default is −14.5): the person −9.8…−14.0 (the
    #: bench's 6 initialisation scenes at 640x480 and 320x240, and section 5's scenes seeds 3–5 at
    #: 320x240, clean and ghost backgrounds), a "body" found in an empty room whose background model
    #: holds ghosts of the person −14.3…−17.5 (section 5's ghost scenes during the blackout)
    min_score: float | None = None


class LooseLimbedStage:
    """Background seeding + loose-limbed tracking of one multi-camera frame at a time."""

    def __init__(self, body: BodyModel, cameras: Sequence[Camera], model: LooseLimbedModel,
                 config: StageConfig | None = None):
        self.config = cfg = config or StageConfig()
        self.body = body
        self.cameras = list(cameras)
        self.geometry = part_geometry(body)
        self.likelihood = PartLikelihood(self.geometry, LikelihoodConfig())
        bp = LooseLimbedBP(model, self.geometry, self.likelihood,
                           NBPConfig(n_particles=cfg.n_particles, n_exclusive=max(cfg.n_particles // 2, 10),
                                     n_message=max(cfg.n_particles * 2 // 5, 10)), seed=cfg.seed)
        self.tracker = LooseLimbedTracker(bp, Shouter(self.geometry, self.likelihood, ShouterConfig(), seed=cfg.seed),
                                          TrackerConfig(init_iterations=cfg.init_iterations,
                                                        track_iterations=cfg.track_iterations,
                                                        use_shouters=cfg.use_shouters, lost_score=cfg.min_score))
        bcfg = BlobTrackerConfig(background_seed_frames=cfg.background_seed_frames,
                                 background_seed_stride=cfg.background_seed_stride)
        self.backgrounds = {c.name: BackgroundModel(bcfg) for c in self.cameras}

    @property
    def ready(self) -> bool:
        """Every camera's background is seeded."""
        return all(b.ready for b in self.backgrounds.values())

    def reinitialise(self) -> None:
        """Forget the belief: the next frame is found from no prior pose."""
        self.tracker.previous = None

    def step_background(self, images: dict[str, np.ndarray]) -> None:
        """Feed one frame (camera name -> BGR uint8 image) to the background seeds only."""
        missing = [c.name for c in self.cameras if c.name not in images]
        if missing:
            raise InputError(f"loose_limbed: a frame has no image from camera '{missing[0]}'")
        for c in self.cameras:
            img = images[c.name]
            if img.shape[:2] != (c.height, c.width):
                raise InputError(f"loose_limbed: camera '{c.name}': image {img.shape[1]}x{img.shape[0]} "
                                 f"differs from the calibration {c.width}x{c.height}")
            bg = self.backgrounds[c.name]
            if not bg.ready:
                bg.foreground(img, img.astype(np.float32))

    def step(self, stamp_ns: int, images: dict[str, np.ndarray]) -> BodyEstimate | None:
        """Process one frame (camera name -> BGR uint8 image); None while the backgrounds seed, when no
        part is found (e.g. nobody in view) or the body found scores below ``min_score``."""
        self.step_background(images)
        if not self.ready:
            return None
        views = [view_evidence(c, images[c.name],
                               np.clip(np.rint(self.backgrounds[c.name].mean), 0, 255).astype(np.uint8),
                               self.likelihood.config) for c in self.cameras]
        initialising = not self.tracker.previous
        joints = self.tracker.step(views)
        if self.tracker.lost:  # too unlikely a body (StageConfig.min_score): nobody found
            return None
        pos, quat = self.tracker.parts
        links = [LinkEstimate(name=name, position=pos[p], rotation=Rotation.from_quat(quat[p]).as_matrix())
                 for p, name in enumerate(self.geometry.names) if np.all(np.isfinite(pos[p]))]
        if not links:
            return None
        return BodyEstimate(stamp_ns=int(stamp_ns), joint_names=list(self.body.joint_names), joints=joints,
                            links=links, blobs=[], status=STATUS_INITIALIZING if initialising else STATUS_TRACKING,
                            quality=float(np.mean(np.all(np.isfinite(joints), axis=1))))


class InitialiserPolicy:
    """When the loose_limbed node infers (ALGORITHMS.md §4 "automatic initialisation, recovery from
    loss"): in mode estimator on every frame; as an initialiser at start until its first body and on
    every frame after the skeleton's last body was LOST — the first frame after the skeleton became
    LOST found again from no prior pose (status INITIALIZING), the following ones tracked (TRACKING:
    what the skeleton takes as a re-seed). With ``start`` also on every frame while the skeleton has
    not started (its last body INITIALIZING), so that a TRACKING body starts it: by default the
    skeleton starts from its own blobs, which measured better (README, bench/loose_limbed.py section 5
    with --loop-ll-start). Shared by the node and bench/loose_limbed.py's closed-loop recovery."""

    def __init__(self, estimator: bool = False, start: bool = False):
        self.estimator = bool(estimator)
        self.start = bool(start)
        self.needs_init = True
        self.skeleton_ok = False  # the skeleton's last body was not LOST (with start: was TRACKING)

    def skeleton(self, status: int) -> bool:
        """Note the status of the skeleton's latest body; True when it has just become LOST (then the
        next frame is found again from no prior pose; while it stays LOST, or with ``start`` has not
        started, the body found is tracked on, so that a TRACKING body can seed it)."""
        status = int(status)
        newly = status == STATUS_LOST and self.skeleton_ok
        self.skeleton_ok = status == STATUS_TRACKING if self.start else status != STATUS_LOST
        self.needs_init = self.needs_init or newly
        return newly

    def infer(self) -> bool:
        """Infer on the next frame (else only seed the backgrounds)?"""
        return self.estimator or self.needs_init or not self.skeleton_ok

    def step(self, stage: LooseLimbedStage, stamp_ns: int, images: dict[str, np.ndarray]) -> BodyEstimate | None:
        """One frame through ``stage`` as the policy says (None: no inference or nothing found)."""
        if not self.infer():
            if not stage.ready:
                stage.step_background(images)
            return None
        if self.needs_init:
            stage.reinitialise()
        est = stage.step(stamp_ns, images)
        if est is not None:
            self.needs_init = False
        return est
