#!/usr/bin/env python3
"""Accuracy and speed of the offline closed loop (ALGORITHMS.md §1) on synthetic scenes.

For each scene (synthesised once with ``artrack.synth`` and cached as an mcap bag under
``--cache``, default ``/tmp/artrack_bench``) it runs ``artrack.pipeline.ClosedLoopPipeline``
for every estimator x feedback on/off and prints one table row each:

    scene  estimator  feedback  MPJPE mm  tracked %  fps  blobs_2d ms  skeleton_3d ms  projection ms

MPJPE is over the frames with an estimate (the tracker reports nothing while its background
model seeds and settles: "tracked %" is the share of frames with an estimate); fps is wall
clock over all frames; per-stage ms are means over all frames. Ends with one JSON line of
all rows. Deterministic (seeded scenes, no randomness in the tracker); wall-clock times
vary with the machine load.

Scenes: ``default`` (walk, waves), ``occlusion`` (``--occlusion``: the right hand goes
behind the back), ``distractor`` (``--distractor``: a second person walks past).

Run from the repository root, e.g.::

    .venv/bin/python bench/closed_loop.py --duration 6 --width 320 --height 240
    .venv/bin/python bench/closed_loop.py --scenes default --estimators baseline kinematic
"""

from __future__ import annotations

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "src" / "artrack_nodes"))

import argparse  # noqa: E402
import json  # noqa: E402
import time  # noqa: E402

import numpy as np  # noqa: E402

from artrack.bags import read_scene, write_scene_bag  # noqa: E402
from artrack.body_model import load_body_model  # noqa: E402
from artrack.pipeline import ClosedLoopPipeline, load_pipeline_config  # noqa: E402
from artrack.synth import SceneConfig, generate_scene, scene_cameras  # noqa: E402

SCENES = {"default": {}, "occlusion": {"occlusion": True}, "distractor": {"distractor": True}}


def scene_bag(name: str, args, body) -> Path:
    """The cached bag of scene ``name`` (synthesised on first use)."""
    cfg = SceneConfig(width=args.width, height=args.height, duration_s=args.duration, seed=args.seed,
                      **SCENES[name])
    path = Path(args.cache) / f"{name}_s{args.seed}_{args.width}x{args.height}_{args.duration:g}s.mcap"
    if not path.exists():
        path.parent.mkdir(parents=True, exist_ok=True)
        write_scene_bag(path, scene_cameras(cfg), generate_scene(cfg, body), joint_names=body.joint_names)
    return path


def run(path: Path, estimator: str, feedback: bool, body) -> dict:
    scene = read_scene(path)
    truth = {int(s): j for s, j in zip(scene.truth.stamps, scene.truth.joints, strict=True)}
    config = load_pipeline_config(estimator=estimator, feedback=feedback)
    pipe = ClosedLoopPipeline(body, scene.cameras, config)
    frames = list(scene.frames())  # decode before timing
    errs, stage = [], {}
    t0 = time.perf_counter()
    for stamp, images in frames:
        res = pipe.step(stamp, images)
        for k, v in res.timings_ms.items():
            stage.setdefault(k, []).append(v)
        j = res.estimate.joints
        if np.all(np.isfinite(j)) and int(stamp) in truth:
            errs.append(float(np.linalg.norm(j - truth[int(stamp)], axis=1).mean()))
    elapsed = time.perf_counter() - t0
    return {
        "mpjpe_mm": 1e3 * float(np.mean(errs)) if errs else float("nan"),
        "tracked": len(errs) / len(frames),
        "fps": len(frames) / elapsed,
        **{f"{k}_ms": float(np.mean(v)) for k, v in stage.items()},
    }


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scenes", nargs="+", default=list(SCENES), choices=list(SCENES))
    ap.add_argument("--estimators", nargs="+", default=["baseline", "kinematic", "dynamic"])
    ap.add_argument("--feedback", nargs="+", default=["on", "off"], choices=["on", "off"])
    ap.add_argument("--width", type=int, default=320)
    ap.add_argument("--height", type=int, default=240)
    ap.add_argument("--duration", type=float, default=6.0, help="s (the motions are 10 s long)")
    ap.add_argument("--seed", type=int, default=3)
    ap.add_argument("--cache", default="/tmp/artrack_bench")
    args = ap.parse_args()
    body = load_body_model()
    rows = []
    head = (f"{'scene':<11}{'estimator':<10}{'feedback':<9}{'MPJPE mm':>9}{'tracked %':>10}{'fps':>6}"
            f"{'blobs ms':>9}{'skel ms':>8}{'proj ms':>8}")
    print(head)
    for name in args.scenes:
        path = scene_bag(name, args, body)
        for est in args.estimators:
            for fb in args.feedback:
                r = run(path, est, fb == "on", body)
                rows.append({"scene": name, "estimator": est, "feedback": fb, **r})
                print(f"{name:<11}{est:<10}{fb:<9}{r['mpjpe_mm']:9.1f}{100 * r['tracked']:10.0f}{r['fps']:6.1f}"
                      f"{r.get('blobs_2d_ms', 0):9.1f}{r.get('skeleton_3d_ms', 0):8.1f}"
                      f"{r.get('projection_ms', 0):8.1f}", flush=True)
    print(json.dumps(rows))
    return 0


if __name__ == "__main__":
    sys.exit(main())
