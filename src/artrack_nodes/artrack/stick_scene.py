"""Synthetic RGB-D scenes of a person holding a stick in both hands, with ground truth
(ALGORITHMS.md §3 experiments).

The person stands at the origin facing +x; one RGB-D camera (``rgbd``,
320×240, registered colour and depth) stands 2.6 m in front at chest height,
like the paper's single stereo camera. Two motions like the paper's:

``stick_side`` (5 s)   the stick, held horizontally at chest height with the
                       hands 0.55 m apart, moves side to side (1.5 periods of
                       1.75 s, the torso twisting along), then goes overhead
                       (2.6-3.6 s) and down behind the head (3.6-4.6 s).
``stick_sword`` (3.2 s) both hands close together near one end of the stick,
                       swung like a sword in diagonal slashes (period 1.6 s).

Poses come from the hands' targets by projecting onto the pose manifold of
the arms (:class:`~artrack.pose_manifold.PoseManifold`, a weighted inverse
kinematics that keeps the rest of the body near a natural pose), frame after
frame; the stick is then placed through the two grip points that were
actually reached, so the ground truth is always consistent. Root and legs do
not move (the person stands).

Each frame: the true pose, the stick end points a, b (world), a noisy depth
image with dropouts (:func:`artrack.pointcloud.render_depth`), its points in
the camera's optical frame, and (optionally) the colour image of the
renderer in :mod:`artrack.synth` with the yellow stick painted where it is
the nearest surface (so a 2-D stick detector can find it).
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from .body_model import BodyModel, load_body_model
from .cameras import Camera
from .motion import _place, _Pose, _standing, smoothstep
from .pointcloud import DepthNoise, points_from_depth, render_depth
from .pose_manifold import PoseManifold

__all__ = [
    "STICK_BGR",
    "STICK_TOPIC",
    "STICK_DURATION_S",
    "STICK_MOTIONS",
    "StickFrame",
    "generate_stick_scene",
    "holding_pose",
    "points_topic",
    "rgbd_camera",
    "scene_bag_messages",
    "stick_length",
    "stick_trajectory",
]

STICK_MOTIONS = ("stick_side", "stick_sword")
STICK_DURATION_S = {"stick_side": 5.0, "stick_sword": 3.2}
STICK_BGR = (0, 215, 255)     # yellow
STICK_RADIUS = 0.015          # m
#: distances (m) of the stick ends a and b from the midpoint of the hands, along the stick
STICK_ENDS = {"stick_side": (0.7, 0.7), "stick_sword": (0.65, 0.17)}


def stick_length(motion: str) -> float:
    """Length (m) of the stick of a stick motion."""
    return float(sum(STICK_ENDS[motion]))


def rgbd_camera(width: int = 320, height: int = 240, name: str = "rgbd") -> Camera:
    """The scene's RGB-D camera: 2.6 m in front of the person (+x), 1.35 m high, looking at
    (0, 0, 1.2); 62° horizontal field of view, no distortion."""
    f = 0.5 * width / np.tan(np.deg2rad(31.0))
    K = np.array([[f, 0.0, (width - 1) / 2.0], [0.0, f, (height - 1) / 2.0], [0.0, 0.0, 1.0]])
    return Camera.look_at(name, width, height, K, eye=np.array([2.6, 0.0, 1.35]),
                          target=np.array([0.0, 0.0, 1.2]))


def holding_pose(body: BodyModel) -> np.ndarray:
    """(n_dof,) standing at the origin facing +x, both forearms forward at chest height (a stick
    motion's start, and the particle tracker's default initial pose)."""
    p = _Pose(body)
    _standing(p)
    p["l_upper_arm"] = [0.1, -1.0, 0.0]
    p["r_upper_arm"] = [-0.1, -1.0, 0.0]
    p["l_forearm"] = 0.6
    p["r_forearm"] = 0.6
    _place(p, (0.0, 0.0), 0.0)
    return p.theta


def _hand_targets(name: str, t: float) -> tuple[np.ndarray, np.ndarray, float, float]:
    """(grip centre (3,), stick direction (3,) unit, from the right to the left hand, hand
    separation m, (tip length beyond the left hand, length beyond the right hand)) at t."""
    if name == "stick_side":
        lift = float(smoothstep((t - 2.6) / 1.0))
        back = float(smoothstep((t - 3.6) / 1.0))
        y = 0.28 * np.sin(2.0 * np.pi * t / 1.75) * (1.0 - lift)
        front = np.array([0.42, y, 1.12])
        over = np.array([0.18, 0.0, 1.78])
        behind = np.array([-0.10, 0.0, 1.52])
        c = (1.0 - lift) * front + lift * ((1.0 - back) * over + back * behind)
        sep = 0.55 + 0.15 * lift
        return c, np.array([0.0, 1.0, 0.0]), sep, 0.3
    # stick_sword: diagonal slashes, period 1.6 s
    ph = 2.0 * np.pi * t / 1.6
    c = np.array([0.42 + 0.05 * np.cos(ph), -0.18 * np.sin(ph), 1.15 + 0.16 * np.cos(ph)])
    u = np.array([0.45, 0.55 * np.sin(ph), 0.75 + 0.1 * np.cos(ph)])
    return c, u / np.linalg.norm(u), 0.10, 0.0


@lru_cache(maxsize=8)
def _trajectory_cached(name: str, fps: float, n: int, body_id: int) -> tuple[np.ndarray, np.ndarray]:
    body = _BODIES[body_id]
    base = holding_pose(body)
    M = PoseManifold(body, base)
    theta = M.active(base)[None]
    rest = theta.copy()
    w = np.full(M.P, 0.05)
    w[M.hand_points] = 1.0
    thetas, sticks = [], []
    for i in range(n):
        t = i / fps
        c, u, sep, _ = _hand_targets(name, t)
        rest_t = rest.copy()
        rest_t[0, 2] = 0.25 * np.sin(2.0 * np.pi * t / 1.75) if name == "stick_side" else 0.0  # torso twist
        x = M.end_points(rest_t)
        x[0, M.hand_points[0]] = c + 0.5 * sep * u
        x[0, M.hand_points[1]] = c - 0.5 * sep * u
        theta, _ = M.project(x, rest_t if i == 0 else theta, w, reg=0.02, max_iter=200)
        hands = M.hands(theta)[0]
        gl, gr = hands
        d = gl - gr
        d /= np.linalg.norm(d)
        m = 0.5 * (gl + gr)
        a, b = m + STICK_ENDS[name][0] * d, m - STICK_ENDS[name][1] * d
        thetas.append(M.full_theta(theta)[0])
        sticks.append(np.stack([a, b]))
    return np.array(thetas), np.array(sticks)


_BODIES: dict[int, BodyModel] = {}


def stick_trajectory(name: str, fps: float, n_frames: int, body: BodyModel | None = None
                     ) -> tuple[np.ndarray, np.ndarray]:
    """(poses (T, n_dof), sticks (T, 2, 3): end points a, b world m) of a stick motion."""
    if name not in STICK_MOTIONS:
        raise ValueError(f"stick motion: unknown motion '{name}' (expected one of {', '.join(STICK_MOTIONS)})")
    body = load_body_model() if body is None else body
    _BODIES[id(body)] = body
    th, st = _trajectory_cached(name, float(fps), int(n_frames), id(body))
    return th.copy(), st.copy()


@dataclass
class StickFrame:
    """One RGB-D frame: index, stamp_ns, theta (n_dof,) true pose, joints (J, 3) world m,
    stick (2, 3) true end points a, b world m, depth (H, W) float32 m (NaN missing),
    points_cam (K, 3) float32 optical frame m, image (H, W, 3) BGR uint8 or None,
    images {camera name: image} (for scene bags)."""

    index: int
    stamp_ns: int
    theta: np.ndarray
    joints: np.ndarray
    stick: np.ndarray
    depth: np.ndarray
    points_cam: np.ndarray
    image: np.ndarray | None
    images: dict


def generate_stick_scene(motion: str, seed: int = 0, fps: float = 15.0, duration_s: float | None = None,
                         camera: Camera | None = None, body: BodyModel | None = None,
                         noise: DepthNoise | None = None, colour: bool = True,
                         pixel_noise: float = 2.0) -> Iterator[StickFrame]:
    """Yield the frames of a stick scene (deterministic for the arguments)."""
    from .synth import Renderer, frame_stamp_ns

    body = load_body_model() if body is None else body
    camera = rgbd_camera() if camera is None else camera
    duration_s = STICK_DURATION_S[motion] if duration_s is None else float(duration_s)
    n = int(round(duration_s * fps))
    thetas, sticks = stick_trajectory(motion, fps, n, body)
    rng = np.random.default_rng([seed, 424242])
    renderer = Renderer(body, [camera], seed) if colour else None
    for i in range(n):
        theta, stick = thetas[i], sticks[i]
        depth, label = render_depth(body, theta, camera, rng, noise, stick=(stick[0], stick[1]))
        image = None
        if renderer is not None:
            image = renderer.render(theta, (), pixel_noise, frame_index=i)[0]
            image[label == 2] = STICK_BGR
        yield StickFrame(index=i, stamp_ns=frame_stamp_ns(i, fps), theta=theta, joints=body.joint_positions(theta),
                         stick=stick, depth=depth, points_cam=points_from_depth(depth, camera), image=image,
                         images={camera.name: image} if image is not None else {})


#: topics of a stick scene bag besides the cameras' and the ground truth (see scene_bag_messages)
STICK_TOPIC = "/artrack/stick"


def points_topic(camera: str) -> str:
    """/cameras/<camera>/points: the depth camera's point cloud (sensor_msgs/PointCloud2)."""
    return f"/cameras/{camera}/points"


def scene_bag_messages(frame: StickFrame, camera: Camera, factory, crop: bool = True) -> list[tuple[str, object]]:
    """A frame's point cloud (optical frame; with ``crop``, only the points in the workspace box
    around the person, as a pass-through filter would keep) and stick pose (world) as
    (topic, message) pairs, built with a messages.MsgFactory."""
    from .messages import pointcloud_msg, stick_pose_msg
    from .pointcloud import camera_from_world_points, crop_box, workspace_box, world_from_camera_points

    pts = frame.points_cam
    if crop:
        lo, hi = workspace_box(frame.theta[:3])
        pts = camera_from_world_points(camera, crop_box(world_from_camera_points(camera, pts), lo, hi))
    return [(points_topic(camera.name), pointcloud_msg(factory, pts, frame.stamp_ns, camera.frame_id)),
            (STICK_TOPIC, stick_pose_msg(factory, frame.stick[0], frame.stick[1], frame.stamp_ns))]
