"""The closed loop of ALGORITHMS.md §1, as three stages.

    images --BlobStage--> 2-D blobs --SkeletonStage--> body(t), prediction(t+1)
                 ^                                              |
                 +------------- 2-D priors <--ProjectionStage---+

Each stage is the whole state and computation of one node of the live graph
(`blob_features` holds one BlobStage per camera, `skeleton` one SkeletonStage,
`feedback_projection` one ProjectionStage). :class:`ClosedLoopPipeline`
composes the same three objects for `artrack track`, so the offline pipeline
and the live graph run identical code in the identical order. Between stages
the offline pipeline passes every value through the same message conversion
the nodes use (:class:`WireRoundTrip`), so both see bit-identical inputs (a
quaternion round trip alone perturbs a rotation by ~1e-16, which a closed
loop can amplify); a process-level test checks that their joints agree to 1e-9.
"""

from __future__ import annotations

import copy
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from .blob_config import BlobTrackerConfig
from .blobs import BlobTracker2D
from .body_model import BodyModel
from .cameras import Camera
from .edge_fusion import EdgeStage, LinkEdgeStatistics, combine
from .edge_tracker import EdgeTrackerConfig
from .errors import InputError
from .messages import (
    blob_array_msg,
    blobs_from_msg,
    body_from_msg,
    body_msg,
    camera_from_msgs,
    camera_info_msg,
    edge_stats_from_msg,
    edge_stats_msg,
    extrinsics_msg,
    prior_array_msg,
    priors_from_msg,
    rosbags_factory,
)
from .projection import DEFAULT_CENTRE_OCCLUSION_LABELS, DEFAULT_OCCLUSION_SURFACE_SIGMA, project_priors
from .skeleton import make_estimator
from .types import STATUS_TRACKING, Blob2D, BodyEstimate, Prior2D


@dataclass
class PipelineConfig:
    """Options shared by the nodes and ``artrack track`` (see config/*.yaml)."""

    estimator: str = "baseline"
    feedback: bool = True
    fps: float = 30.0
    blob: BlobTrackerConfig = field(default_factory=BlobTrackerConfig)
    skeleton: dict[str, Any] = field(default_factory=dict)
    #: edge features (ALGORITHMS.md §2) measured at the prediction and fused into the
    #: skeleton (baseline estimator) as soft constraints on the links; off by default
    edges: bool = False
    edge: EdgeTrackerConfig = field(default_factory=EdgeTrackerConfig)
    #: the loop iterated within a frame (:meth:`ClosedLoopPipeline.step`; in the graph the skeleton's
    #: ``refine_passes``, lockstep, the feature nodes answering): a frame
    #: that comes at least ``refine_min_interval_s`` after the previous one is processed this many
    #: more times, each pass from the same state with the last pass's body as the priors; 0 = off
    refine_passes: int = 0
    refine_min_interval_s: float = 0.05
    #: the same at the start of a track: the ``startup_refine_frames`` frames after the one a track
    #: started on go round the loop ``startup_refine_passes`` more times (at least), whatever their
    #: interval. The start-up pose is crude (skin blobs matched across views, the rest pose for the
    #: rest), so the first priors land off the limbs, and the loop, one iteration a frame, took ~10
    #: frames to settle on the body (docs/HISTORY.md, stop 62). With edges too since stop 63 (the
    #: graph's edge_features nodes measure a refined frame again, as blob_features label it). 0 = off.
    startup_refine_frames: int = 10
    startup_refine_passes: int = 2


def refine_passes(config: PipelineConfig, previous_stamp_ns: int | None, stamp_ns: int,
                  track_frames: int = 0) -> int:
    """How many more times a frame goes round the loop: ``refine_passes`` for a frame at least
    ``refine_min_interval_s`` after the previous one (none for the first frame, ``previous_stamp_ns``
    None), and at least ``startup_refine_passes`` while the track is young: ``track_frames``, the
    frames just before this one whose body was :func:`refinable`, between 1 and
    ``startup_refine_frames``. The offline pipeline and the skeleton node decide by this."""
    passes = 0
    if (config.refine_passes and previous_stamp_ns is not None
            and (stamp_ns - previous_stamp_ns) * 1e-9 >= config.refine_min_interval_s):
        passes = config.refine_passes
    if 1 <= track_frames <= config.startup_refine_frames:
        passes = max(passes, config.startup_refine_passes)
    return passes


def check_refinement(config: PipelineConfig) -> None:
    """InputError (one line naming the option) for negative refinement settings."""
    for name in ("refine_passes", "refine_min_interval_s", "startup_refine_frames", "startup_refine_passes"):
        value = getattr(config, name)
        if not value >= 0:
            raise InputError(f"pipeline: {name} must be >= 0, got {value}")


def refinable(estimate: BodyEstimate) -> bool:
    """Whether a pass's body can be the next pass's priors: tracking, with finite joints."""
    return estimate.status == STATUS_TRACKING and bool(np.all(np.isfinite(estimate.joints)))


def state_copy(state: Any, shared: Sequence[Any]) -> Any:
    """A deep copy of a stage's state (to go round the loop again from it) that shares the
    ``shared`` objects, which a step never changes (body model, cameras, configuration)."""
    return copy.deepcopy(state, {id(x): x for x in shared})


class FrameClock:
    """Predicts the stamp of the next frame: last interval, or 1/fps at start."""

    def __init__(self, fps: float):
        if fps <= 0:
            raise ValueError(f"fps must be positive, got {fps}")
        self.default_dt_ns = int(round(1e9 / fps))
        self.last_ns: int | None = None

    def next_stamp(self, stamp_ns: int) -> int:
        """The stamp the frame after ``stamp_ns`` is expected at (ns): the last interval when plausible
        (0 < dt < 10 frames), else 1/fps."""
        dt = self.default_dt_ns
        if self.last_ns is not None and 0 < stamp_ns - self.last_ns < 10 * self.default_dt_ns:
            dt = stamp_ns - self.last_ns
        self.last_ns = stamp_ns
        return stamp_ns + dt


def blob_colour_classes(body: BodyModel) -> dict[str, str]:
    """Colour class ('skin', 'shirt', ...) of each blob-carrying link."""
    return {link.name: link.blob.colour for link in body.links if link.blob is not None}


class BlobStage:
    """One camera's 2-D blob tracker, fed with the priors for its frame (§1)."""

    def __init__(self, camera_name: str, body: BodyModel, config: PipelineConfig):
        self.camera_name = camera_name
        self.feedback = config.feedback
        self.tracker = BlobTracker2D(camera_name, list(body.blob_labels), blob_colour_classes(body), config.blob)
        self.shape: tuple[int, ...] | None = None
        self.used_priors = False  # whether the last step's priors were used (feedback / start-up)

    def step(self, image_bgr: np.ndarray, priors: list[Prior2D] | None) -> list[Blob2D]:
        """Blobs of one image; InputError (the frame is skipped) if it is not the camera's BGR size."""
        shape = getattr(image_bgr, "shape", ())
        if len(shape) != 3 or shape[2] != 3 or image_bgr.dtype != np.uint8:
            raise InputError(f"camera '{self.camera_name}': image is not (H, W, 3) uint8 BGR (shape {shape})")
        if self.shape is None:
            self.shape = shape
        elif shape != self.shape:
            raise InputError(f"camera '{self.camera_name}': image is {shape[1]}x{shape[0]}, "
                             f"earlier frames were {self.shape[1]}x{self.shape[0]}")
        # Feedback off (the comparison of ALGORITHMS.md §1): the priors only hand the labels
        # over at start-up (and after every label was lost); tracking then runs on 2-D
        # temporal smoothness alone.
        self.used_priors = bool(priors) and (self.feedback or not self.tracker.tracks)
        return self.tracker.step(image_bgr, priors if self.used_priors else None)


class SkeletonStage:
    """The 3-D estimator: update with all cameras' blobs, predict the next frame."""

    def __init__(self, body: BodyModel, cameras: list[Camera], config: PipelineConfig):
        self.estimator = make_estimator(config.estimator, body, cameras, config.skeleton)
        self.clock = FrameClock(config.fps)
        self.prediction_ms = 0.0  # the last step's prediction, ms

    def step(self, stamp_ns: int, blobs_by_camera: Mapping[str, list[Blob2D]],
             edges: LinkEdgeStatistics | None = None) -> tuple[BodyEstimate, BodyEstimate]:
        """(the body at ``stamp_ns`` from every camera's blobs and the optional edge statistics,
        the body predicted for the next frame)."""
        ordered = {name: blobs_by_camera[name] for name in sorted(blobs_by_camera)}
        estimate = self.estimator.update(stamp_ns, ordered, edges)
        t0 = time.perf_counter()
        prediction = self.estimator.predict(self.clock.next_stamp(stamp_ns))
        self.prediction_ms = (time.perf_counter() - t0) * 1e3  # (the kinematic one runs the solver)
        return estimate, prediction


class ProjectionStage:
    """Feedback projection of the predicted 3-D blobs into every camera (§1)."""

    def __init__(self, body: BodyModel, cameras: list[Camera],
                 occlusion_surface_sigma: float = DEFAULT_OCCLUSION_SURFACE_SIGMA,
                 centre_occlusion_labels: Sequence[str] = DEFAULT_CENTRE_OCCLUSION_LABELS):
        self.body = body
        self.cameras = sorted(cameras, key=lambda c: c.name)
        self.occlusion_surface_sigma = float(occlusion_surface_sigma)
        self.centre_occlusion_labels = tuple(centre_occlusion_labels)

    def step(self, prediction: BodyEstimate) -> dict[str, list[Prior2D]]:
        """{camera: the 2-D priors of the predicted body} (:func:`artrack.projection.project_priors`)."""
        return project_priors(prediction, self.cameras, self.body,
                              occlusion_surface_sigma=self.occlusion_surface_sigma,
                              centre_occlusion_labels=self.centre_occlusion_labels)


@dataclass
class FrameResult:
    """What one frame's step gives: the 2-D blobs per camera, the body estimated at the frame and
    predicted for the next, the priors used and those for the next frame, per-stage wall times (ms)
    and the passes the frame took round the loop."""

    stamp_ns: int
    blobs: dict[str, list[Blob2D]]
    estimate: BodyEstimate
    prediction: BodyEstimate
    priors_used: dict[str, list[Prior2D] | None]
    next_priors: dict[str, list[Prior2D]]
    timings_ms: dict[str, float] = field(default_factory=dict)
    passes: int = 1  # times the frame went round the loop (``PipelineConfig.refine_passes``)


class WireRoundTrip:
    """The message conversions of the live graph, applied between offline stages."""

    def __init__(self):
        self.f = rosbags_factory()

    def blobs(self, stamp_ns: int, camera: str, blobs: list[Blob2D]) -> list[Blob2D]:
        """The blobs as the skeleton node receives them (BlobArray and back)."""
        return blobs_from_msg(blob_array_msg(self.f, stamp_ns, camera, camera, blobs))[2]

    def priors(self, camera: str, priors: list[Prior2D], stamp_ns: int) -> list[Prior2D]:
        """The priors as a blob_features node receives them (PriorArray and back)."""
        return priors_from_msg(prior_array_msg(self.f, stamp_ns, camera, camera, priors))[2]

    def body(self, body: BodyEstimate) -> BodyEstimate:
        """The body as feedback_projection and the edge nodes receive it (TrackedBody and back)."""
        return body_from_msg(body_msg(self.f, body))

    def edges(self, stamp_ns: int, camera: str, link_names: list[str], stats: LinkEdgeStatistics | None,
              reference_stamp_ns: int) -> LinkEdgeStatistics | None:
        """The edge statistics as the skeleton node receives them (EdgeStatistics and back)."""
        msg = edge_stats_msg(self.f, stamp_ns, camera, camera, link_names, stats, reference_stamp_ns)
        return edge_stats_from_msg(msg, link_names)[2]

    def camera(self, camera: Camera) -> Camera:
        """As the nodes see it: published by bag_player / camera_ingest, rebuilt by subscribers."""
        return camera_from_msgs(camera.name, camera_info_msg(self.f, camera, 0), extrinsics_msg(self.f, camera, 0))


class ClosedLoopPipeline:
    """All three stages in one process: the offline form of the live graph."""

    def __init__(self, body: BodyModel, cameras: list[Camera], config: PipelineConfig | None = None):
        self.config = config or PipelineConfig()
        self.wire = WireRoundTrip()
        self.cameras = sorted((self.wire.camera(c) for c in cameras), key=lambda c: c.name)
        self.blob_stages = {c.name: BlobStage(c.name, body, self.config) for c in self.cameras}
        self.skeleton = SkeletonStage(body, self.cameras, self.config)
        self.projection = ProjectionStage(body, self.cameras)
        self.edge_stages = ({c.name: EdgeStage(c, body, self.config.edge) for c in self.cameras}
                            if self.config.edges else {})
        self.link_names = list(body.link_names)
        self.reference: np.ndarray | None = None  # world_from_link of the last prediction (edges)
        self.reference_stamp = 0
        self.reference_status: int | None = None  # its status (a new track: the edge stages relearn)
        self.priors: dict[str, list[Prior2D]] = {}
        self.frames = 0
        self.last_stamp_ns: int | None = None  # the previous frame's (refine_min_interval_s)
        self.track_frames = 0  # frames in a row whose body was refinable (startup_refine_frames)
        check_refinement(self.config)
        # shared, never changed by a step: not copied by the refinement's snapshots
        self._shared = [body, self.config, *self.cameras]

    def step(self, stamp_ns: int, images: Mapping[str, np.ndarray]) -> FrameResult:
        """One frame round the loop: blobs with the priors predicted for it, the body, the next
        frame's priors.

        With ``config.refine_passes`` k > 0, a tracked frame that comes at least
        ``refine_min_interval_s`` after the previous one goes round up to k more times. Each pass
        starts from the state before the frame (blob trackers, skeleton, edge stages) and takes
        the previous pass's body, projected, as its priors; the last pass is kept. The closed loop
        is one labelling / body-fit iteration a frame, which converges while the body moves little
        between frames; when frames come further apart (a slow loop or camera) the prediction
        lands off the limbs, the labels follow it, and more iterations on the same images pull
        the body back onto them. The same holds for the first frames of a track, whose priors come
        from the crude start-up pose: the ``startup_refine_frames`` frames after the one a track
        started on go round ``startup_refine_passes`` more times. The timings are summed over the
        passes."""
        extra = refine_passes(self.config, self.last_stamp_ns, stamp_ns, self.track_frames)
        total: dict[str, float] = {}
        for done in range(1, extra + 2):
            snapshot = self._snapshot() if done <= extra else None
            result = self._step_once(stamp_ns, images)
            for k, v in result.timings_ms.items():
                total[k] = total.get(k, 0.0) + v
            if snapshot is None or not refinable(result.estimate):
                break  # the last pass, or no body to refine from: this pass stands
            self._restore(snapshot)
            self._feed_back(result.estimate)
        result.timings_ms, result.passes = total, done
        self.last_stamp_ns = int(stamp_ns)
        self.track_frames = self.track_frames + 1 if refinable(result.estimate) else 0
        return result

    def _snapshot(self) -> tuple:
        return state_copy((self.blob_stages, self.skeleton, self.edge_stages, self.frames), self._shared)

    def _restore(self, snapshot: tuple) -> None:
        self.blob_stages, self.skeleton, self.edge_stages, self.frames = snapshot

    def _step_once(self, stamp_ns: int, images: Mapping[str, np.ndarray]) -> FrameResult:
        blobs: dict[str, list[Blob2D]] = {}
        used: dict[str, list[Prior2D] | None] = {}
        t0 = time.perf_counter()
        for name in sorted(images):
            stage = self.blob_stages.get(name)
            if stage is None:
                raise KeyError(f"unknown camera '{name}' (not in the calibration)")
            priors = self.priors.get(name) if self.frames > 0 else None
            blobs[name] = self.wire.blobs(stamp_ns, name, stage.step(images[name], priors))
            used[name] = priors if stage.used_priors else None
        t1 = time.perf_counter()
        edges = None
        if self.edge_stages:
            edges = combine([self.wire.edges(
                stamp_ns, name, self.link_names,
                self.edge_stages[name].step(images[name], self.reference, self.reference_status)
                if self.reference is not None else None,
                self.reference_stamp) for name in sorted(images) if name in self.edge_stages])
        t_edges = time.perf_counter()
        estimate, prediction = self.skeleton.step(stamp_ns, blobs, edges)
        t2 = time.perf_counter()
        self._feed_back(prediction)
        t3 = time.perf_counter()
        self.frames += 1
        timings = {"blobs_2d": (t1 - t0) * 1e3, "skeleton_3d": (t2 - t_edges) * 1e3, "projection": (t3 - t2) * 1e3}
        if self.edge_stages:
            timings["edges"] = (t_edges - t1) * 1e3
        # sub-stages (ms): the blob trackers' summed over cameras, the estimator's update
        for name in blobs:
            for k, v in self.blob_stages[name].tracker.timings_ms.items():
                timings[f"blobs_2d.{k}"] = timings.get(f"blobs_2d.{k}", 0.0) + v
        for k, v in self.skeleton.estimator.timings_ms.items():
            timings[f"skeleton_3d.{k}"] = v
        timings["skeleton_3d.prediction"] = self.skeleton.prediction_ms
        return FrameResult(stamp_ns, blobs, estimate, prediction, used, self.priors, timings)

    def _feed_back(self, prediction: BodyEstimate) -> None:
        """The prediction for the next frame becomes the blob priors and the edge reference."""
        wired = self.wire.body(prediction)
        self.reference = link_poses(wired) if self.edge_stages else None
        self.reference_stamp = prediction.stamp_ns
        self.reference_status = wired.status
        projected = self.projection.step(wired)
        self.priors = {name: self.wire.priors(name, p, prediction.stamp_ns) for name, p in projected.items()}

    def restart(self, stamp_ns: int, joints: np.ndarray) -> None:
        """Start a new track from a known body, the frame at ``stamp_ns``'s own: the skeleton is
        reset and re-seeded with ``joints`` (J, 3) world m at that stamp (:meth:`Estimator.reseed`), its
        prediction for that frame becomes the priors and the edge reference, and the edge stages
        learn their appearance again there. The benches' "correct start" protocol (the loop's
        drift without the automatic start-up); InputError for bad joints."""
        estimator = self.skeleton.estimator
        joints = estimator.check_reseed_joints(joints)  # before anything is reset
        estimator.reset()
        # known joints: the limbs too; at the frame's own stamp, so that its update follows no time
        # step (at stamp - 1, before stop 71, the first update's 1-ns step made the baseline's
        # joint velocities ~1e8 rad/s: lost at the next frame)
        estimator.reseed(int(stamp_ns), joints, limb_sigma_m=0.05)
        for stage in self.edge_stages.values():
            stage.relearn()
        self._feed_back(estimator.predict(int(stamp_ns)))
        self.frames = max(self.frames, 1)  # the priors are fresh: the blob stages use them
        self.track_frames = self.config.startup_refine_frames + 1  # a known body: no start-up refinement


def load_pipeline_config(
    estimator: str = "baseline",
    feedback: bool = True,
    fps: float = 30.0,
    blob_config: str | None = None,
    skeleton_config: str | None = None,
    edges: bool = False,
    edge_config: str | None = None,
) -> PipelineConfig:
    """PipelineConfig from the switches and the tunables files in config/."""
    from .config import config_path, load_dataclass_yaml, read_yaml

    blob = load_dataclass_yaml(config_path(blob_config, "blob_features.yaml"), BlobTrackerConfig)
    skeleton = read_yaml(config_path(skeleton_config, "skeleton.yaml"))
    edge = EdgeTrackerConfig.from_yaml(config_path(edge_config, "edge_features.yaml"))
    return PipelineConfig(estimator=estimator, feedback=feedback, fps=fps, blob=blob, skeleton=skeleton,
                          edges=edges, edge=edge)


def link_poses(body: BodyEstimate) -> np.ndarray | None:
    """(L, 4, 4) world_from_link of an estimate's links (None if it has none: not tracking)."""
    if not body.links:
        return None
    E = np.tile(np.eye(4), (len(body.links), 1, 1))
    for i, link in enumerate(body.links):
        E[i, :3, :3] = link.rotation
        E[i, :3, 3] = link.position
    return E
