#!/usr/bin/env python3
"""Where the closed loop's 2-D blob labelling goes wrong (ALGORITHMS.md §1), frame by frame.

Runs ``artrack.pipeline.ClosedLoopPipeline`` on one cached synthetic scene (the same bags as
``bench/closed_loop.py``) and compares every stage with the ground truth of ``artrack.synth``
(the true pose from ``artrack.motion.pose_at``):

* per frame: MPJPE, head / left / right wrist error (mm), true and estimated heading (yaw of
  the root, deg), whether the estimated wrists or knees are left/right swapped;
* per blob label: in how many views a 2-D blob was reported, the mean distance (px) of those
  blob means to the projected true blob centre, and the 3-D stage's triangulated blob: its
  error (mm) and whether it lies nearer another true part (``evaluation.label_confusion``:
  a swapped or stolen label).

Prints one row every ``--every`` frames::

    frame  MPJPE  head  lwr  rwr  yaw true/est  swap | label views:px[mm][>nearest] ...

then a summary (first tracked frame, frames with the heading off by more than 45 deg, with
hands / legs swapped, with a leg pair exchanged in some views by the view association
(``triangulation.associate_views``), per-label seen share, 2-D px error, mislabelled share, and the median
offset, in the true link's frame, of the triangulated blob (seen in 3 or more views) from the
body model's blob centre: a bias of the appearance model) and ends with one JSON line of the
summary. ``--true-start FRAME`` re-seeds the skeleton with the true pose at that frame (the
loop's drift from a perfect start, without the start-up); ``--true-priors FRAME`` re-seeds it at
every frame from there on (the labelling given right priors, without the loop's dynamics).
``--support`` adds, per label and view, the recall and precision of the blob tracker's support
map against the renderer's true blob pixels (``synth.Renderer.blob_pixels``: the link's pixels
nearest the blob's colour class), each colour class model's mean against the true pixels' mean
colour, and how often each class was bootstrapped again (``colour_relearn_frames``).
Deterministic; run from the repository root::

    .venv/bin/python bench/label_diagnosis.py --scene default --seed 3
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "src" / "artrack_nodes"))
sys.path.insert(0, str(Path(__file__).resolve().parent))
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse  # noqa: E402
import json  # noqa: E402
import math  # noqa: E402

import numpy as np  # noqa: E402
from closed_loop import SCENES, scene_bag  # noqa: E402

from artrack.bags import read_scene  # noqa: E402
from artrack.body_model import load_body_model  # noqa: E402
from artrack.colour_model import colour_features  # noqa: E402
from artrack.constraints import exp_so3  # noqa: E402
from artrack.evaluation import label_confusion  # noqa: E402
from artrack.motion import pose_at  # noqa: E402
from artrack.pipeline import ClosedLoopPipeline, load_pipeline_config  # noqa: E402
from artrack.progress import Progress  # noqa: E402
from artrack.synth import START_STAMP_NS, Renderer, SceneConfig  # noqa: E402

HEADING_LIMIT_DEG = 45.0


def yaw_deg(theta: np.ndarray) -> float:
    """Heading (deg) of the root's forward (+x) axis on the floor."""
    R = exp_so3(np.asarray(theta[3:6], float))
    return math.degrees(math.atan2(R[1, 0], R[0, 0]))


def swapped(est: np.ndarray, truth: np.ndarray, i: int, j: int) -> bool:
    """Whether joints i, j of est (J, 3) fit truth better exchanged."""
    straight = np.linalg.norm(est[i] - truth[i]) + np.linalg.norm(est[j] - truth[j])
    crossed = np.linalg.norm(est[i] - truth[j]) + np.linalg.norm(est[j] - truth[i])
    return bool(crossed < straight)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scene", default="default", choices=list(SCENES))
    ap.add_argument("--seed", type=int, default=3)
    ap.add_argument("--estimator", default="baseline", help="baseline | kinematic | dynamic")
    ap.add_argument("--feedback", default="on", choices=["on", "off"])
    ap.add_argument("--width", type=int, default=320)
    ap.add_argument("--height", type=int, default=240)
    ap.add_argument("--duration", type=float, default=6.0)
    ap.add_argument("--every", type=int, default=6, help="print every this many frames")
    ap.add_argument("--cache", default="/tmp/artrack_bench")
    ap.add_argument("--true-start", type=int, default=-1, metavar="FRAME",
                    help="re-seed the skeleton with the true pose at this frame (-1: its own start-up)")
    ap.add_argument("--true-priors", type=int, default=-1, metavar="FRAME",
                    help="re-seed the skeleton with the true pose at every frame from this one (-1: never)")
    ap.add_argument("--support", action="store_true",
                    help="support-map recall / precision per label and view against the true blob pixels")
    args = ap.parse_args()
    body = load_body_model()
    path = scene_bag(args.scene, 4, argparse.Namespace(**vars(args)), body)
    cfg = SceneConfig(n_cameras=4, width=args.width, height=args.height, duration_s=args.duration,
                      seed=args.seed, **SCENES[args.scene])
    scene = read_scene(path)
    pipe = ClosedLoopPipeline(body, scene.cameras, load_pipeline_config(estimator=args.estimator,
                                                                        feedback=args.feedback == "on"))
    cams = {c.name: c for c in pipe.cameras}
    labels = list(body.blob_labels)
    names = list(body.joint_names)
    J = {n: names.index(n) for n in ("head", "l_wrist", "r_wrist", "l_knee", "r_knee")}
    model_local = {lab: body.link(lab).blob.centre for lab in labels}  # link frame, m ('auto' resolved)
    offsets: dict[str, list[np.ndarray]] = {lab: [] for lab in labels}
    rows = []
    renderer = Renderer(body, scene.cameras, cfg.seed) if args.support else None
    support = {}  # (camera, label) -> [(recall, precision)] over tracked frames, NaN where undefined
    sources = {}  # label -> {source: support pixels} over views and tracked frames (see support_scores)
    colour_true = {}  # (camera, colour class) -> true pixels' mean colour features, last frame
    for stamp, images in Progress(scene.frames(), total=scene.n_frames, label="label diagnosis"):
        t = (int(stamp) - START_STAMP_NS) * 1e-9 - SCENES[args.scene].get("empty_s", 0.0)
        index = round((int(stamp) - START_STAMP_NS) * cfg.fps * 1e-9)
        if t >= 0 and (index == args.true_start or 0 <= args.true_priors <= index):
            pipe.restart(int(stamp), body.joint_positions(pose_at(cfg.motion_name, t, body)))
        res = pipe.step(stamp, images)
        if t < 0 or not np.all(np.isfinite(res.estimate.joints)):
            continue
        theta = pose_at(cfg.motion_name, t, body)
        if renderer is not None:
            support_scores(pipe, renderer, theta, index, images, labels, support, colour_true, sources)
        T = body.forward_kinematics(theta)
        for lab, b in pipe.skeleton.estimator.last_observed.items():
            if len(b.cameras) >= 3:
                offsets[lab].append((np.linalg.inv(T[body.link_names.index(lab)]) @ np.append(b.mean, 1.0))[:3]
                                    - model_local[lab])
        true_blobs = dict(zip(labels, body.blob_gaussians(theta)[0], strict=True))
        tj = body.joint_positions(theta)
        est = res.estimate.joints
        err = 1e3 * np.linalg.norm(est - tj, axis=1)
        dyaw = (yaw_deg(pipe.skeleton.estimator.theta) - yaw_deg(theta) + 180.0) % 360.0 - 180.0
        per = {}
        for lab in labels:
            px = []
            for cname, blobs in res.blobs.items():
                uv, _ = cams[cname].project(true_blobs[lab][None])
                px += [float(np.linalg.norm(np.asarray(b.mean) - uv[0])) for b in blobs if b.label == lab]
            per[lab] = {"views": len(px), "px": float(np.mean(px)) if px else math.nan}
        obs = {lab: b.mean for lab, b in pipe.skeleton.estimator.last_observed.items()}
        for lab, (nearest, dist) in label_confusion(obs, true_blobs).items():
            per[lab].update(mm=1e3 * dist, nearest=nearest)
        frame = int(round((int(stamp) - START_STAMP_NS) * cfg.fps * 1e-9))
        rows.append({"frame": frame, "mpjpe": float(err.mean()),
                     "head": float(err[J["head"]]), "lwr": float(err[J["l_wrist"]]), "rwr": float(err[J["r_wrist"]]),
                     "yaw_true": yaw_deg(theta), "yaw_err": float(dyaw),
                     "hands_swapped": swapped(est, tj, J["l_wrist"], J["r_wrist"]),
                     "legs_swapped": swapped(est, tj, J["l_knee"], J["r_knee"]),
                     "view_swaps": bool(pipe.skeleton.estimator.view_swaps), "labels": per})
    print(f"{'frame':>5} {'MPJPE':>6} {'head':>5} {'lwr':>5} {'rwr':>5} {'yaw true/err':>13} swap | "
          "label views:px [3-D mm] [>nearest true part]")
    for r in rows[:: max(1, args.every)]:
        sw = ("H" if r["hands_swapped"] else "-") + ("L" if r["legs_swapped"] else "-")
        cells = []
        for lab, p in r["labels"].items():
            c = f"{lab}:{p['views']}"
            if p["views"]:
                c += f":{p['px']:.0f}"
            if "mm" in p:
                c += f"[{p['mm']:.0f}]" + ("" if p["nearest"] == lab else f">{p['nearest']}")
            cells.append(c)
        print(f"{r['frame']:5d} {r['mpjpe']:6.0f} {r['head']:5.0f} {r['lwr']:5.0f} {r['rwr']:5.0f} "
              f"{r['yaw_true']:6.0f}/{r['yaw_err']:+5.0f}  {sw}  | " + " ".join(cells))
    summary = {
        "scene": args.scene, "seed": args.seed, "estimator": args.estimator, "feedback": args.feedback,
        "tracked_frames": len(rows), "first_tracked_frame": rows[0]["frame"] if rows else None,
        "mpjpe_mm": float(np.mean([r["mpjpe"] for r in rows])) if rows else math.nan,
        "heading_off_frames": sum(abs(r["yaw_err"]) > HEADING_LIMIT_DEG for r in rows),
        "hands_swapped_frames": sum(r["hands_swapped"] for r in rows),
        "legs_swapped_frames": sum(r["legs_swapped"] for r in rows),
        "view_association_frames": sum(r["view_swaps"] for r in rows),
        "labels": {},
    }
    for lab in labels:
        views = [r["labels"][lab]["views"] for r in rows]
        px = [r["labels"][lab]["px"] for r in rows if r["labels"][lab]["views"]]
        obs = [r["labels"][lab] for r in rows if "mm" in r["labels"][lab]]
        summary["labels"][lab] = {
            "mean_views": float(np.mean(views)) if views else 0.0,
            "px": float(np.mean(px)) if px else math.nan,
            "obs3d_mm": float(np.median([o["mm"] for o in obs])) if obs else math.nan,
            "mislabelled_share": sum(o["nearest"] != lab for o in obs) / max(len(obs), 1),
            "centre_offset_mm": (1e3 * np.median(offsets[lab], axis=0)).round(1).tolist() if offsets[lab] else None,
        }
    print(f"\ntracked {len(rows)} frames from frame {summary['first_tracked_frame']}; "
          f"MPJPE {summary['mpjpe_mm']:.1f} mm; "
          f"heading off > {HEADING_LIMIT_DEG:.0f} deg in {summary['heading_off_frames']}, hands swapped in "
          f"{summary['hands_swapped_frames']}, legs swapped in {summary['legs_swapped_frames']} of them; the view "
          f"association exchanged a pair in {summary['view_association_frames']}")
    print(f"{'label':<9}{'views/4':>8}{'2-D px':>8}{'3-D mm (median)':>17}{'mislabelled %':>15}"
          "  blob - model centre, link frame x y z mm (median)")
    for lab, s in summary["labels"].items():
        off = s["centre_offset_mm"]
        print(f"{lab:<9}{s['mean_views']:8.2f}{s['px']:8.1f}{s['obs3d_mm']:17.0f}{100 * s['mislabelled_share']:15.0f}"
              + ("  " + " ".join(f"{v:6.0f}" for v in off) if off else "  -"))
    if renderer is not None:
        summary["support"] = print_support(pipe, labels, support, colour_true)
        summary["support"]["sources"] = print_sources(labels, sources)
    print(json.dumps(summary))
    return 0


def support_scores(pipe, renderer, theta, index, images, labels, support, colour_true, sources) -> None:
    """Recall and precision of each tracking view's support map per label against the renderer's
    true blob pixels of this frame (appended to ``support``); the true mean colour features of
    each colour class (``colour_true``); per label, the pixels of its support by what the renderer
    drew there (``sources``: its own true blob pixels 'own', another blob's true pixels by label,
    a link without a blob or a blob link's other colours by link name, 'room' elsewhere)."""
    link_names = renderer.body.link_names
    _, label_images = renderer.render(theta, (), 0.0, frame_index=index, labels=True)  # labels only
    for cam, label_image in zip(renderer.cameras, label_images, strict=True):
        tracker = pipe.blob_stages[cam.name].tracker
        if not tracker.support_labels or tracker.mode != "tracking":
            continue
        smap = tracker.support_map
        truth = renderer.blob_pixels(images[cam.name], label_image)
        feats = colour_features(images[cam.name])
        blob_of = np.full(smap.shape, -1, np.int32)  # index in labels of the true blob at a pixel (disjoint)
        for k, lab in enumerate(labels):
            xs, ys = truth[lab]
            blob_of[ys, xs] = k
        by_class: dict[str, list[np.ndarray]] = {}
        for k, lab in enumerate(labels):
            true = blob_of == k
            got = smap == tracker.support_labels.index(lab) if lab in tracker.support_labels else np.zeros_like(true)
            both = np.count_nonzero(true & got)
            n_true, n_got = np.count_nonzero(true), np.count_nonzero(got)
            support.setdefault((cam.name, lab), []).append(
                (both / n_true if n_true >= 10 else math.nan, both / n_got if n_got >= 10 else math.nan))
            xs, ys = truth[lab]
            by_class.setdefault(tracker.colour_classes[lab], []).append(feats[ys, xs])
            if lab not in tracker.support_labels:
                continue
            counts = sources.setdefault(lab, {})
            for j, n in zip(*np.unique(blob_of[got], return_counts=True), strict=True):
                if j >= 0:
                    key = "own" if j == k else labels[j]
                    counts[key] = counts.get(key, 0) + int(n)
            links = label_image[got & (blob_of < 0)]
            for j, n in zip(*np.unique(links, return_counts=True), strict=True):
                key = "room" if j == 0 else link_names[j - 1]
                counts[key] = counts.get(key, 0) + int(n)
        for cls, parts in by_class.items():
            c = np.concatenate(parts)
            if len(c):
                colour_true[(cam.name, cls)] = c.mean(axis=0)


def print_support(pipe, labels, support, colour_true) -> dict:
    """Print the support table (recall / precision %, per label and view), the colour models and
    how often each class was bootstrapped again; returns them for the JSON summary."""
    cams = sorted({c for c, _ in support})
    out: dict = {"recall_precision": {}, "colour_models": {}, "colour_relearned": {}}
    print("\nsupport map vs true blob pixels, recall / precision % (mean over tracked frames)")
    print(f"{'label':<9}" + "".join(f"{c:>13}" for c in cams))
    for lab in labels:
        cells = []
        for c in cams:
            v = np.array(support.get((c, lab), [(math.nan, math.nan)]), float)
            r, p = (np.nanmean(v[:, k]) if np.any(np.isfinite(v[:, k])) else math.nan for k in (0, 1))
            out["recall_precision"].setdefault(lab, {})[c] = [round(100 * r, 1), round(100 * p, 1)]
            cells.append(f"{100 * r:8.0f}/{100 * p:<4.0f}")
        print(f"{lab:<9}" + "".join(cells))
    print("colour class models at the end (r, g, I) vs the true pixels' mean; times bootstrapped again")
    for c in cams:
        tracker = pipe.blob_stages[c].tracker
        for cls, model in sorted(tracker.colour_models.items()):
            true = colour_true.get((c, cls))
            out["colour_models"].setdefault(c, {})[cls] = {
                "model": np.round(model.mean, 3).tolist(),
                "true": None if true is None else np.round(np.asarray(true, float), 3).tolist()}
            print(f"  {c} {cls:<9} model {np.round(model.mean, 3)} true "
                  f"{'-' if true is None else np.round(true, 3)} relearned {tracker.colour_relearned.get(cls, 0)}")
        out["colour_relearned"][c] = dict(tracker.colour_relearned)
    return out


def print_sources(labels, sources, top: int = 5) -> dict:
    """Print, per label, where its support pixels lie (largest shares first); returns the shares."""
    print("support pixels by what lies there, % (own = the label's true blob pixels; room = no body part)")
    out = {}
    for lab in labels:
        counts = sources.get(lab, {})
        total = sum(counts.values())
        shares = {k: round(100.0 * n / total, 1) for k, n in sorted(counts.items(), key=lambda kv: -kv[1])} \
            if total else {}
        out[lab] = shares
        print(f"  {lab:<9}" + "  ".join(f"{k} {v:.0f}" for k, v in list(shares.items())[:top]))
    return out


if __name__ == "__main__":
    sys.exit(main())
