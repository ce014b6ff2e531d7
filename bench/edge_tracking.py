#!/usr/bin/env python3
"""Edge-based articulated tracking alone (ALGORITHMS.md §2) on a synthetic scene with ground truth.

The scene (``artrack.synth.generate_scene``: the ``default`` motion — walking on a circle —,
4 ring cameras, Gaussian pixel noise) is rendered once per resolution. The tracker
(``artrack.edge_tracker.EdgeTracker``) starts from the *true* first-frame pose — from which it also
learns each quadric's colour for edge polarity and the outline offset (``learn_appearance``) — and then
runs on its own, each frame's prediction being the previous frame's estimate (no motion model, no other
cue). It is run with all 4 views and with 1 view (cam01). For each run the table shows MPJPE
(mm, over all frames after the first, all 15 output joints and the limb joints
elbows/knees/wrists/ankles), the last-second MPJPE (drift), the worst frame, "held" (seconds until
the first frame with MPJPE > 100 mm), the joints' mean reprojection error in the tracked views
("2-D px", over the run and over its first second: a single view keeps the image fit long after
the depth along its rays has drifted), the frame rate of ``step`` (wall clock
on this machine, images already in memory), the process CPU time of ``step`` (ms per frame: less
sensitive than the wall clock to other work on a shared machine) and the mean per-stage wall-clock
times (ms per frame).

Ends with one JSON line (one entry per run). Progress goes to stderr.

Run from the repository root::

    .venv/bin/python bench/edge_tracking.py                          # 3 s, 320x240
    .venv/bin/python bench/edge_tracking.py --sizes 320x240 640x480 --duration 4
"""

from __future__ import annotations

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "src" / "artrack_nodes"))

import argparse  # noqa: E402
import json  # noqa: E402
import time  # noqa: E402

import numpy as np  # noqa: E402

from artrack.body_model import limb_joint_indices, load_body_model  # noqa: E402
from artrack.edge_tracker import STAGES, EdgeTracker, EdgeTrackerConfig  # noqa: E402
from artrack.evaluation import mpjpe  # noqa: E402
from artrack.synth import SceneConfig, generate_scene, scene_cameras  # noqa: E402

LOST_MM = 100.0  # a frame with MPJPE above this counts as lost; "held" = time until the first such frame


def render(size: tuple[int, int], duration: float, seed: int, fps: float):
    cfg = SceneConfig(n_cameras=4, width=size[0], height=size[1], duration_s=duration, seed=seed, fps=fps)
    body = load_body_model()
    cams = scene_cameras(cfg)
    frames = []
    for f in generate_scene(cfg, body, cams):
        frames.append(f)
        if f.index % 30 == 0:
            print(f"  rendering {size[0]}x{size[1]}: frame {f.index + 1}/{cfg.n_frames}", file=sys.stderr, flush=True)
    return body, cams, frames


def run(body, cams, frames, views: int, config: EdgeTrackerConfig, label: str) -> dict:
    use = cams[:views]
    tracker = EdgeTracker(body, use, config)
    E = body.forward_kinematics(frames[0].theta)  # correct first-frame pose
    if config.polarity:  # appearance and outline offset from the first frame at its (correct) pose
        tracker.learn_appearance({c.name: frames[0].images[c.name] for c in use}, E)
    pred = [body.transform_points(E, body.joint_links, body.joint_points)]
    stage = dict.fromkeys(STAGES, 0.0)
    t_total = 0.0
    cpu_total = 0.0
    for k, f in enumerate(frames[1:], start=1):
        t0, c0 = time.perf_counter(), time.process_time()
        E, _, _, tm = tracker.step({c.name: f.images[c.name] for c in use}, E)
        t_total += time.perf_counter() - t0
        cpu_total += time.process_time() - c0
        for s in STAGES:
            stage[s] += tm[s]
        pred.append(body.transform_points(E, body.joint_links, body.joint_points))
        if k % 15 == 0 or k == len(frames) - 1:
            err = np.linalg.norm(pred[-1] - f.joints, axis=1).mean() * 1e3
            print(f"  {label}: frame {k}/{len(frames) - 1}  current error {err:.0f} mm", file=sys.stderr, flush=True)
    pred = np.array(pred[1:])
    truth = np.array([f.joints for f in frames[1:]])
    overall, per_joint, per_frame = mpjpe(pred, truth)
    # the same estimate in the images it was tracked in: mean joint reprojection error, px
    reprojection = np.mean([np.linalg.norm(c.project(pred.reshape(-1, 3))[0] - c.project(truth.reshape(-1, 3))[0],
                                           axis=1).reshape(len(pred), -1).mean(axis=1) for c in use], axis=0)
    limb = limb_joint_indices(body.joint_names)
    n = len(frames) - 1
    fps_in = 1.0 / max(frames[1].stamp_ns - frames[0].stamp_ns, 1) * 1e9
    last = per_frame[-int(round(fps_in)):]
    return {
        "views": views,
        "mpjpe_mm": overall,
        "limb_mpjpe_mm": float(np.mean(per_joint[limb])),
        "last_second_mpjpe_mm": float(np.mean(last)),
        "max_frame_mpjpe_mm": float(np.max(per_frame)),
        "held_s": float(np.argmax(np.r_[per_frame, np.inf] > LOST_MM) / fps_in),
        "reprojection_px": float(reprojection.mean()),
        "reprojection_first_s_px": float(reprojection[: int(round(fps_in))].mean()),
        "fps": n / t_total,
        "cpu_ms": cpu_total / n * 1e3,
        "stage_ms": {s: stage[s] / n for s in STAGES},
        "frames": n,
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sizes", nargs="+", default=["320x240"], help="image sizes WxH (default 320x240)")
    ap.add_argument("--views", nargs="+", type=int, default=[4, 1], help="numbers of views (default 4 1)")
    ap.add_argument("--duration", type=float, default=3.0, help="scene length, s (default 3)")
    ap.add_argument("--fps", type=float, default=30.0, help="scene frame rate (default 30)")
    ap.add_argument("--seed", type=int, default=3, help="scene seed (default 3)")
    ap.add_argument("--iterations", type=int, default=None, help="override EdgeTrackerConfig.iterations")
    ap.add_argument("--config", default=None, help="edge_features.yaml to read (default: built-in defaults)")
    args = ap.parse_args()
    config = EdgeTrackerConfig.from_yaml(args.config) if args.config else EdgeTrackerConfig()
    if args.iterations is not None:
        config.iterations = args.iterations
    results = []
    for size_s in args.sizes:
        w, h = (int(x) for x in size_s.lower().split("x"))
        body, cams, frames = render((w, h), args.duration, args.seed, args.fps)
        for v in args.views:
            r = run(body, cams, frames, v, config, f"{v} view(s) {w}x{h}")
            r["resolution"] = f"{w}x{h}"
            results.append(r)
    print(f"edge tracking alone from the true first pose: seed {args.seed}, {args.duration:g} s at {args.fps:g} fps, "
          f"iterations {config.iterations}, select {config.select}, colour {config.colour}")
    head = (f"{'views':>5} {'res':>8} {'MPJPE mm':>9} {'limbs mm':>9} {'last 1s':>8} {'max':>7} "
            f"{'held s':>6} {'2-D px':>6} {'1st s':>6} {'fps':>6} {'cpu ms':>6} | "
            + " ".join(f"{s[:6]:>7}" for s in STAGES) + "  (ms/frame)")
    print(head)
    print("-" * len(head))
    for r in results:
        print(f"{r['views']:>5} {r['resolution']:>8} {r['mpjpe_mm']:>9.1f} {r['limb_mpjpe_mm']:>9.1f} "
              f"{r['last_second_mpjpe_mm']:>8.1f} {r['max_frame_mpjpe_mm']:>7.1f} "
              f"{r['held_s']:>6.2f} {r['reprojection_px']:>6.1f} {r['reprojection_first_s_px']:>6.1f} "
              f"{r['fps']:>6.1f} {r['cpu_ms']:>6.1f} | "
              + " ".join(f"{r['stage_ms'][s]:>7.1f}" for s in STAGES))
    print(json.dumps({"edge_tracking": results, "seed": args.seed, "duration_s": args.duration,
                      "config": config.as_dict()}))


if __name__ == "__main__":
    main()
