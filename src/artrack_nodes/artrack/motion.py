"""Scripted synthetic motions: deterministic pose trajectories theta(t) for the body model.

Every motion is a smooth (C2) function of time built from quintic blends, a
walking gait and a small numerical arm IK; poses respect the joint limits and
keep the feet on the floor (z = 0). World frame: z up, the floor is z = 0,
metres, radians, seconds.

Motions (``motion_names()``):

``default`` (10 s)
    0-4.9 s walk one lap of a circle of radius 0.6 m (centre (0, 0.6)),
    starting and ending at the origin facing +x, arms swinging;
    4.9-7.4 s wave both arms overhead; 7.4-10 s reach across the body with
    the right hand to the left side and back.
``self_occlusion`` (10 s)
    the same walk, then the right hand goes behind the back (~5.4-6.7 s it is
    hidden by the torso from the two front cameras cam01 and cam04 of
    ``synth.default_rig``) and returns; then (7.4-10 s) the left hand waves overhead.
``line``
    standing at the origin facing +x; the right wrist moves back and forth on a
    0.4 m straight line in front of the body (mean speed 0.3 m/s, period 2.67 s).
``rotation``
    standing; the right wrist moves on a 0.15 m radius circle in a frontal
    plane (period 3 s) so the forearm rotates smoothly.
``distractor``
    a second person walking along y = -0.9 m from x = +5 m to x = -5 m at
    1 m/s (passes the target at t = 5 s, ~0.9-1.5 m away).
``rest``
    standing still at the origin.
"""

from __future__ import annotations

from collections.abc import Callable
from functools import lru_cache

import numpy as np
from scipy.optimize import least_squares

from .body_model import BodyModel, load_body_model
from .errors import InputError

#: nominal duration of each motion, s (they are defined for any t >= 0)
DURATION_S = {"default": 10.0, "self_occlusion": 10.0, "line": 10.0, "rotation": 10.0,
              "distractor": 10.0, "rest": 10.0}

# Walk of the target: circle through the origin, tangent to +x, counter-clockwise.
WALK_RADIUS = 0.6
WALK_SPEED = 0.9          # m/s at full amplitude
STRIDE_LENGTH = 1.2       # m per gait cycle (two steps)
WALK_RAMP_UP = (0.0, 0.6)  # s, amplitude 0 -> 1
WALK_RAMP_DOWN_S = 0.8

_SOFTMIN_K = 0.005  # m, smoothness of the floor contact (feet within ±k·ln(n)/2 of z = 0)


# ------------------------------------------------------------------ smooth helpers
def smoothstep(x: np.ndarray | float) -> np.ndarray | float:
    """Quintic 0 -> 1 blend on [0, 1] (C2: zero 1st and 2nd derivatives at both ends)."""
    x = np.clip(x, 0.0, 1.0)
    return x * x * x * (x * (6.0 * x - 15.0) + 10.0)


def _smoothstep_integral(x: float) -> float:
    """∫_0^x smoothstep(u) du for x in [0, 1]."""
    x = float(np.clip(x, 0.0, 1.0))
    return x**6 - 3.0 * x**5 + 2.5 * x**4


def window(t: float, t0: float, t1: float, ramp: float) -> float:
    """C2 weight: 0 before t0, rises over ``ramp`` s, 1 until t1 - ramp, falls to 0 at t1."""
    return float(smoothstep((t - t0) / ramp) * (1.0 - smoothstep((t - (t1 - ramp)) / ramp)))


# ------------------------------------------------------------------ pose helpers
class _Pose:
    """Mutable theta with named access (link name -> its dof values)."""

    def __init__(self, body: BodyModel):
        self.body = body
        self.theta = body.rest_pose()

    def __getitem__(self, link: str) -> np.ndarray:
        return self.theta[self.body.dof_slice(link)]

    def __setitem__(self, link: str, value) -> None:
        self.theta[self.body.dof_slice(link)] = value

    def blend(self, link: str, value, w: float) -> None:
        """theta[link] <- (1 - w) theta[link] + w value."""
        s = self.body.dof_slice(link)
        self.theta[s] = (1.0 - w) * self.theta[s] + w * np.asarray(value, float)


def _standing(p: _Pose) -> None:
    """Relaxed standing: arms slightly away from the thighs, elbows a little bent."""
    p["l_upper_arm"] = [0.10, 0.0, 0.0]
    p["r_upper_arm"] = [-0.10, 0.0, 0.0]
    p["l_forearm"] = 0.15
    p["r_forearm"] = 0.15


def _gait(p: _Pose, phase: float, a: float) -> None:
    """Add a walking gait at gait phase ``phase`` (rad) with amplitude a in [0, 1].

    Left thigh forward at phase pi/2; left leg swings (knee bends) around phase 0.
    """
    s, c = np.sin(phase), np.cos(phase)
    hip = 0.42 * a * s
    p["l_thigh"] = p["l_thigh"] + [0.0, -hip, 0.0]
    p["r_thigh"] = p["r_thigh"] + [0.0, hip, 0.0]
    p["l_shin"] = p["l_shin"] + a * (0.08 + 0.75 * ((1.0 + c) / 2.0) ** 2)
    p["r_shin"] = p["r_shin"] + a * (0.08 + 0.75 * ((1.0 - c) / 2.0) ** 2)
    p["l_foot"] = p["l_foot"] + a * (0.12 * s - 0.05)
    p["r_foot"] = p["r_foot"] + a * (-0.12 * s - 0.05)
    # arms swing opposite to the legs
    p["l_upper_arm"] = p["l_upper_arm"] + [0.0, 0.35 * a * s, 0.0]
    p["r_upper_arm"] = p["r_upper_arm"] + [0.0, -0.35 * a * s, 0.0]
    p["l_forearm"] = p["l_forearm"] + a * (0.2 - 0.15 * s)
    p["r_forearm"] = p["r_forearm"] + a * (0.2 + 0.15 * s)
    p["torso"] = p["torso"] + [0.0, 0.06 * a, -0.10 * a * s]


def _place(p: _Pose, xy, heading: float) -> None:
    """Root at ground position xy (m), yaw ``heading`` (rad, continuous: rotvec (0, 0, heading)),
    height chosen so that the lowest sole point (soft minimum) touches z = 0."""
    p.theta[0:2] = xy
    p.theta[2] = 0.0
    p.theta[3:6] = [0.0, 0.0, heading]
    z = _sole_heights(p.body, p.theta)
    # soft minimum (C-infinity), centred so the lowest point is within ±k·ln(n)/2 of the floor
    softmin = -_SOFTMIN_K * np.log(np.sum(np.exp(-(z - z.min()) / _SOFTMIN_K))) + z.min()
    p.theta[2] = -(softmin + 0.5 * _SOFTMIN_K * np.log(len(z)))


@lru_cache(maxsize=8)
def _sole_points(body: BodyModel) -> tuple[np.ndarray, np.ndarray]:
    """(link index (P,), sole points (P, 3) in link frames): bottoms of the foot shapes."""
    idx, pts = [], []
    for i, lk in enumerate(body.links):
        if not lk.name.endswith("foot"):
            continue
        for sh in lk.shapes:
            a, b, r = sh.as_capsule()
            for q in (a, b):
                idx.append(i)
                pts.append(q - [0.0, 0.0, r])
    if not idx:  # a model without feet: use the link ends of the leaves
        leaves = [i for i in range(len(body.links)) if i not in set(body.parent_index)]
        idx = leaves
        pts = [body.links[i].end for i in leaves]
    return np.array(idx), np.array(pts, float)


def _sole_heights(body: BodyModel, theta: np.ndarray) -> np.ndarray:
    idx, pts = _sole_points(body)
    T = body.forward_kinematics(theta)
    return body.transform_points(T, idx, pts)[:, 2]


# ------------------------------------------------------------------ arm IK
def arm_ik(body: BodyModel, side: str, target_torso: np.ndarray, preferred: np.ndarray,
           reg: float = 1e-3) -> np.ndarray:
    """Shoulder rotvec (3,) + elbow angle placing the ``side`` ('l'/'r') wrist at target_torso.

    target_torso: (3,) wrist position in the torso frame, m. preferred: (4,)
    dof values the solution is pulled towards (selects the elbow swivel) and
    the start of the search. Returns (4,) within the joint limits; the wrist
    error is sub-millimetre when the target is reachable.
    """
    upper = body.link(f"{side}_upper_arm")
    fore = body.link(f"{side}_forearm")
    hand = body.link(f"{side}_hand")
    lo = np.concatenate([upper.lower, fore.lower])
    hi = np.concatenate([upper.upper, fore.upper])
    x0 = np.clip(preferred, lo + 1e-6, hi - 1e-6)
    from scipy.spatial.transform import Rotation

    def wrist(q):
        R_sh = Rotation.from_rotvec(q[:3]).as_matrix()
        k = fore.axis
        K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
        R_el = np.eye(3) + np.sin(q[3]) * K + (1 - np.cos(q[3])) * K @ K
        return upper.offset + R_sh @ (fore.offset + R_el @ hand.offset)

    def resid(q):
        return np.concatenate([wrist(q) - target_torso, reg * (q - preferred)])

    sol = least_squares(resid, x0, bounds=(lo, hi), xtol=1e-12, ftol=1e-12, gtol=1e-12, max_nfev=200)
    return sol.x


# ------------------------------------------------------------------ walking path
def _walk_amplitude(t: float, t_stop: float) -> float:
    up = smoothstep((t - WALK_RAMP_UP[0]) / (WALK_RAMP_UP[1] - WALK_RAMP_UP[0]))
    down = 1.0 - smoothstep((t - (t_stop - WALK_RAMP_DOWN_S)) / WALK_RAMP_DOWN_S)
    return float(up * down)


def _walk_distance(t: float, t_stop: float) -> float:
    """Arc length walked by time t, m (∫ speed · amplitude)."""
    r_up = WALK_RAMP_UP[1] - WALK_RAMP_UP[0]
    t_down = t_stop - WALK_RAMP_DOWN_S
    d = r_up * _smoothstep_integral(t / r_up)
    d += max(0.0, min(t, t_down) - r_up)
    if t > t_down:
        x = min((t - t_down) / WALK_RAMP_DOWN_S, 1.0)
        d += WALK_RAMP_DOWN_S * (x - _smoothstep_integral(x))
    return WALK_SPEED * d


def _lap_stop_time() -> float:
    """Stop time such that exactly one lap of the circle is walked."""
    lap = 2.0 * np.pi * WALK_RADIUS / WALK_SPEED  # s at full speed
    r_up = WALK_RAMP_UP[1] - WALK_RAMP_UP[0]
    # full-speed-equivalent time = r_up/2 + hold + ramp_down/2
    hold = lap - 0.5 * r_up - 0.5 * WALK_RAMP_DOWN_S
    return r_up + hold + WALK_RAMP_DOWN_S


T_WALK_END = _lap_stop_time()  # ~4.89 s


def _circle_walk(p: _Pose, t: float) -> tuple[tuple[float, float], float]:
    """Add the gait of the circle walk to p; returns (ground position xy, heading) to _place last."""
    a = _walk_amplitude(t, T_WALK_END)
    s = _walk_distance(t, T_WALK_END)
    alpha = -np.pi / 2 + s / WALK_RADIUS
    xy = (WALK_RADIUS * np.cos(alpha), WALK_RADIUS + WALK_RADIUS * np.sin(alpha))
    phase = 2.0 * np.pi * s / STRIDE_LENGTH
    _gait(p, phase, a)
    heading = s / WALK_RADIUS - 0.06 * a * np.sin(phase)
    return xy, heading


# ------------------------------------------------------------------ motions
def _wave_both(p: _Pose, t: float, w: float) -> None:
    """Both arms overhead, swaying sideways in anti-phase at 1.2 Hz (weight w)."""
    if w <= 0.0:
        return
    sway = 0.28 * np.sin(2 * np.pi * 1.0 * t)
    elbow = 0.35 + 0.25 * np.sin(2 * np.pi * 1.0 * t + 0.8)
    p.blend("l_upper_arm", [2.72 + sway, -0.15, 0.0], w)
    p.blend("r_upper_arm", [-2.72 + sway, -0.15, 0.0], w)
    p.blend("l_forearm", elbow, w)
    p.blend("r_forearm", 0.95 - elbow, w)
    p.blend("head", [0.0, -0.25, 0.0], w)


def _wave_left(p: _Pose, t: float, w: float) -> None:
    """Left hand waving overhead (elbow flexing at 1.5 Hz)."""
    if w <= 0.0:
        return
    p.blend("l_upper_arm", [2.5, -0.3, 0.0], w)
    p.blend("l_forearm", 0.7 + 0.35 * np.sin(2 * np.pi * 1.2 * t), w)


@lru_cache(maxsize=32)
def _ik_cached(body: BodyModel, side: str, target: tuple, preferred: tuple) -> np.ndarray:
    return arm_ik(body, side, np.array(target), np.array(preferred))


def _reach_across(p: _Pose, t: float, t0: float, t1: float) -> None:
    """Right hand reaches to the left side of the body and back within [t0, t1]."""
    w = window(t, t0, t1, 0.9)
    if w <= 0.0:
        return
    mid = 0.5 * (t0 + t1)
    dz = 0.04 * np.sin(2 * np.pi * (t - mid) / 1.2) * w
    q = _ik_cached(p.body, "r", (0.28, 0.26, 0.16), (0.6, -1.0, 0.0, 0.6))
    p.blend("r_upper_arm", q[:3], w)
    p.blend("r_forearm", q[3], w)
    p.blend("torso", [0.0, 0.12, 0.35], w)
    p.blend("head", [0.0, 0.15, 0.4], w)
    p["r_hand"] = p["r_hand"] + [0.0, dz * 3.0, 0.0]


def _hand_behind_back(p: _Pose, t: float, t0: float, t1: float) -> None:
    """Right hand moves behind the back, slides there from right to left, returns; within [t0, t1]."""
    w = window(t, t0, t1, 1.0)
    if w <= 0.0:
        return
    u = float(smoothstep((t - t0 - 0.8) / (t1 - t0 - 1.6)))
    pref = (-0.3, 0.5, 1.2, 1.6)
    qa = _ik_cached(p.body, "r", (-0.20, -0.05, 0.10), pref)
    qb = _ik_cached(p.body, "r", (-0.20, -0.01, 0.10), pref)
    q = (1.0 - u) * qa + u * qb
    p.blend("r_upper_arm", q[:3], w)
    p.blend("r_forearm", q[3], w)
    p.blend("r_hand", [0.0, -0.3, 0.0], w)


def _idle(p: _Pose, t: float, w: float = 1.0) -> None:
    """Tiny breathing / balance sway (amplitude w)."""
    s = lambda f: np.sin(2.0 * np.pi * f * t)  # noqa: E731
    p["torso"] = p["torso"] + w * np.array([0.015 * s(0.23), 0.01 * s(0.3), 0.02 * s(0.17)])
    p["head"] = p["head"] + w * np.array([0.0, 0.03 * s(0.21), 0.05 * s(0.13)])


def _default(body: BodyModel, t: float) -> np.ndarray:
    p = _Pose(body)
    _standing(p)
    xy, heading = _circle_walk(p, t)
    _idle(p, t, 1.0 - _walk_amplitude(t, T_WALK_END))
    _wave_both(p, t, window(t, T_WALK_END, 7.4, 0.6))
    _reach_across(p, t, 7.4, 10.0)
    _place(p, xy, heading)
    return p.theta


def _self_occlusion(body: BodyModel, t: float) -> np.ndarray:
    p = _Pose(body)
    _standing(p)
    xy, heading = _circle_walk(p, t)
    _idle(p, t, 1.0 - _walk_amplitude(t, T_WALK_END))
    _hand_behind_back(p, t, T_WALK_END, 7.2)
    _wave_left(p, t, window(t, 7.4, 10.0, 0.6))
    _place(p, xy, heading)
    return p.theta


LINE_START = np.array([0.32, -0.30, 0.02])   # torso frame, m (wrist)
LINE_END = np.array([0.32, 0.06, 0.20])
LINE_PERIOD_S = 2.0 * float(np.linalg.norm(LINE_END - LINE_START)) / 0.3
_ARM_FORWARD = (0.0, -1.1, 0.0, 0.9)


def line_target(t: float) -> np.ndarray:
    """(3,) torso-frame wrist target of the ``line`` motion at t (s): back and forth, cosine-timed."""
    u = 0.5 * (1.0 - np.cos(2.0 * np.pi * t / LINE_PERIOD_S))
    return LINE_START + u * (LINE_END - LINE_START)


CIRCLE_CENTRE = np.array([0.30, -0.12, 0.15])  # torso frame, m
CIRCLE_RADIUS = 0.15
CIRCLE_PERIOD_S = 3.0


def circle_target(t: float) -> np.ndarray:
    """(3,) torso-frame wrist target of the ``rotation`` motion: a circle in the y-z plane."""
    a = 2.0 * np.pi * t / CIRCLE_PERIOD_S
    return CIRCLE_CENTRE + CIRCLE_RADIUS * np.array([0.0, np.cos(a), np.sin(a)])


def _arm_target_motion(body: BodyModel, t: float, target: np.ndarray) -> np.ndarray:
    p = _Pose(body)
    _standing(p)
    q = arm_ik(body, "r", target, np.array(_ARM_FORWARD))
    p["r_upper_arm"] = q[:3]
    p["r_forearm"] = q[3]
    _place(p, (0.0, 0.0), 0.0)
    return p.theta


def _line(body: BodyModel, t: float) -> np.ndarray:
    return _arm_target_motion(body, t, line_target(t))


def _rotation(body: BodyModel, t: float) -> np.ndarray:
    return _arm_target_motion(body, t, circle_target(t))


DISTRACTOR_START = np.array([5.0, -0.9])
DISTRACTOR_VELOCITY = np.array([-1.0, 0.0])


def _distractor(body: BodyModel, t: float) -> np.ndarray:
    p = _Pose(body)
    _standing(p)
    # different arm carriage and gait phase from the target
    p["l_upper_arm"] = [0.16, 0.0, 0.0]
    p["r_upper_arm"] = [-0.16, 0.0, 0.0]
    s = float(np.linalg.norm(DISTRACTOR_VELOCITY)) * t
    phase = 2.0 * np.pi * s / 1.3 + 1.0
    _gait(p, phase, 1.0)
    heading = float(np.arctan2(DISTRACTOR_VELOCITY[1], DISTRACTOR_VELOCITY[0])) - 0.05 * np.sin(phase)
    _place(p, DISTRACTOR_START + DISTRACTOR_VELOCITY * t, heading)
    return p.theta


def _rest(body: BodyModel, t: float) -> np.ndarray:
    p = _Pose(body)
    _standing(p)
    _place(p, (0.0, 0.0), 0.0)
    return p.theta


_MOTIONS: dict[str, Callable[[BodyModel, float], np.ndarray]] = {
    "default": _default,
    "self_occlusion": _self_occlusion,
    "line": _line,
    "rotation": _rotation,
    "distractor": _distractor,
    "rest": _rest,
}


# ------------------------------------------------------------------ public API
def motion_names() -> list[str]:
    """Names accepted by pose_at."""
    return list(_MOTIONS)


@lru_cache(maxsize=1)
def _default_body() -> BodyModel:
    return load_body_model()


def pose_at(name: str, t_s: float, body: BodyModel | None = None) -> np.ndarray:
    """theta (n_dof,) of motion ``name`` at time t_s (s, >= 0), within the joint limits.

    body: the body model (default: load_body_model()); it must have the
    standard link names of config/body_model.yaml.
    """
    if name not in _MOTIONS:
        raise InputError(f"motion: unknown motion '{name}' (expected one of {', '.join(_MOTIONS)})")
    body = _default_body() if body is None else body
    theta = _MOTIONS[name](body, float(max(t_s, 0.0)))
    root = slice(0, 6)
    clipped = body.clip(theta)
    clipped[root] = theta[root]
    return clipped


def trajectory(name: str, times_s: np.ndarray, body: BodyModel | None = None) -> np.ndarray:
    """(T, n_dof) poses of motion ``name`` at times_s (T,) seconds."""
    return np.stack([pose_at(name, float(t), body) for t in np.asarray(times_s, float)])
