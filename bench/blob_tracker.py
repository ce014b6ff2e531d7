#!/usr/bin/env python3
"""The blob-tracker issue's acceptance figures (ALGORITHMS.md §1), all in one run.

Runs the offline closed loop (``artrack.pipeline.ClosedLoopPipeline``, the same code as the
live graph) on the synthetic scenes of ``bench/closed_loop.py`` (cached bags, 4 cameras,
320x240, 6 s, seed 3 unless told otherwise) and prints one table per claim:

1. accuracy on the default scene: MPJPE over the 15 joints and the RMS 3-D error of head and
   wrists, for the raw tracker (the ``baseline`` per-frame body fit) and the skeleton
   (``--skeleton``, default the Kalman filters + virtual-work solver, ``kinematic``) — and the
   same two estimators fed *perfect* 2-D blobs (the true blob Gaussians projected, occluded
   ones left out, 1 px noise: "oracle blobs"), which separates the error of the 2-D blob
   tracker from that of the 3-D estimator; and fed the blob statistics of the renderer's *true
   label images* (each blob's pixels: its link's pixels nearest its colour class, "oracle
   labels"): what a perfect pixel labelling would give, body-model blob centres included;
2. the paper's table: RMS of the hand to its best-fit line / of its angle to the smoothed
   angle, skeleton / raw tracker (the claim: ratio <= 0.7), over the whole track and settled
   (from 2 s after the track starts: without the start-up's wrong hands);
3. self-occlusion: worst hand error with feedback on and off (claim: <= 150 mm with);
4. distractor: frames where head or a hand is nearer the other person (claim: 0);
5. camera count: 4, 2 and 1 cameras (one and two: config/skeleton.yaml's `few_cameras` settings);
6. throughput: frames per second at 320x240 and 640x480 and milliseconds per stage
   (background, MAP classification and blob statistics summed over the 4 cameras;
   triangulation, outlier fit, Kalman filters, constraint solver, the rest of the pose
   update; projection of the priors). Wall clock: varies with machine load.

Section 1 also splits the tracked runs into phases (``bench/closed_loop.py``: the first 10 tracked
frames of the automatic start-up, the walk, the arms overhead after it), and section 3 gives the
self-occlusion figures without those start-up frames as well.

Ends with one JSON line: mpjpe_mm, head_hands_rms_mm, line_ratio, rotation_ratio (and their
``_settled`` versions), occlusion_max_hand_err_mm_feedback,
occlusion_max_hand_err_mm_no_feedback, fps_320x240, fps_640x480 (all for the ``--skeleton``
estimator, feedback on), plus the occlusion frame counts and the phases' figures (``*_settled``:
without the start-up frames), head + hands at their blob centres
(``head_hands_blob_centres_rms_mm``, ``bench/closed_loop.py``), the raw tracker's, the raw
tracker's with the edge features fused (``baseline+edges``, section 1) and the oracle's figures
for comparison. Run from the repository root (about 15 min on 2 cores)::

    .venv/bin/python bench/blob_tracker.py
    .venv/bin/python bench/blob_tracker.py --skeleton baseline     # the graph's default estimator
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "src" / "artrack_nodes"))
# one BLAS thread, as scripts/env.sh sets for the graph: on 2 cores BLAS threads only spin
# (default scene 320x240: 8.2 -> 12.2 fps, CPU 116 -> 78 ms per frame)
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
sys.path.insert(0, str(Path(__file__).resolve().parent))

import argparse  # noqa: E402
import json  # noqa: E402
import time  # noqa: E402

import closed_loop as cl  # noqa: E402  (bench/closed_loop.py: scenes, runs, claims)
import numpy as np  # noqa: E402

from artrack.bags import read_scene  # noqa: E402
from artrack.body_model import load_body_model  # noqa: E402
from artrack.motion import pose_at  # noqa: E402
from artrack.pipeline import load_pipeline_config  # noqa: E402
from artrack.projection import project_priors  # noqa: E402
from artrack.skeleton import make_estimator  # noqa: E402
from artrack.synth import START_STAMP_NS, Renderer, SceneConfig, frame_stamp_ns  # noqa: E402
from artrack.types import (
    VISIBLE,  # noqa: E402
    Blob2D,  # noqa: E402
)

STAGES = [  # (timing key, column) in pipeline order
    ("blobs_2d.background", "bg"), ("blobs_2d.classification", "classify"), ("blobs_2d.statistics", "stats"),
    ("skeleton_3d.triangulation", "3-D"), ("skeleton_3d.outlier_fit", "outl.fit"),
    ("skeleton_3d.kalman", "kalman"), ("skeleton_3d.constraints", "constr."), ("skeleton_3d.pose", "pose"),
    ("skeleton_3d.prediction", "predict"), ("projection", "proj"),
]


def oracle_blobs(body, cameras, theta, stamp_ns: int, rng, sigma_px: float) -> dict[str, list[Blob2D]]:
    """Perfect 2-D blobs: the true blob Gaussians projected into every camera (first order, as the
    priors), occluded or off-image ones left out, the means perturbed by ``sigma_px`` noise. Pixel
    counts: the area of the uniform ellipse with that covariance, 4π √det (so they shrink with
    distance as real blobs do; the face check reads facing from them, and the model's Gaussians
    look alike from every side)."""
    p0, p1, radius, link, _ = body.capsules(theta)
    occluders = [(body.link_names[k], a, b, r) for a, b, r, k in zip(p0, p1, radius, link, strict=True)]
    projected = project_priors(body.blobs3d(theta), cameras, stamp_ns, occluders=occluders)
    return {cam: [Blob2D(p.label, p.mean + sigma_px * rng.standard_normal(2), p.cov,
                         pixel_count=max(1, round(4.0 * np.pi * float(np.sqrt(max(np.linalg.det(p.cov), 0.0))))))
                  for p in priors if p.visibility == VISIBLE]
            for cam, priors in projected.items()}


def label_oracle_run(name: str, args, estimator: str, body) -> dict:
    """The 3-D estimator alone on the blob statistics (pixel mean and covariance, as
    ``BlobTracker2D`` computes them) of the renderer's true label images of scene ``name``: a
    blob's pixels are its link's pixels whose colour is nearest the blob's colour class in the
    person's palette (the head's skin without its hair). No background, no feedback."""
    cfg = SceneConfig(n_cameras=4, width=args.width, height=args.height, duration_s=args.duration,
                      seed=args.seed, **cl.SCENES[name])
    scene = read_scene(cl.scene_bag(name, 4, args, body))
    renderer = Renderer(body, scene.cameras, cfg.seed)
    est = make_estimator(estimator, body, scene.cameras, load_pipeline_config(estimator=estimator).skeleton)
    stamps, out, tru = [], [], []
    t0 = time.perf_counter()
    for i in range(cfg.n_frames):
        t = i / cfg.fps - cfg.empty_s
        if t < 0:  # the room is still empty
            continue
        theta = pose_at(cfg.motion_name, t, body)
        images, labels = renderer.render(theta, (), cfg.noise_sigma, frame_index=i, labels=True)
        blobs = {}
        for cam, img, lab in zip(scene.cameras, images, labels, strict=True):
            blobs[cam.name] = []
            for label, (xs, ys) in renderer.blob_pixels(img, lab).items():
                if len(xs) >= 10:
                    pts = np.column_stack([xs, ys]).astype(float)
                    d = pts - pts.mean(axis=0)
                    blobs[cam.name].append(Blob2D(label, pts.mean(axis=0), d.T @ d / len(pts), pixel_count=len(xs)))
        e = est.update(frame_stamp_ns(i, cfg.fps), blobs)
        if np.all(np.isfinite(e.joints)):
            stamps.append(frame_stamp_ns(i, cfg.fps))
            out.append(e.joints)
            tru.append(body.joint_positions(theta))
    r = cl.score(name, body, stamps, out, tru, cfg.n_frames)
    r["fps"] = cfg.n_frames / (time.perf_counter() - t0)
    return r


def oracle_run(path: Path, name: str, estimator: str, body, sigma_px: float = 1.0) -> dict:
    """The 3-D estimator alone on oracle blobs of scene ``name`` (no images, no feedback)."""
    scene = read_scene(path)
    cfg = SceneConfig(**cl.SCENES[name])
    est = make_estimator(estimator, body, scene.cameras, load_pipeline_config(estimator=estimator).skeleton)
    rng = np.random.default_rng(0)
    stamps, out, tru = [], [], []
    t0 = time.perf_counter()
    for s, joints in zip(scene.truth.stamps, scene.truth.joints, strict=True):
        theta = pose_at(cfg.motion_name, (int(s) - START_STAMP_NS) * 1e-9 - cfg.empty_s, body)
        if not np.allclose(body.joint_positions(theta), joints, atol=1e-6):
            raise SystemExit(f"{path}: ground truth does not match motion '{cfg.motion_name}' (stale cache?)")
        e = est.update(int(s), oracle_blobs(body, scene.cameras, theta, int(s), rng, sigma_px))
        if np.all(np.isfinite(e.joints)):
            stamps.append(int(s))
            out.append(e.joints)
            tru.append(joints)
    r = cl.score(name, body, stamps, out, tru, len(scene.truth.stamps))
    r["fps"] = len(scene.truth.stamps) / (time.perf_counter() - t0)
    return r


def fmt(x: float, spec: str = "9.1f") -> str:
    return format(x, spec) if np.isfinite(x) else format("-", ">" + spec.split(".")[0])


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--skeleton", default="kinematic", choices=["baseline", "kinematic", "dynamic"],
                    help="the estimator the claims are made for (the raw tracker is always 'baseline')")
    ap.add_argument("--width", type=int, default=320)
    ap.add_argument("--height", type=int, default=240)
    ap.add_argument("--duration", type=float, default=6.0, help="s per scene")
    ap.add_argument("--seed", type=int, default=3)
    ap.add_argument("--cache", default="/tmp/artrack_bench")
    ap.add_argument("--no-large", action="store_true", help="skip the 640x480 throughput run")
    args = ap.parse_args()
    body = load_body_model()
    sk, raw = args.skeleton, "baseline"
    estimators = [raw] if sk == raw else [raw, sk]
    bag = lambda name, cams=4: cl.scene_bag(name, cams, args, body)  # noqa: E731
    res: dict = {}

    print(f"1. Accuracy, default scene ({args.width}x{args.height}, 4 cameras, feedback on)")
    print(f"{'estimator':<11}{'blobs':<9}{'MPJPE mm':>9}{'head+hands RMS mm':>19}{'limbs mm':>9}{'tracked %':>10}")
    for e in estimators:
        for src, r in (("tracked", cl.run(bag("default"), "default", e, True, body)),
                       ("oracle", oracle_run(bag("default"), "default", e, body)),
                       ("labels", label_oracle_run("default", args, e, body))):
            res[("default", e, src)] = r
            print(f"{e:<11}{src:<9}{fmt(r['mpjpe_mm'])}{fmt(r['head_hands_rms_mm'], '19.1f')}"
                  f"{fmt(r['limbs_mm'])}{100 * r['tracked']:10.0f}", flush=True)
    print(f"phases of the tracked runs (bench/closed_loop.py: the first {cl.STARTUP_FRAMES} tracked frames, then the "
          "walk, then the arms overhead; mm)")
    print(f"{'estimator':<11}{'start-up':>9}{'walk':>7}{'after walk':>11}{'settled':>9}{'head+hands RMS settled':>24}"
          f"{'at blob centres: all':>22}{'settled':>9}")
    for e in estimators:
        r = res[("default", e, "tracked")]
        print(f"{e:<11}{fmt(r['startup_mm'])}{fmt(r['walk_mm'], '7.1f')}{fmt(r['after_walk_mm'], '11.1f')}"
              f"{fmt(r['settled_mm'])}{fmt(r['head_hands_rms_settled_mm'], '24.1f')}"
              f"{fmt(r.get('head_hands_blob_centres_rms_mm', float('nan')), '22.1f')}"
              f"{fmt(r.get('head_hands_blob_centres_rms_settled_mm', float('nan')))}", flush=True)
    print("(head + hands at the blob centres: the head's and hands' blob centres on the estimated and the true link "
          "poses; the joint figure, the head joint and the wrists, also carries the head's pitch and the hand's turn "
          "that no blob observes)")
    # the raw tracker with the edge features fused (ALGORITHMS.md §2 "Fusion"; issue 4's blobs + edges)
    r = res[("default", "baseline+edges", "tracked")] = cl.run(bag("default"), "default", "baseline+edges", True, body)
    print(f"{'baseline+edges':<20}{fmt(r['mpjpe_mm'])}{fmt(r['head_hands_rms_mm'], '19.1f')}"
          f"{fmt(r['limbs_mm'])}{100 * r['tracked']:10.0f}  {r['fps']:.1f} frames/s", flush=True)

    print("\n2. The paper's table (right hand; skeleton / raw tracker, claim <= 0.7; settled: from "
          f"{cl.SETTLE_S:g} s after the track starts)")
    print(f"{'scene':<10}{'truth':>8}{'raw':>9}{'skeleton':>10}{'ratio':>7}{'settled: raw':>14}{'skeleton':>10}"
          f"{'ratio':>7}")
    ratios = {}
    for name, key, unit in (("line", "line_rms_mm", "mm"), ("rotation", "rot_rms_deg", "deg")):
        rr = {e: cl.run(bag(name), name, e, True, body) for e in estimators}
        truth_key, settled = "truth_" + key, key + "_settled"
        ratios[name] = rr[sk][key] / rr[raw][key]
        ratios[name + "_settled"] = rr[sk][settled] / rr[raw][settled]
        print(f"{name:<10}{rr[raw][truth_key]:8.2f}{rr[raw][key]:9.2f}{rr[sk][key]:10.2f}{ratios[name]:7.2f}"
              f"{rr[raw][settled]:14.2f}{rr[sk][settled]:10.2f}{ratios[name + '_settled']:7.2f}  {unit}", flush=True)
        if name == "line":  # what smoothing alone can reach: the raw track through a non-causal smoother
            sm = rr[raw]["line_rms_mm_smoothed_settled"] / rr[raw][settled]
            ratios["line_smoothed_raw_settled"] = sm
            print(f"{'':<10}the raw tracker's settled line through a 9-frame Savitzky-Golay smoother: "
                  f"{rr[raw]['line_rms_mm_smoothed_settled']:.2f} mm, ratio {sm:.2f}", flush=True)
            # the slow part of the error, which no filter of the same observations removes: the
            # skeleton's track through the same smoother, against the raw tracker's settled RMS
            slow = rr[sk]["line_rms_mm_smoothed_settled"] / rr[raw][settled]
            ratios["line_smoothed_skeleton_settled"] = slow
            print(f"{'':<10}the skeleton's, the same: {rr[sk]['line_rms_mm_smoothed_settled']:.2f} mm, ratio "
                  f"{slow:.2f} (the slow error both share: about the best ratio a causal filter could reach)",
                  flush=True)

    print("\n3. Self-occlusion (worst wrist error over the tracked frames; claim <= 150 mm with feedback)")
    print(f"{'estimator':<11}{'feedback':<9}{'hand max mm':>12}{'frames > 150 mm':>16}{'MPJPE mm':>9}"
          f"   after the first {cl.STARTUP_FRAMES} tracked frames: {'hand max mm':>11}{'frames > 150 mm':>16}")
    for e in estimators:
        for fb in (True, False):
            r = res[("occlusion", e, fb)] = cl.run(bag("occlusion"), "occlusion", e, fb, body)
            print(f"{e:<11}{'on' if fb else 'off':<9}{r['hand_max_mm']:12.0f}{r['frames_over_150mm']:16d}"
                  f"{fmt(r['mpjpe_mm'])}{'':>38}{r['hand_max_settled_mm']:11.0f}{r['frames_over_150mm_settled']:16d}",
                  flush=True)

    print("\n4. Distractor (frames with head or a hand nearer the other person; claim 0; 'on them': and within "
          f"{cl.JUMP_NEAR_M:g} m of their joint)")
    print("   'legs': the same for the knees and ankles (not the claim; the other person's trousers look alike)")
    print(f"{'estimator':<11}{'feedback':<9}{'jump frames':>12}{'on them':>9}{'MPJPE mm':>9}{'legs':>7}{'on them':>9}")
    for e in estimators:
        for fb in (True, False):
            r = res[("distractor", e, fb)] = cl.run(bag("distractor"), "distractor", e, fb, body)
            print(f"{e:<11}{'on' if fb else 'off':<9}{r['jump_frames']:12d}{r['jump_frames_near_other']:9d}"
                  f"{fmt(r['mpjpe_mm'])}{r['leg_jump_frames']:7d}{r['leg_jump_frames_near_other']:9d}", flush=True)

    print("\n5. Camera count (default scene, feedback on)")
    print(f"{'estimator':<11}{'cameras':>8}{'MPJPE mm':>9}{'tracked %':>10}")
    for e in estimators:
        for n in (4, 2, 1):
            r = res[("default", e, "tracked")] if n == 4 else cl.run(bag("default", n), "default", e, True, body)
            res[("cameras", e, n)] = r
            print(f"{e:<11}{n:8d}{fmt(r['mpjpe_mm'])}{100 * r['tracked']:10.0f}", flush=True)

    print("\n6. Throughput (default scene, 4 cameras, feedback on; ms per frame, wall clock)")
    sizes = [(args.width, args.height)] + ([] if args.no_large else [(640, 480)])
    print(f"{'estimator':<11}{'size':<9}{'fps':>6}" + "".join(f"{c:>9}" for _, c in STAGES))
    fps = {}
    for w, h in sizes:
        big = argparse.Namespace(**{**vars(args), "width": w, "height": h})
        for e in estimators:
            r = (res[("default", e, "tracked")] if (w, h) == sizes[0]
                 else cl.run(cl.scene_bag("default", 4, big, body), "default", e, True, body))
            fps[(e, w, h)] = r["fps"]
            stages = "".join(f"{r.get(k + '_ms', 0.0):9.1f}" for k, _ in STAGES)
            print(f"{e:<11}{f'{w}x{h}':<9}{r['fps']:6.1f}{stages}", flush=True)

    head = {
        "skeleton": sk,
        "mpjpe_mm": res[("default", sk, "tracked")]["mpjpe_mm"],
        "head_hands_rms_mm": res[("default", sk, "tracked")]["head_hands_rms_mm"],
        "line_ratio": ratios["line"],
        "rotation_ratio": ratios["rotation"],
        "line_ratio_settled": ratios["line_settled"],
        "line_ratio_smoothed_raw_settled": ratios["line_smoothed_raw_settled"],
        "line_ratio_smoothed_skeleton_settled": ratios["line_smoothed_skeleton_settled"],
        "rotation_ratio_settled": ratios["rotation_settled"],
        "occlusion_max_hand_err_mm_feedback": res[("occlusion", sk, True)]["hand_max_mm"],
        "occlusion_max_hand_err_mm_no_feedback": res[("occlusion", sk, False)]["hand_max_mm"],
        "occlusion_frames_over_150mm_feedback": res[("occlusion", sk, True)]["frames_over_150mm"],
        "occlusion_frames_over_150mm_feedback_settled": res[("occlusion", sk, True)]["frames_over_150mm_settled"],
        "mpjpe_mm_settled": res[("default", sk, "tracked")]["settled_mm"],
        "head_hands_rms_mm_settled": res[("default", sk, "tracked")]["head_hands_rms_settled_mm"],
        "head_hands_blob_centres_rms_mm": res[("default", sk, "tracked")].get("head_hands_blob_centres_rms_mm",
                                                                             float("nan")),
        "head_hands_blob_centres_rms_mm_settled": res[("default", sk, "tracked")].get(
            "head_hands_blob_centres_rms_settled_mm", float("nan")),
        "fps_320x240": fps.get((sk, 320, 240), float("nan")),
        "fps_640x480": fps.get((sk, 640, 480), float("nan")),
        "raw_mpjpe_mm": res[("default", raw, "tracked")]["mpjpe_mm"],
        "blobs_edges_mpjpe_mm": res[("default", "baseline+edges", "tracked")]["mpjpe_mm"],
        "blobs_edges_head_hands_rms_mm": res[("default", "baseline+edges", "tracked")]["head_hands_rms_mm"],
        "oracle_blobs_mpjpe_mm": res[("default", sk, "oracle")]["mpjpe_mm"],
        "oracle_labels_mpjpe_mm": res[("default", sk, "labels")]["mpjpe_mm"],
        "distractor_jump_frames_feedback": res[("distractor", sk, True)]["jump_frames"],
        "distractor_jump_frames_near_other_feedback": res[("distractor", sk, True)]["jump_frames_near_other"],
        "distractor_leg_jump_frames_feedback": res[("distractor", sk, True)]["leg_jump_frames"],
        "distractor_leg_jump_frames_near_other_feedback": res[("distractor", sk, True)]["leg_jump_frames_near_other"],
        "mpjpe_mm_2_cameras": res[("cameras", sk, 2)]["mpjpe_mm"],
        "mpjpe_mm_1_camera": res[("cameras", sk, 1)]["mpjpe_mm"],
        "tracked_share_1_camera": res[("cameras", sk, 1)]["tracked"],
    }
    clean = {k: (None if not np.isfinite(v) else round(v, 3)) if isinstance(v, float) else v for k, v in head.items()}
    print(json.dumps(clean))
    return 0


if __name__ == "__main__":
    sys.exit(main())
