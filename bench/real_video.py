#!/usr/bin/env python3
"""Tracking a real four-camera recording without ground truth (issue 5, "Checks").

Reads the Pose2Sim Demo_SinglePerson videos with their Qualisys calibration (/work/shared/DATA.md;
``scripts/fetch_pose2sim.sh`` fetches them) at the working resolution ``--scale``, tracks them
offline with the closed loop of the live graph (``artrack.pipeline.ClosedLoopPipeline``, the
blob tracker and the default 'baseline' body fit, tunables from ``--blob-config`` /
``--skeleton-config``), and measures, per view and frame:

* ``IoU``: overlap of the projected body model (the body model's capsules and ellipsoids at the
  estimated link poses, rasterised: ``artrack.silhouette.BodySilhouette``) with a reference
  foreground mask. The mask is NOT the tracker's: the tracker's background is causal (seeded from
  the clip's first frames); the reference uses the whole clip, as the minimum difference to
  per-block temporal medians of blocks far in time (``artrack.silhouette.reference_foreground``:
  the person has moved away from where they stand now, so the room shows through). Frames
  without an estimate count as IoU 0.
* ``on ±3`` / ``cov. ±3``: where the IoU's misses lie, at a tolerance of ``--tolerance-px``: the
  share of the model's pixels within it of the reference mask, and of the mask's within it of
  the model, over the tracked frames (``artrack.silhouette.tolerant_overlap``). Printed with
  them: the IoU of the reference mask with itself moved by that many pixels, the strict IoU's
  ceiling for a pose or calibration offset that small.
* ``inside``: share of projected joints inside the reference mask dilated by ``--dilate-px``
  (joint-frames without an estimate count as outside).
* ``LOO IoU``: leave-one-camera-out, the IoU in a camera of the body tracked with the three
  others (``--no-loo`` skips these four extra runs).
* ``--track-cameras``: track with some cameras only (one, say); every view is still checked, so the
  others are held out, as in leave-one-camera-out.
* joint speeds between frames; any above 10 m/s is flagged.
* ``head to cap``: the man wears a cyan cap; found by colour in every view and triangulated
  (``artrack.silhouette.colour_marker``) it is an independent 3-D point on him. The distance of
  the tracked head joint (the head's centre, ~0.12 m below the cap's centroid) to it tells whether
  the skeleton stays with him (Demo_MultiPerson: not jumping to the woman); frames with more than
  ``--head-off-m`` are counted (``--marker-hsv none`` skips this check on other recordings).
  Since stop 44 the Pose2Sim configs track the cap itself as the head's blob
  (config/pose2sim_body_model.yaml), so there this check is no longer independent of the
  tracker: it shows that the head follows its feature. IoU and ``inside`` stay independent.
* frames per second of the tracking loop (decoding and checks excluded) and ms per stage.

With ``--pred DIR_OR_BAG`` (e.g. the output bag of the live graph, ``make demo``) the checks are
made on that estimate instead; the offline run still gives fps and per-stage ms, and the largest
joint difference between the two is printed (lockstep graph = offline pipeline).
``--overlay-png`` / ``--overlay-mp4`` draw the projected skeleton and 2-D blobs on the four views.

Prints a table and ends with one JSON line: fps, inside_foreground_share, mean_iou (per view),
loo_iou (per view), max_joint_speed, and more. Run from the repository root::

    .venv/bin/python bench/real_video.py                                   # Demo_SinglePerson, quarter size
    .venv/bin/python bench/real_video.py --pred out/demo/graph --overlay-png out/demo/overlay.png
    .venv/bin/python bench/real_video.py --demo .cache/pose2sim/Pose2Sim/Demo_MultiPerson
"""

from __future__ import annotations

import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "src" / "artrack_nodes"))

import argparse  # noqa: E402
import json  # noqa: E402
import os  # noqa: E402
import time  # noqa: E402

import cv2  # noqa: E402
import numpy as np  # noqa: E402

from artrack.body_model import load_body_model  # noqa: E402
from artrack.cameras import load_calibration  # noqa: E402
from artrack.errors import ArtrackError, InputError  # noqa: E402
from artrack.overlay import draw_body, montage, write_montage_png, write_mp4  # noqa: E402
from artrack.pipeline import ClosedLoopPipeline, load_pipeline_config  # noqa: E402
from artrack.progress import Progress  # noqa: E402
from artrack.silhouette import (  # noqa: E402
    BodySilhouette,
    colour_marker,
    iou,
    joint_speeds,
    joints_inside,
    reference_foreground,
    shifted_iou,
    tolerant_overlap,
)
from artrack.video import open_videos  # noqa: E402

CACHE = Path(os.environ.get("ARTRACK_CACHE", REPO / ".cache"))
DEFAULT_DEMO = CACHE / "pose2sim/Pose2Sim/Demo_SinglePerson"
SPEED_LIMIT = 10.0  # m/s: faster joints are flagged


def load_bag(bag: Path, max_frames: int | None):
    """As load_clip, from a recording written by `artrack bag-from-videos` (the graph's input)."""
    from artrack.bags import read_scene

    scene = read_scene(bag)
    t0 = time.perf_counter()
    frames, stamps = [], []
    for stamp, images in scene.frames():
        if max_frames and len(frames) >= max_frames:
            break
        frames.append(images)
        stamps.append(stamp)
    decode_ms = (time.perf_counter() - t0) * 1e3 / max(1, len(frames))
    if not frames:
        raise InputError(f"{bag}: no frames")
    fps = 1e9 / float(np.median(np.diff(stamps))) if len(stamps) > 1 else 30.0
    return list(scene.cameras), frames, np.asarray(stamps, np.int64), fps, decode_ms


def load_clip(demo: Path, scale: float, max_frames: int | None):
    """(working cameras, frames [{camera: BGR}], stamps (T,), fps, decode ms per frame)."""
    calib = demo / "calibration" / "Calib.qca.txt"
    cams = load_calibration(calib)
    videos = open_videos([demo / "videos" / f"{c.name}.mp4" for c in cams], cams, scale, max_frames=max_frames)
    t0 = time.perf_counter()
    frames, stamps = [], []
    for _, stamp, images in videos:
        frames.append(images)
        stamps.append(stamp)
    decode_ms = (time.perf_counter() - t0) * 1e3 / max(1, len(frames))
    if not frames:
        raise InputError(f"{demo}/videos: no frames")
    return list(videos.cameras), frames, np.asarray(stamps, np.int64), videos.fps, decode_ms


def track(body, cameras, frames, stamps, config, label: str, quiet: bool):
    """Offline closed loop over the clip: (estimates, blobs per frame, per-stage ms lists, seconds)."""
    pipe = ClosedLoopPipeline(body, cameras, config)
    names = {c.name for c in cameras}
    estimates, blobs, stages = [], [], {}
    elapsed = 0.0
    for stamp, images in Progress(list(zip(stamps, frames, strict=True)), label=label, quiet=quiet):
        t0 = time.perf_counter()
        res = pipe.step(int(stamp), {n: im for n, im in images.items() if n in names})
        elapsed += time.perf_counter() - t0
        for k, v in res.timings_ms.items():
            stages.setdefault(k, []).append(v)
        estimates.append(res.estimate)
        blobs.append(res.blobs)
    return estimates, blobs, stages, elapsed


def read_pred(path: Path, stamps: np.ndarray, camera_names: list[str]):
    """Estimates and blobs per frame from an output bag (or an `artrack track` folder's track/ bag)."""
    from artrack.bags import open_bag
    from artrack.messages import blobs_from_msg, body_from_msg

    if path.is_dir() and (path / "track").is_dir():
        path = path / "track"
    index = {int(s): i for i, s in enumerate(stamps)}
    estimates = [None] * len(stamps)
    blobs = [dict() for _ in stamps]
    with open_bag(path) as bag:
        topics = set(bag.topics())
        wanted = ["/artrack/body"] + [f"/cameras/{n}/blobs" for n in camera_names
                                      if f"/cameras/{n}/blobs" in topics]
        for topic, _, msg in bag.messages(wanted):
            if topic == "/artrack/body":
                est = body_from_msg(msg)
                i = index.get(int(est.stamp_ns))
                if i is not None:
                    estimates[i] = est
            else:
                stamp, cam, bl = blobs_from_msg(msg)
                i = index.get(int(stamp))
                if i is not None:
                    blobs[i][cam or topic.split("/")[2]] = bl
    missing = sum(e is None for e in estimates)
    if missing == len(estimates):
        raise InputError(f"{path}: no /artrack/body message matches a frame stamp of the clip")
    return estimates, blobs, missing


def joints_array(estimates, n_joints: int) -> np.ndarray:
    out = np.full((len(estimates), n_joints, 3), np.nan)
    for i, e in enumerate(estimates):
        if e is not None and len(e.links) and np.asarray(e.joints).size == n_joints * 3:
            out[i] = np.asarray(e.joints, float).reshape(n_joints, 3)
    return out


def model_masks(silhouette: BodySilhouette, estimates) -> list[dict[str, np.ndarray] | None]:
    """Per frame, the projected body model's {camera: mask}, or None without an estimate."""
    return [silhouette.masks(est) if est is not None else None for est in estimates]


def view_ious(masks, refs, names: list[str]) -> dict[str, np.ndarray]:
    """Per view, (T,) IoU of the projected body model (``model_masks``) with the reference mask (0
    without an estimate)."""
    out = {n: np.zeros(len(masks)) for n in names}
    for t, m in enumerate(masks):
        if m is not None:
            for n in names:
                out[n][t] = iou(m[n], refs[t][n])
    return out


def view_overlaps(masks, refs, names: list[str], tol_px: int) -> dict[str, tuple[float, float, float]]:
    """Per view, the means over the tracked frames of ``tolerant_overlap`` (model on the reference,
    reference covered by the model; ``model_masks``), and the mean IoU of each frame's reference with
    itself moved ``tol_px`` (frames with an empty reference left out)."""
    def mean(values) -> float:
        return float(np.mean(values)) if len(values) else float("nan")

    out = {}
    for n in names:
        shares = np.array([tolerant_overlap(m[n], refs[t][n], tol_px) for t, m in enumerate(masks)
                           if m is not None]).reshape(-1, 2)
        moved = [shifted_iou(r[n], tol_px) for r in refs if r[n].any()]
        out[n] = (mean(shares[:, 0]), mean(shares[:, 1]), mean(moved))
    return out


def draw_frame(cameras, images, joints, joint_names, blobs) -> list[np.ndarray]:
    return [draw_body(images[c.name], c, None if not np.isfinite(joints).all() else joints, joint_names,
                      blobs2d=blobs.get(c.name), frame=None) for c in cameras]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--demo", type=Path, default=DEFAULT_DEMO,
                    help="recording folder with videos/camNN.mp4 and calibration/Calib.qca.txt")
    ap.add_argument("--bag", type=Path, default=None,
                    help="read the frames from this bag (`artrack bag-from-videos` output) instead of --demo's "
                         "videos: the graph's input, so that --pred output can be compared to the offline run")
    ap.add_argument("--scale", type=float, default=0.25, help="working resolution factor (default 0.25: 272x480)")
    ap.add_argument("--max-frames", type=int, default=0, help="first N frames only (0: all)")
    ap.add_argument("--blob-config", default=str(REPO / "config" / "pose2sim_demo.yaml"))
    ap.add_argument("--skeleton-config", default=str(REPO / "config" / "pose2sim_skeleton.yaml"),
                    help="estimator tunables YAML (default: the Pose2Sim recordings' config/pose2sim_skeleton.yaml)")
    ap.add_argument("--edges", action="store_true",
                    help="fuse the edge features (ALGORITHMS.md §2) into the body fit, as `artrack track --edges`")
    ap.add_argument("--edge-config", default=None, help="edge tracker tunables (default config/edge_features.yaml)")
    ap.add_argument("--body-model", default=str(REPO / "config" / "pose2sim_body_model.yaml"),
                    help="body model YAML (default: the Pose2Sim recordings' config/pose2sim_body_model.yaml)")
    ap.add_argument("--pred", type=Path, default=None, help="check this tracking output instead (bag or track folder)")
    ap.add_argument("--no-loo", action="store_true", help="skip the leave-one-camera-out runs")
    ap.add_argument("--track-cameras", nargs="+", default=None, metavar="NAME",
                    help="track with these cameras only (e.g. one: cam03; config/skeleton.yaml's few_cameras "
                         "settings apply to one or two); the checks still cover every view, the others held out; no "
                         "leave-one-camera-out runs")
    ap.add_argument("--dilate-px", type=int, default=6, help="dilation of the reference mask for 'inside', px")
    ap.add_argument("--tolerance-px", type=int, default=3,
                    help="tolerance of the 'on' / 'covered' shares and of the shifted reference's IoU, px")
    ap.add_argument("--marker-hsv", default="84,120,60,100,255,255",
                    help="HSV range (low h,s,v,high h,s,v; OpenCV hue 0..180) of a marker worn on the head (default: "
                         "the Pose2Sim man's cyan cap), or 'none'")
    ap.add_argument("--head-off-m", type=float, default=0.35, help="head-to-marker distance counted as off, m")
    ap.add_argument("--overlay-png", type=Path, default=None, help="montage: 4 views x 4 frames")
    ap.add_argument("--overlay-mp4", type=Path, default=None, help="video of the 4 views, all frames")
    ap.add_argument("--startup-refine-frames", type=int, default=None, metavar="N",
                    help="PipelineConfig.startup_refine_frames (default: the pipeline's, 10; 0: off)")
    ap.add_argument("--quiet", action="store_true")
    args = ap.parse_args()
    try:
        return run(args)
    except ArtrackError as exc:
        print(f"real_video: {exc}", file=sys.stderr)
        return 1


def run(args) -> int:
    if args.bag is not None:
        cameras, frames, stamps, fps_clip, decode_ms = load_bag(args.bag, args.max_frames or None)
    else:
        cameras, frames, stamps, fps_clip, decode_ms = load_clip(args.demo, args.scale, args.max_frames or None)
    names = [c.name for c in cameras]
    tracking = cameras
    if args.track_cameras:
        unknown = sorted(set(args.track_cameras) - set(names))
        if unknown:
            raise InputError(f"--track-cameras: no camera '{unknown[0]}' in {args.bag or args.demo} "
                             f"(cameras: {', '.join(names)})")
        tracking = [c for c in cameras if c.name in args.track_cameras]
    body = load_body_model(args.body_model)
    config = load_pipeline_config(fps=fps_clip, blob_config=args.blob_config, skeleton_config=args.skeleton_config,
                                  edges=args.edges, edge_config=args.edge_config)
    if args.startup_refine_frames is not None:
        config.startup_refine_frames = args.startup_refine_frames
    t0 = time.perf_counter()
    refs = reference_foreground(frames)
    ref_ms = (time.perf_counter() - t0) * 1e3 / len(frames)

    estimates, blobs, stages, elapsed = track(body, tracking, frames, stamps, config, "track", args.quiet)
    fps = len(frames) / elapsed
    offline_joints = joints_array(estimates, len(body.joint_names))
    graph_diff = None
    if args.pred is not None:
        estimates, blobs, _ = read_pred(args.pred, stamps, names)
        pj = joints_array(estimates, len(body.joint_names))
        both = np.isfinite(pj).all(axis=(1, 2)) & np.isfinite(offline_joints).all(axis=(1, 2))
        graph_diff = float(np.abs(pj[both] - offline_joints[both]).max()) if both.any() else None
    joints = joints_array(estimates, len(body.joint_names))
    tracked = np.isfinite(joints).all(axis=(1, 2))

    silhouette = BodySilhouette(body, cameras)
    t0 = time.perf_counter()
    masks = model_masks(silhouette, estimates)
    ious = view_ious(masks, refs, names)
    overlaps = view_overlaps(masks, refs, names, args.tolerance_px)
    sil_ms = (time.perf_counter() - t0) * 1e3 / len(frames)

    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * args.dilate_px + 1,) * 2)
    inside = {n: np.zeros((len(frames), len(body.joint_names)), bool) for n in names}
    for t in range(len(frames)):
        for c in cameras:
            dil = cv2.dilate(refs[t][c.name].astype(np.uint8), kernel).astype(bool)
            inside[c.name][t] = joints_inside(c, joints[t], dil)
    inside_share = float(np.mean([inside[n].mean() for n in names]))

    loo: dict[str, float | None] = {n: None for n in names}
    if not args.no_loo and not args.track_cameras and len(cameras) > 1:
        for c in cameras:
            rest = [k for k in cameras if k.name != c.name]
            est_c, _, _, _ = track(body, rest, frames, stamps, config, f"loo-{c.name}", args.quiet)
            loo[c.name] = float(view_ious(model_masks(silhouette, est_c), refs, [c.name])[c.name].mean())

    head_dist = np.full(len(frames), np.nan)
    if args.marker_hsv != "none":
        try:
            hsv = [int(v) for v in args.marker_hsv.split(",")]
        except ValueError:
            hsv = []
        if len(hsv) != 6:
            raise InputError(f"--marker-hsv '{args.marker_hsv}': expected 6 integers h,s,v,h,s,v or 'none'")
        hi = body.joint_names.index("head")
        for t in range(len(frames)):
            X, _ = colour_marker(cameras, frames[t], hsv[:3], hsv[3:])
            if X is not None and tracked[t]:
                head_dist[t] = float(np.linalg.norm(joints[t, hi] - X))
    speeds = joint_speeds(stamps, joints)
    finite_speeds = speeds[np.isfinite(speeds)]
    max_speed = float(finite_speeds.max()) if finite_speeds.size else None
    flagged = int(np.count_nonzero(finite_speeds > SPEED_LIMIT))
    fast_frames = sorted({int(t) + 1 for t, _ in zip(*np.nonzero(np.nan_to_num(speeds) > SPEED_LIMIT),
                                                     strict=True)})

    # ------------------------------------------------------------------ report
    w, h = cameras[0].width, cameras[0].height
    src = f"{args.pred} (checked), offline run for fps" if args.pred else "offline closed loop"
    print(f"{(args.bag or args.demo).name}: {len(frames)} frames x {len(cameras)} views at {w}x{h}, "
          f"{fps_clip:g} fps; {src}"
          + (f"; tracked with {', '.join(c.name for c in tracking)} only" if args.track_cameras else ""))
    print(f"tracked frames: {int(tracked.sum())}/{len(frames)} (first at frame "
          f"{int(np.argmax(tracked)) if tracked.any() else '-'})")
    tol = f"±{args.tolerance_px}"
    print(f"{'view':<8}{'mean IoU':>10}{'IoU tracked':>13}{'LOO IoU':>10}{'inside %':>10}{'on ' + tol:>9}"
          f"{'cov. ' + tol:>9}{'ref. moved ' + str(args.tolerance_px):>14}")
    for n in names:
        tr = ious[n][tracked].mean() if tracked.any() else float('nan')
        lo = f"{loo[n]:10.3f}" if loo[n] is not None else f"{'-':>10}"
        on, cov, moved = overlaps[n]
        print(f"{n:<8}{ious[n].mean():10.3f}{tr:13.3f}{lo}{100 * inside[n].mean():10.1f}{on:9.2f}{cov:9.2f}"
              f"{moved:14.2f}")
    print(f"(on / cov. {tol}: the model's pixels within {args.tolerance_px} px of the reference mask / the mask's "
          f"within {args.tolerance_px} px of the model; ref. moved {args.tolerance_px}: the IoU of the reference "
          f"with itself moved {args.tolerance_px} px)")
    print(f"joints inside the dilated foreground ({args.dilate_px} px): {100 * inside_share:.1f} % of joint-frames")
    if tracked.any():  # where the misses are: per joint, over the tracked frames and the views
        per_joint = np.mean([inside[n][tracked] for n in names], axis=(0, 1))
        print(f"over the {int(tracked.sum())} tracked frames: {100 * per_joint.mean():.1f} %; per joint: "
              + ", ".join(f"{j} {100 * v:.0f}" for j, v in zip(body.joint_names, per_joint, strict=True)))
    print(f"max joint speed {max_speed if max_speed is None else round(max_speed, 2)} m/s; "
          f"{flagged} joint-steps above {SPEED_LIMIT:g} m/s" + (f" (frames {fast_frames[:12]})" if flagged else ""))
    hd = head_dist[np.isfinite(head_dist)]
    off = int(np.count_nonzero(hd > args.head_off_m))
    if hd.size:
        off_frames = np.flatnonzero(np.nan_to_num(head_dist) > args.head_off_m).tolist()
        print(f"head to cap: median {np.median(hd):.2f} m, max {hd.max():.2f} m over {hd.size} frames; "
              f"{off} frames above {args.head_off_m:g} m"
              + (f" (frames {off_frames[:12]}{' ...' if off > 12 else ''})" if off else ""))
        big = np.nanargmax(head_dist)
        print(f"  largest at frame {int(big)}; above 0.6 m: {np.flatnonzero(np.nan_to_num(head_dist) > 0.6).tolist()}")
    if graph_diff is not None:
        print(f"largest joint difference, checked output vs offline run: {graph_diff * 1e3:.3g} mm")
    stage_ms = {"decode+scale": decode_ms, **{k: float(np.mean(v)) for k, v in stages.items()}}
    print(f"{'stage':<16}{f'ms/frame ({len(tracking)} views)':>20}")
    for k, v in stage_ms.items():
        print(f"{k:<16}{v:20.2f}")
    print(f"{'(checks) ref. mask':<16}{ref_ms:20.2f}\n{'(checks) model':<16}{sil_ms:20.2f}")
    print(f"tracking loop: {fps:.1f} frames per second ({len(tracking)} views; decoding and checks excluded)")

    if args.overlay_png or args.overlay_mp4:
        picks = sorted({0, len(frames) // 3, 2 * len(frames) // 3, len(frames) - 1})

        def tiles(idx):
            for t in idx:
                drawn = draw_frame(cameras, frames[t], joints[t], body.joint_names, blobs[t])
                for img in drawn:
                    cv2.putText(img, f"frame {t}", (6, img.shape[0] - 8), cv2.FONT_HERSHEY_SIMPLEX, 0.45,
                                (255, 255, 255), 1, cv2.LINE_AA)
                yield drawn
        if args.overlay_png:
            write_montage_png([im for row in tiles(picks) for im in row], args.overlay_png, cols=len(cameras))
            print(f"wrote {args.overlay_png}")
        if args.overlay_mp4:
            write_mp4((montage(row, cols=len(cameras)) for row in tiles(range(len(frames)))), args.overlay_mp4,
                      fps=min(fps_clip, 30.0))
            print(f"wrote {args.overlay_mp4}")

    print(json.dumps({
        "recording": (args.bag or args.demo).name, "frames": len(frames), "views": names, "width": w, "height": h,
        "fps": round(fps, 2), "stage_ms": {k: round(v, 2) for k, v in stage_ms.items()},
        "tracked_frames": int(tracked.sum()),
        "inside_foreground_share": round(inside_share, 4),
        "mean_iou": {n: round(float(ious[n].mean()), 4) for n in names},
        "tolerance_px": args.tolerance_px,
        "model_on_reference": {n: round(overlaps[n][0], 4) for n in names},
        "reference_covered": {n: round(overlaps[n][1], 4) for n in names},
        "reference_moved_iou": {n: round(overlaps[n][2], 4) for n in names},
        "loo_iou": {n: (None if v is None else round(v, 4)) for n, v in loo.items()},
        "max_joint_speed": None if max_speed is None else round(max_speed, 3),
        "joint_steps_above_10mps": flagged,
        "head_to_marker_median_m": round(float(np.median(hd)), 3) if hd.size else None,
        "head_to_marker_max_m": round(float(hd.max()), 3) if hd.size else None,
        "frames_head_off_marker": off if hd.size else None,
        "checked": str(args.pred) if args.pred else "offline",
        "tracked_with": [c.name for c in tracking],
        "max_diff_to_offline_m": graph_diff,
    }))
    return 0


if __name__ == "__main__":
    sys.exit(main())
