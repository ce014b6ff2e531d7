#!/usr/bin/env python3
"""Accuracy and speed of the offline closed loop (ALGORITHMS.md §1) on synthetic scenes.

For each scene (synthesised once with ``artrack.synth`` and cached as an mcap bag under
``--cache``, default ``/tmp/artrack_bench``) it runs ``artrack.pipeline.ClosedLoopPipeline``
for every estimator x feedback on/off and prints one table row each:

    scene cams estimator feedback  MPJPE mm  limbs mm  tracked %  <claim>  fps  blobs ms  skel ms  proj ms

(limbs: elbows, wrists, knees, ankles; estimator ``baseline+edges``: the edge features fused.)

MPJPE is over the frames with an estimate and ground truth (the tracker reports nothing while
its background model seeds and settles: "tracked %" is the share of the frames with ground truth
that have an estimate); fps is wall
clock over all frames (decoding excluded); per-stage ms are means over all frames. The
``claim`` column is the figure the issue asks for on that scene (ALGORITHMS.md §1, the
paper's Table 1 and its occlusion / distractor claims), computed on the tracked frames:

* ``line``       — the right hand (wrist joint) moves on a straight line: RMS distance of the
  tracked wrist to its own best-fit 3-D line, mm (ground truth: 0);
* ``rotation``   — the right hand moves smoothly on a circle: RMS difference, degrees, between
  the tracked wrist's angle about its best-fit circle centre and that angle smoothed
  (Savitzky-Golay, 9 frames, cubic);
  Both also come "settled" (``line_rms_mm_settled``, ``rot_rms_deg_settled``): over the tracked
  frames from ``SETTLE_S`` (2 s) after the track starts, leaving out the start-up, where a
  hand found on the wrong side for a few frames (several hundred mm) outweighs the whole
  track's jitter; the paper's table is about the latter. The line also comes smoothed
  (``line_rms_mm_smoothed[_settled]``: the tracked wrist through a 9-frame Savitzky-Golay
  smoother first): the deviation that no filter of the track removes;
* ``occlusion``  — the right hand goes behind the back: the worst wrist error over the
  tracked frames, mm (the claim: no frame above 150 mm with feedback), and the number of
  frames above 150 mm; both also without the start-up frames (``*_settled``, see the phases);
* ``distractor`` — a second person walks past: frames in which the tracked head or a wrist
  is nearer to the second person's same joint than to the true one ("jumps"; the claim: 0),
  and those of them in which it is also within ``JUMP_NEAR_M`` of that joint
  (``jump_frames_near_other``: on the other person, not a part lost far from both); the same
  for the knees and ankles (``leg_jump_frames[_near_other]``, printed "legs"), which the claim
  leaves out but which the second person's look-alike trousers can take (stop 55);
* ``default``    — walk, waves, reach: the worst frame's MPJPE, mm.

Every run is also split into phases (JSON keys; with ``--seeds`` a "phases" line after each mean
row gives their means): ``startup_mm``, the MPJPE over the first ``STARTUP_FRAMES`` tracked frames
(the automatic start-up and the loop's convergence from it), ``settled_mm`` over the frames after
them, ``head_hands_rms_settled_mm`` likewise; on the scenes that start with the walk, ``walk_mm``
(after the start-up frames, until the walk stops at ``motion.T_WALK_END``, ~4.9 s) and
``after_walk_mm`` (from then on: both arms overhead in ``default``, the hand behind the back in
``occlusion``).

Head and hands are also scored where their blobs measure them (``head_hands_blob_centres_rms_mm``
and ``..._settled_mm``): the body model's blob centres of the head and the hands on the estimated
and on the true link poses (the scene's motion replayed), RMS over the three. The joint figure
(the head joint, the wrists) also carries what no blob observes: the head's pitch about the neck
and the hand's turn about the wrist (``blob_points``).

Ends with one JSON line of all rows. Deterministic (seeded scenes, no randomness in the
tracker); wall-clock times vary with the machine load. Run from the repository root::

    .venv/bin/python bench/closed_loop.py                      # all scenes, 4 cameras, 320x240, 6 s
    .venv/bin/python bench/closed_loop.py --scenes default --cameras 4 2 1 --estimators baseline
    .venv/bin/python bench/closed_loop.py --scenes default --width 640 --height 480 --feedback on
    .venv/bin/python bench/closed_loop.py --scenes default --estimators baseline --feedback on --seeds 1 2 3
    .venv/bin/python bench/closed_loop.py --scenes default --estimators baseline baseline+edges --feedback on \
        --seeds 1 2 3 4 5 6 --true-start 60      # blobs vs blobs + edges from a correct pose at frame 60

``--every 3`` gives the loop every third frame once it tracks (10 frames/s: what the free-running
graph manages on this machine), ``--refine-passes 2`` lets each such frame go round the loop up to
two more times (``PipelineConfig.refine_passes``)::

    .venv/bin/python bench/closed_loop.py --scenes default --estimators baseline --feedback on \
        --seeds 1 2 3 4 5 6 --every 3 --refine-passes 2

``--empty-seed 1.5`` renders the same scenes with the room shown empty for their first 1.5 s
(the person moves on unseen): the background then seeds without the ghost of the start
position, which measures how much of a scene's error that ghost causes. ``--body YAML`` tracks
with another body model (e.g. extra blobs, ``extends: body_model.yaml`` with ``link_overrides``)
on the same images, which are always rendered with the default body.

A change is judged on many seeds, paired: save the JSON line of a run before it and pass it
with ``--compare`` to the run after it (``artrack.evaluation.compare_paired``: per seed
before -> after, means, medians, seeds better / worse by more than 1 mm, sign-test and Wilcoxon p)::

    .venv/bin/python bench/closed_loop.py --scenes default --estimators baseline --feedback on \
        --seeds 1 2 3 4 5 6 7 8 9 10 | tail -1 > before.json
    # ... the change ...
    .venv/bin/python bench/closed_loop.py ... --compare before.json
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "src" / "artrack_nodes"))
# one BLAS thread, as scripts/env.sh sets for the graph: on 2 cores BLAS threads only spin
# (default scene 320x240: 8.2 -> 12.2 fps, CPU 116 -> 78 ms per frame)
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse  # noqa: E402
import json  # noqa: E402
import time  # noqa: E402

import numpy as np  # noqa: E402
from scipy.signal import savgol_filter  # noqa: E402

from artrack.bags import read_scene, write_scene_bag  # noqa: E402
from artrack.body_model import BodyModelError, limb_joint_indices, load_body_model  # noqa: E402
from artrack.evaluation import compare_paired  # noqa: E402
from artrack.motion import T_WALK_END, pose_at  # noqa: E402
from artrack.pipeline import ClosedLoopPipeline, load_pipeline_config  # noqa: E402
from artrack.progress import Progress  # noqa: E402
from artrack.synth import START_STAMP_NS, SceneConfig, generate_scene, scene_cameras  # noqa: E402

SCENES = {
    "default": {},
    # the person stands in one place: the room is shown empty first (1.5 s), as in the paper's
    # set-up, or the background model would learn the person
    "line": {"motion": "line", "empty_s": 1.5},
    "rotation": {"motion": "rotation", "empty_s": 1.5},
    "occlusion": {"occlusion": True},
    "distractor": {"distractor": True},
}
JUMP_NEAR_M = 0.25  # the distractor claim: a jump frame "on" the other person has a joint this near theirs
LEG_JOINTS = ("l_knee", "r_knee", "l_ankle", "r_ankle")  # the distractor's leg figures (not the claim)
HAND_LIMIT_M = 0.150  # the occlusion claim: no frame with a hand error above this
SETTLE_S = 2.0  # the paper's table "settled": scored from this long after the track starts, s
STARTUP_FRAMES = 10  # the phases' "start-up": a track's first tracked frames (score())
WALK_SCENES = ("default", "occlusion", "distractor")  # the scenes whose motion starts with the walk


def scene_bag(name: str, n_cameras: int, args, body) -> Path:
    """The cached bag of scene ``name`` (synthesised on first use)."""
    blackout = getattr(args, "empty_seed", 0.0)
    cfg = SceneConfig(n_cameras=n_cameras, width=args.width, height=args.height, duration_s=args.duration,
                      seed=args.seed, blackout=(0.0, blackout) if blackout > 0 else None, **SCENES[name])
    # (fewer than 4 cameras: the corners of the 4-camera ring since stop 27, "corners" in the name)
    rig = f"c{n_cameras}" + ("corners" if n_cameras < 4 else "")
    empty = f"_empty{blackout:g}s" if blackout > 0 else ""
    path = Path(args.cache) / f"{name}_{rig}_s{args.seed}_{args.width}x{args.height}_{args.duration:g}s{empty}.mcap"
    if not path.exists():
        path.parent.mkdir(parents=True, exist_ok=True)
        frames = Progress(generate_scene(cfg, body), total=cfg.n_frames, label=f"synth {path.name}")
        write_scene_bag(path, scene_cameras(cfg), frames, joint_names=body.joint_names)
    return path


# ------------------------------------------------------------------ the claims
def motion_time(name: str, stamps: list[int]) -> np.ndarray:
    """(T,) the scene's motion clock, s, at the frame stamps (synth: the motion starts after the
    scene's empty room, ``empty_s``)."""
    return (np.asarray(stamps, dtype=np.int64) - START_STAMP_NS) * 1e-9 - SCENES[name].get("empty_s", 0.0)


def line_rms_mm(points: np.ndarray) -> float:
    """RMS distance of (T, 3) points to their best-fit 3-D line (PCA), mm."""
    c = points - points.mean(axis=0)
    _, _, vt = np.linalg.svd(c, full_matrices=False)
    off = c - np.outer(c @ vt[0], vt[0])
    return 1e3 * float(np.sqrt(np.mean(np.sum(off**2, axis=1))))


def rotation_rms_deg(points: np.ndarray) -> float:
    """RMS of (angle - smoothed angle) of (T, 3) points about their best-fit circle's centre
    (plane by PCA, centre by a linear least-squares circle fit in that plane), degrees."""
    mean = points.mean(axis=0)
    _, _, vt = np.linalg.svd(points - mean, full_matrices=False)
    xy = (points - mean) @ vt[:2].T
    A = np.column_stack([2 * xy, np.ones(len(xy))])
    centre = np.linalg.lstsq(A, np.sum(xy**2, axis=1), rcond=None)[0][:2]
    angle = np.unwrap(np.arctan2(xy[:, 1] - centre[1], xy[:, 0] - centre[0]))
    window = min(9, len(angle) - (1 - len(angle) % 2))
    if window < 5:
        return float("nan")
    smooth = savgol_filter(angle, window, 3)
    return float(np.degrees(np.sqrt(np.mean((angle - smooth) ** 2))))


def claim(name: str, body, stamps: list[int], est: np.ndarray, truth: np.ndarray) -> dict:
    """The scene's claim figures (see the module docstring) from (T, J, 3) estimates and truth."""
    names = list(body.joint_names)
    wr, wl, head = names.index("r_wrist"), names.index("l_wrist"), names.index("head")
    if len(est) == 0:
        return {}
    settled = np.asarray(stamps) >= stamps[0] + int(SETTLE_S * 1e9)
    if name == "line":
        # the same after a non-causal smoother (Savitzky-Golay, 9 frames, quadratic): what smoothing the
        # track at its best leaves, the part of the deviation that is not frame-to-frame noise
        smooth = savgol_filter(est[:, wr], 9, 2, axis=0) if len(est) >= 9 else est[:, wr]
        return {"line_rms_mm": line_rms_mm(est[:, wr]), "truth_line_rms_mm": line_rms_mm(truth[:, wr]),
                "line_rms_mm_settled": line_rms_mm(est[settled, wr]) if settled.sum() > 2 else float("nan"),
                "line_rms_mm_smoothed": line_rms_mm(smooth),
                "line_rms_mm_smoothed_settled": line_rms_mm(smooth[settled]) if settled.sum() > 2 else float("nan")}
    if name == "rotation":
        return {"rot_rms_deg": rotation_rms_deg(est[:, wr]), "truth_rot_rms_deg": rotation_rms_deg(truth[:, wr]),
                "rot_rms_deg_settled": rotation_rms_deg(est[settled, wr]) if settled.sum() > 2 else float("nan")}
    if name == "occlusion":
        hand = np.linalg.norm(est[:, [wl, wr]] - truth[:, [wl, wr]], axis=2).max(axis=1)
        after = hand[STARTUP_FRAMES:]  # without the start-up frames (phases())
        return {"hand_max_mm": 1e3 * float(hand.max()), "frames_over_150mm": int(np.sum(hand > HAND_LIMIT_M)),
                "hand_max_settled_mm": 1e3 * float(after.max()) if after.size else float("nan"),
                "frames_over_150mm_settled": int(np.sum(after > HAND_LIMIT_M))}
    if name == "distractor":
        counts = dict.fromkeys(("jump_frames", "jump_frames_near_other", "leg_jump_frames",
                                "leg_jump_frames_near_other"), 0)
        legs = [names.index(n) for n in LEG_JOINTS]
        for k, t in enumerate(motion_time(name, stamps)):
            other = body.joint_positions(pose_at("distractor", float(t), body))
            for prefix, parts in (("", [head, wl, wr]), ("leg_", legs)):
                to_other = np.linalg.norm(est[k, parts] - other[parts], axis=1)
                nearer = to_other < np.linalg.norm(est[k, parts] - truth[k, parts], axis=1)
                counts[prefix + "jump_frames"] += int(nearer.any())
                counts[prefix + "jump_frames_near_other"] += int((nearer & (to_other < JUMP_NEAR_M)).any())
        return counts
    return {"worst_frame_mm": 1e3 * float(np.linalg.norm(est - truth, axis=2).mean(axis=1).max())}


def claim_text(r: dict) -> str:
    for key, fmt in (("line_rms_mm", "line {:.1f} mm"), ("rot_rms_deg", "rot {:.2f} deg"),
                     ("jump_frames", "jumps {}"), ("worst_frame_mm", "worst {:.0f} mm")):
        if key in r:
            text = fmt.format(r[key])
            return text + (f", legs {r['leg_jump_frames']}" if "leg_jump_frames" in r else "")
    if "hand_max_mm" in r:
        return f"hand max {r['hand_max_mm']:.0f} mm ({r['frames_over_150mm']} fr)"
    return "-"


BLOB_POINT_LINKS = ("head", "l_hand", "r_hand")  # head + hands as the blobs see them (blob_points())


def blob_points(name: str, body, stamp: int, links, true_joints) -> tuple[np.ndarray, np.ndarray] | None:
    """Head and hands where their blobs measure them: the body model's blob centres of
    :data:`BLOB_POINT_LINKS` on the estimated link poses (``links``, LinkEstimate list) and on the
    true ones (the scene's motion replayed, ``motion.pose_at``), as ((3, 3) estimated, (3, 3) true),
    m. The head + hands figure over joints (the head joint, the wrists) also carries what no
    blob observes: the head's pitch about the neck, the hand's turn about the wrist. None if the
    estimate lacks a link, or the replayed truth is not the scene's: its joints differ from the
    recorded ``true_joints`` (J, 3) by more than 1 mm (e.g. tracking with another body model)."""
    index = {n: i for i, n in enumerate(body.link_names)}
    by_name = {lk.name: lk for lk in links}
    if any(n not in by_name or body.links[index[n]].blob is None for n in BLOB_POINT_LINKS):
        return None
    motion = SceneConfig(**SCENES[name]).motion_name
    theta = pose_at(motion, float(motion_time(name, [stamp])[0]), body)
    T = body.forward_kinematics(theta)
    if np.abs(body.joint_positions(theta, T) - np.asarray(true_joints).reshape(-1, 3)).max() > 1e-3:
        return None
    est, tru = np.empty((3, 3)), np.empty((3, 3))
    for k, n in enumerate(BLOB_POINT_LINKS):
        c = body.links[index[n]].blob.centre
        est[k] = by_name[n].position + by_name[n].rotation @ c
        tru[k] = T[index[n], :3, 3] + T[index[n], :3, :3] @ c
    return est, tru


def score(name: str, body, stamps: list[int], est: list, tru: list, n_truth: int,
          points: list | None = None) -> dict:
    """Accuracy figures of one run: MPJPE, limbs, head+hands RMS (mm), tracked share and the
    scene's claim, from the per-frame (J, 3) estimates and truth of the tracked frames;
    ``points``: per tracked frame, blob_points()'s (estimated, true) head and hands or None."""
    n_j = len(body.joint_names)
    est_a, tru_a = np.asarray(est).reshape(-1, n_j, 3), np.asarray(tru).reshape(-1, n_j, 3)
    err = np.linalg.norm(est_a - tru_a, axis=2)  # (T, J) m
    names = list(body.joint_names)
    limbs = limb_joint_indices(names)
    head_hands = [names.index(n) for n in ("head", "l_wrist", "r_wrist")]
    nan = float("nan")
    centres = {}
    if points is not None and len(points) and all(p is not None for p in points):
        perr = np.array([np.linalg.norm(e - t, axis=1) for e, t in points])  # (T, 3) m
        rms = lambda e: 1e3 * float(np.sqrt(np.mean(e**2))) if e.size else nan  # noqa: E731
        centres = {"head_hands_blob_centres_rms_mm": rms(perr),
                   "head_hands_blob_centres_rms_settled_mm": rms(perr[STARTUP_FRAMES:])}
    return {
        "mpjpe_mm": 1e3 * float(err.mean()) if len(est) else nan,
        "limbs_mm": 1e3 * float(err[:, limbs].mean()) if len(est) else nan,
        "head_hands_rms_mm": 1e3 * float(np.sqrt(np.mean(err[:, head_hands] ** 2))) if len(est) else nan,
        "tracked": len(est) / max(n_truth, 1),
        **phases(name, stamps, err, head_hands),
        **centres,
        **claim(name, body, stamps, est_a, tru_a),
    }


def phases(name: str, stamps: list[int], err: np.ndarray, head_hands: list[int]) -> dict:
    """The run's phases (module docstring) from the (T, J) joint errors (m) of its tracked frames."""
    def mm(rows: np.ndarray, cols=slice(None), rms: bool = False) -> float:
        e = err[rows][:, cols]
        if not e.size:
            return float("nan")
        return 1e3 * float(np.sqrt(np.mean(e**2)) if rms else e.mean())

    n = len(stamps)
    start, rest = np.arange(n) < STARTUP_FRAMES, np.arange(n) >= STARTUP_FRAMES
    out = {"startup_mm": mm(start), "settled_mm": mm(rest), "head_hands_rms_settled_mm": mm(rest, head_hands, True)}
    if name in WALK_SCENES:
        t = motion_time(name, stamps)
        out["walk_mm"], out["after_walk_mm"] = mm(rest & (t < T_WALK_END)), mm(t >= T_WALK_END)
    return out


def phases_text(rows: list[dict]) -> str:
    """The phases' means over the seeds' rows, for the line after a mean row."""
    keys = [("startup_mm", "start-up {:.1f}"), ("walk_mm", "walk {:.1f}"), ("after_walk_mm", "after the walk {:.1f}"),
            ("settled_mm", "settled {:.1f}"), ("head_hands_rms_settled_mm", "head + hands RMS settled {:.1f}"),
            ("head_hands_blob_centres_rms_settled_mm", "at the blob centres {:.1f}")]
    parts = [fmt.format(float(np.nanmean([r[k] for r in rows]))) for k, fmt in keys if all(k in r for r in rows)]
    return f"phases, mean over the seeds (mm): {', '.join(parts)}"


def run(path: Path, name: str, estimator: str, feedback: bool, body, true_start: int | None = None,
        every: int = 1, refine_passes: int = 0, refine_min_interval_s: float = 0.05,
        startup_refine_frames: int | None = None) -> dict:
    """One closed-loop run; ``true_start``: restart from the true pose at that frame index and
    score only the frames from there on (the loop's drift from a correct start). ``every`` k > 1:
    once the loop tracks, it is given every k-th frame only (a loop or camera k times slower than
    the scene; the frames before, while the background seeds, all go in); the scores, the tracked
    share and the frame rate are over the frames given. ``refine_passes``, ``startup_refine_frames``:
    the pipeline's (``PipelineConfig``; None: its default)."""
    scene = read_scene(path)
    truth = {int(s): j for s, j in zip(scene.truth.stamps, scene.truth.joints, strict=True)}
    kind, _, extra = estimator.partition("+")  # 'baseline+edges': with the edge features fused
    config = load_pipeline_config(estimator=kind, feedback=feedback, edges=extra == "edges")
    config.refine_passes, config.refine_min_interval_s = refine_passes, refine_min_interval_s
    if startup_refine_frames is not None:
        config.startup_refine_frames = startup_refine_frames
    pipe = ClosedLoopPipeline(body, scene.cameras, config)
    frames = list(scene.frames())  # decode before timing
    if true_start is not None:
        if not 0 <= true_start < len(frames) or int(frames[true_start][0]) not in truth:
            raise SystemExit(f"closed_loop: --true-start {true_start}: {path} has no ground truth at that frame")
        truth = {s: j for s, j in truth.items() if s >= int(frames[true_start][0])}
    stamps, est, tru, links, stage, given = [], [], [], [], {}, []
    first = None  # index of the first tracked frame (``every``)
    t0 = time.perf_counter()
    for index, (stamp, images) in enumerate(frames):
        if every > 1 and first is not None and (index - first) % every:
            continue
        given.append(int(stamp))
        if index == true_start:
            pipe.restart(int(stamp), truth[int(stamp)])
        res = pipe.step(stamp, images)
        for k, v in res.timings_ms.items():
            stage.setdefault(k, []).append(v)
        j = res.estimate.joints
        if np.all(np.isfinite(j)) and first is None:
            first = index
        if np.all(np.isfinite(j)) and int(stamp) in truth:
            stamps.append(int(stamp))
            est.append(j)
            tru.append(truth[int(stamp)])
            links.append(res.estimate.links)
    elapsed = time.perf_counter() - t0
    points = [blob_points(name, body, s, lk, j) for s, lk, j in zip(stamps, links, tru, strict=True)]  # untimed
    return {
        **score(name, body, stamps, est, tru, sum(s in truth for s in given), points),
        "fps": len(given) / elapsed,
        # per-stage means over the frames given (a sub-stage absent in a frame counts as 0 there)
        **{f"{k}_ms": float(np.sum(v) / len(given)) for k, v in stage.items()},
    }


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scenes", nargs="+", default=list(SCENES), choices=list(SCENES))
    ap.add_argument("--estimators", nargs="+", default=["baseline", "baseline+edges", "kinematic", "dynamic"],
                    help="baseline | kinematic | dynamic, '+edges' to fuse the edge features")
    ap.add_argument("--feedback", nargs="+", default=["on", "off"], choices=["on", "off"])
    ap.add_argument("--cameras", nargs="+", type=int, default=[4], help="camera counts to run (e.g. 4 2 1)")
    ap.add_argument("--width", type=int, default=320)
    ap.add_argument("--height", type=int, default=240)
    ap.add_argument("--duration", type=float, default=6.0, help="s (the default motion is 10 s long)")
    ap.add_argument("--seed", type=int, default=3)
    ap.add_argument("--seeds", nargs="+", type=int, default=None,
                    help="several scene seeds: one row per seed plus a 'mean' row (MPJPE mean +- standard "
                         "deviation; the closed loop is chaotic, single-seed differences of ~50 mm are noise)")
    ap.add_argument("--true-start", type=int, default=None, metavar="FRAME",
                    help="restart every run from the true pose at this frame index and score the frames from "
                         "there on: the loop's drift from a correct start, without the automatic start-up")
    ap.add_argument("--every", type=int, default=1, metavar="K",
                    help="once tracking, give the loop every K-th frame only: a loop or camera K times slower "
                         "than the scene's 30 frames/s (default 1)")
    ap.add_argument("--refine-passes", type=int, default=0, metavar="K",
                    help="frames at least --refine-min-interval apart go round the loop up to K more times "
                         "(PipelineConfig.refine_passes; default 0)")
    ap.add_argument("--refine-min-interval", type=float, default=0.05, metavar="S")
    ap.add_argument("--startup-refine-frames", type=int, default=None, metavar="N",
                    help="the N frames after a track's first go round the loop more times "
                         "(PipelineConfig.startup_refine_frames; default: the pipeline's, 10; 0: off)")
    ap.add_argument("--cache", default="/tmp/artrack_bench")
    ap.add_argument("--empty-seed", type=float, default=0.0, metavar="S",
                    help="diagnosis: every camera shows the empty room for the first S seconds (the person moves "
                         "on unseen; ground truth kept), so the background seeds without a ghost of the start "
                         "position (synth.SceneConfig.blackout; default 0: off)")
    ap.add_argument("--body", metavar="YAML", default=None,
                    help="the tracker's body model (default config/body_model.yaml); the scenes are always "
                         "rendered with the default body, so a model that differs in its blobs is scored "
                         "against the same images")
    ap.add_argument("--compare", metavar="JSON", default=None,
                    help="the JSON line (last line) of an earlier run: per-seed MPJPE before -> after, paired")
    args = ap.parse_args()
    if not args.empty_seed >= 0:
        ap.error(f"--empty-seed must be >= 0 seconds, got {args.empty_seed}")
    if args.every < 1 or args.refine_passes < 0 or not args.refine_min_interval >= 0 or (
            args.startup_refine_frames is not None and args.startup_refine_frames < 0):
        ap.error("--every must be >= 1, --refine-passes, --refine-min-interval and --startup-refine-frames >= 0")
    before = load_rows(args.compare) if args.compare else None
    seeds = args.seeds or [args.seed]
    body = load_body_model()
    try:
        track_body = load_body_model(args.body) if args.body else body
    except (BodyModelError, OSError) as exc:
        ap.error(f"--body: {exc}")
    if list(track_body.joint_names) != list(body.joint_names):
        ap.error(f"--body {args.body}: its joints differ from the default body's, so it cannot be scored here")
    rows = []
    head = (f"{'scene':<11}{'cams':>4} {'estimator':<15}{'feedback':<9}{'MPJPE mm':>9}{'limbs mm':>9}{'tracked %':>10}"
            f"  {'claim':<24}{'fps':>6}{'blobs ms':>9}{'edges ms':>9}{'skel ms':>8}{'proj ms':>8}")
    print(head)
    for name in args.scenes:
        for n_cam in args.cameras:
            paths = {sd: scene_bag(name, n_cam, argparse.Namespace(**{**vars(args), "seed": sd}), body)
                     for sd in seeds}
            for est in args.estimators:
                for fb in args.feedback:
                    mpjpe, limbs = [], []
                    for sd, path in paths.items():
                        r = run(path, name, est, fb == "on", track_body, args.true_start, args.every,
                                args.refine_passes, args.refine_min_interval, args.startup_refine_frames)
                        rows.append({"scene": name, "cameras": n_cam, "estimator": est, "feedback": fb,
                                     "seed": sd, "every": args.every, "refine_passes": args.refine_passes,
                                     "startup_refine_frames": args.startup_refine_frames, **r})
                        mpjpe.append(r["mpjpe_mm"])
                        limbs.append(r["limbs_mm"])
                        tag = "" if len(seeds) == 1 else f" s{sd}"
                        print(f"{name:<11}{n_cam:>4} {est + tag:<15}{fb:<9}{r['mpjpe_mm']:9.1f}{r['limbs_mm']:9.1f}"
                              f"{100 * r['tracked']:10.0f}"
                              f"  {claim_text(r):<24}{r['fps']:6.1f}{r.get('blobs_2d_ms', 0):9.1f}"
                              f"{r.get('edges_ms', 0):9.1f}"
                              f"{r.get('skeleton_3d_ms', 0):8.1f}{r.get('projection_ms', 0):8.1f}", flush=True)
                    if len(seeds) > 1:
                        m, sdv, lm = float(np.nanmean(mpjpe)), float(np.nanstd(mpjpe)), float(np.nanmean(limbs))
                        rows.append({"scene": name, "cameras": n_cam, "estimator": est, "feedback": fb,
                                     "seed": "mean", "mpjpe_mm": m, "mpjpe_mm_sd": sdv, "limbs_mm": lm})
                        print(f"{name:<11}{n_cam:>4} {est + ' mean':<15}{fb:<9}{m:9.1f}{lm:9.1f}  (MPJPE +- {sdv:.1f} "
                              f"mm over {len(seeds)} seeds)", flush=True)
                        group = [r for r in rows[-len(seeds) - 1:-1] if np.isfinite(r["mpjpe_mm"])]
                        if group:
                            print(f"{'':<40}{phases_text(group)}", flush=True)
    if before is not None:
        print_comparison(args.compare, before, rows)
    print(json.dumps(rows))
    return 0


def _group(row: dict) -> tuple:
    return row["scene"], row["cameras"], row["estimator"], row["feedback"]


def load_rows(path: str) -> list[dict]:
    """The rows of an earlier run's JSON line (this script's last output line); SystemExit with one
    line naming the file for anything else."""
    try:
        with open(path, encoding="utf-8") as f:
            lines = [ln for ln in f.read().splitlines() if ln.strip()]
        rows = json.loads(lines[-1]) if lines else None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise SystemExit(f"closed_loop: --compare {path}: {exc}") from None
    if not isinstance(rows, list) or not all(isinstance(r, dict) and {"scene", "cameras", "estimator", "feedback",
                                                                       "seed", "mpjpe_mm"} <= set(r) for r in rows):
        raise SystemExit(f"closed_loop: --compare {path}: not the JSON line of a closed_loop.py run")
    return rows


def print_comparison(path: str, before: list[dict], after: list[dict]) -> None:
    """Per group (scene, cameras, estimator, feedback) of this run with paired seeds in ``before``:
    MPJPE per seed before -> after and the paired summary (``compare_paired``)."""
    print(f"\ncompared with {path} (MPJPE mm per seed, before -> after)")
    for group in dict.fromkeys(_group(r) for r in after):
        b = {r["seed"]: r["mpjpe_mm"] for r in before if _group(r) == group and r["seed"] != "mean"}
        a = {r["seed"]: r["mpjpe_mm"] for r in after if _group(r) == group and r["seed"] != "mean"}
        if not any(k in b for k in a):
            print(f"{' '.join(map(str, group))}: no seed of this run in {path}")
            continue
        c = compare_paired(b, a)
        pairs = "  ".join(f"s{k} {b[k]:.1f} -> {a[k]:.1f}" for k in a if k in b)
        print(f"{' '.join(map(str, group))}: {pairs}")
        print(f"  mean {c['mean_before']:.1f} -> {c['mean_after']:.1f}, median {c['median_before']:.1f} -> "
              f"{c['median_after']:.1f}; {c['better']} better, {c['worse']} worse, {c['ties']} within 1 mm of "
              f"{c['n']}; sign test p = {c['sign_test_p']:.2f}, Wilcoxon signed-rank p = {c['wilcoxon_p']:.3f}")


if __name__ == "__main__":
    sys.exit(main())
