"""3-D body estimators: the raw baseline and the dynamic skeleton (ALGORITHMS.md §1).

``make_estimator(kind, body, cameras, config)`` returns an object with

    update(stamp_ns, blobs_by_camera) -> BodyEstimate   # estimate at stamp_ns
    predict(stamp_ns) -> BodyEstimate                   # prediction for a later frame

The parts they share live beside this module: the tunables in ``skeleton_config``, the
cues in ``startup``. The estimators live in one module each, with the rules they apply:

``estimator``           ``Estimator``, their common frame: 3-D blobs from the labelled 2-D blobs,
                        start-up, the face check and verification, re-acquisition, the track's
                        life cycle, one or two cameras; ``BodyKinematics`` (theta <-> link poses)
``baseline_estimator``  ``'baseline'``, the raw feature tracker: triangulation + body fit per frame
``kalman_skeleton``     ``'kinematic'`` (Kalman filters as goals of the constraint solver, paper
                        §2.3) and ``'dynamic'`` (full dynamics, paper §2.1), the raw tracker beside them

Units: metres, radians, seconds (stamps in integer ns); world frame z up.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from typing import Any

from .baseline_estimator import BaselineEstimator
from .body_model import BodyModel
from .cameras import Camera
from .errors import InputError
from .estimator import BodyKinematics
from .kalman_skeleton import DynamicEstimator, KinematicEstimator
from .skeleton_config import KINDS, SkeletonConfig

__all__ = [
    "BaselineEstimator",
    "BodyKinematics",
    "DynamicEstimator",
    "KinematicEstimator",
    "make_estimator",
]


def make_estimator(
    kind: str,
    body: BodyModel,
    cameras: Iterable[Camera] | Mapping[str, Camera],
    config: SkeletonConfig | Mapping[str, Any] | None = None,
):
    """The 3-D estimator ``kind`` ('baseline' | 'kinematic' | 'dynamic') for ``body`` seen by
    ``cameras`` (list or {name: Camera}); config: parsed config/skeleton.yaml (mapping of
    sections), a SkeletonConfig, or None for the defaults."""
    classes = {"baseline": BaselineEstimator, "kinematic": KinematicEstimator, "dynamic": DynamicEstimator}
    if kind not in classes:
        raise InputError(f"skeleton: unknown estimator kind '{kind}' (expected one of {', '.join(KINDS)})")
    return classes[kind](body, cameras, config)
