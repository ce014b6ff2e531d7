"""Plain data exchanged between the core stages (and mirrored by artrack_msgs).

Units: metres, radians, seconds; image coordinates in pixels with (0, 0) at
the centre of the top-left pixel (OpenCV convention). Time stamps are integer
nanoseconds everywhere. World frame: right-handed, z up (REP 103).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

#: Tracking status codes, identical to artrack_msgs/TrackedBody constants.
STATUS_INITIALIZING = 0
STATUS_TRACKING = 1
STATUS_LOST = 2

#: Visibility codes of a projected prior, identical to artrack_msgs/BlobPrior2D.
VISIBLE = 0
BEHIND_CAMERA = 1
OFF_IMAGE = 2
OCCLUDED = 3


def all_finite(*arrays) -> bool:
    """Whether every value of the given arrays (any shapes) is finite: one numpy call for all."""
    return not arrays or bool(np.isfinite(np.concatenate([np.ravel(a) for a in arrays])).all())


@dataclass
class Blob2D:
    """One 2-D blob in one camera image (ALGORITHMS.md §1, "2-D blobs").

    mean: (2,) pixel position (u, v); cov: (2, 2) pixel² covariance;
    color_mean: (3,) colour features (normalised chroma r, g and intensity);
    color_cov: (3, 3); pixel_count: support-map pixels with this label.
    """

    label: str
    mean: np.ndarray
    cov: np.ndarray
    color_mean: np.ndarray = field(default_factory=lambda: np.zeros(3))
    color_cov: np.ndarray = field(default_factory=lambda: np.eye(3))
    pixel_count: int = 0


@dataclass
class Prior2D:
    """Projected 3-D prediction of one blob in one camera (ALGORITHMS.md §1,
    "Inverse observation model"). ``stamp_ns`` is the frame it predicts."""

    label: str
    mean: np.ndarray
    cov: np.ndarray
    confidence: float
    visibility: int = VISIBLE
    stamp_ns: int = 0


@dataclass
class Blob3D:
    """A 3-D blob in the world frame: mean (3,) m and covariance (3, 3) m²,
    with the cameras that contributed."""

    label: str
    mean: np.ndarray
    cov: np.ndarray
    cameras: tuple[str, ...] = ()


@dataclass
class LinkEstimate:
    """Pose of one body link in the world frame.

    position: (3,) link-frame origin (proximal joint), m; rotation: (3, 3)
    world_from_link; velocity: (3,) m/s, angular_velocity: (3,) rad/s;
    cov: (6, 6) covariance of [position, rotation-vector] (m², rad²).
    """

    name: str
    position: np.ndarray
    rotation: np.ndarray
    velocity: np.ndarray = field(default_factory=lambda: np.zeros(3))
    angular_velocity: np.ndarray = field(default_factory=lambda: np.zeros(3))
    cov: np.ndarray = field(default_factory=lambda: np.eye(6) * 1e-4)


@dataclass
class BodyEstimate:
    """The tracked body at one instant (what the skeleton node publishes).

    joints: (J, 3) world positions (m) of ``joint_names`` (the 15 output
    joints of the body model). ``blobs`` holds the predicted/estimated 3-D
    blob of every link that carries a blob feature (mean and covariance),
    which feedback projection turns into 2-D priors.
    """

    stamp_ns: int
    joint_names: list[str]
    joints: np.ndarray
    links: list[LinkEstimate]
    blobs: list[Blob3D]
    status: int = STATUS_TRACKING
    quality: float = 1.0

    @classmethod
    def empty(cls, joint_names: list[str], stamp_ns: int, status: int) -> BodyEstimate:
        """A body with no estimate (NaN joints, no links or blobs, quality 0) at ``stamp_ns``."""
        names = list(joint_names)
        return cls(stamp_ns=int(stamp_ns), joint_names=names, joints=np.full((len(names), 3), np.nan),
                   links=[], blobs=[], status=status, quality=0.0)
