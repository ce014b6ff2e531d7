#!/usr/bin/env python3
"""Loose-limbed body by non-parametric BP (ALGORITHMS.md §4) on synthetic scenes with ground truth.

Train/test separation. The potentials (``config/loose_limbed_model.yaml``) are
learned (``--retrain``) from the ``default``, ``line`` and ``rotation`` motions,
each perturbed by seeded smooth joint-angle noise and a random heading
(``part_potentials.training_motion``, seeds 1000–1002), and the spatial ones also
from poses over the joints' range (the ``default`` motion perturbed by up to ~4.5 rad
per dof, clipped to the limits; seeds 2000–2002). The test scenes play
the ``self_occlusion`` motion from t = 5.0 s (the right hand goes behind the
back, then the left hand waves) — poses and motion that are not in the
training set — rendered with seeds 0.. (room, clothes, noise), 4 ring cameras.

1. Automatic initialisation: each test scene's frame (seed k starts at 5.0 + 0.4 k s) from
   no prior pose — shouters + BP on one frame, ``--init-repeats`` times with different random
   streams; MPJPE (15 joints, mm) per BP iteration of the tracker's estimate (the joint MAP over
   the belief samples so far, ``loose_limbed.MapAssembler``) and, for comparison, of each part's
   marginal mode alone, mean ± sd over the runs (table + PNG plot), the median and how often the
   mirrored body (left <-> right) would be nearer the truth. Joints of parts with no belief yet
   (iteration 0: parts without a shouter) are skipped in the marginal-mode curve.
2. Tracking on a low-contrast version of the scene (person blended towards the
   background by ``--contrast``, extra pixel noise): the loose-limbed tracker with
   shouters, without shouters, and the annealed kinematic-tree particle filter
   (10 layers × 200 particles, same likelihood); all start from the true
   first-frame pose; MPJPE per frame, mean ± sd over seeds (table + PNG plot).
3. Recovery: the tracker's belief is shifted 0.6 m at frame 5; with loss detection (mean
   part log-likelihood below −20; the truth scores ≈ −11) it re-initialises from the shouters;
   frames until the MPJPE is back under 200 mm, with and without the detection.
4. Timing per BP iteration / per frame and per stage (wall clock, this machine).
5. Recovery in the closed loop (the issue's acceptance item): the offline form of the live graph
   (``pipeline.ClosedLoopPipeline``: blob trackers, baseline skeleton, feedback) on a synthetic
   scene (``synth.SceneConfig``, 320x240, ``default`` motion) where every camera sees only the empty
   room for 1 s (``artrack synth --blackout 2.5:1.0``), with and without the loose_limbed
   initialiser (``loose_limbed_stage.InitialiserPolicy``, as the node: it infers while the
   skeleton's last body is LOST; its TRACKING bodies re-seed the skeleton before the next frame,
   ``estimator.reseed`` — the graph's ``reseed_topic``; in the live graph the body may arrive a
   frame or more later). Two backgrounds: the room empty for the first 1.5 s (every background
   model clean), and the person in view from frame 0 (background models seeded with the person:
   ghosts). Frames from the blackout's end until the skeleton is TRACKING with MPJPE under
   max(2 x its MPJPE over the 0.5 s before the blackout, 200 mm), and MPJPE before / after.

Ends with one JSON line of the headline figures. Run from the repository root::

    .venv/bin/python bench/loose_limbed.py            # the acceptance run (10 seeds × 50 frames; long)
    .venv/bin/python bench/loose_limbed.py --init-scenes 10 --init-repeats 3 --seeds 0 --recovery-seeds 0 --loop-seeds 0
    .venv/bin/python bench/loose_limbed.py --quick    # smoke run (2 scenes, 2 seeds × 8 frames)
    .venv/bin/python bench/loose_limbed.py --retrain  # re-learn config/loose_limbed_model.yaml and exit
"""

from __future__ import annotations

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "src" / "artrack_nodes"))

import argparse  # noqa: E402
import json  # noqa: E402
import time  # noqa: E402

import cv2  # noqa: E402
import numpy as np  # noqa: E402

from artrack.annealed_filter import AnnealedParticleFilter, AnnealingConfig  # noqa: E402
from artrack.body_model import load_body_model  # noqa: E402
from artrack.body_parts import joints_from_parts, part_geometry, parts_from_theta  # noqa: E402
from artrack.errors import ArtrackError  # noqa: E402
from artrack.evaluation import mpjpe  # noqa: E402
from artrack.loose_limbed import (  # noqa: E402
    LooseLimbedBP,
    LooseLimbedTracker,
    NBPConfig,
    TrackerConfig,
    joints_estimate,
)
from artrack.motion import pose_at  # noqa: E402
from artrack.part_likelihood import PartLikelihood, view_evidence  # noqa: E402
from artrack.part_potentials import default_model_path, load_model, save_model, train_model, training_motion  # noqa: E402
from artrack.shouters import Shouter, ShouterConfig  # noqa: E402
from artrack.synth import Renderer, SceneConfig, default_rig, generate_scene, scene_cameras  # noqa: E402
from artrack.types import STATUS_LOST, STATUS_TRACKING  # noqa: E402

TRAIN_MOTIONS = ("default", "line", "rotation")
TRAIN_SEEDS = (1000, 1001, 1002)
#: poses over the joints' whole range for the spatial potentials only: the default motion perturbed by
#: up to ~4.5 rad per dof (clipped to the joint limits). Without them the potentials knew only the
#: training motions' arm poses and scored a test pose such as a hand behind the back ~15 nats below a
#: wrong body (measured on the initialisation scenes)
RANGE_MOTION, RANGE_SEEDS, RANGE_AMPLITUDE = "default", (2000, 2001, 2002), 3.0
TEST_MOTION = "self_occlusion"
TEST_START_S = 5.0
FPS = 30.0
#: per-frame tracking budget (smaller than for initialisation: the temporal messages carry most of the pose)
TRACK_NBP = NBPConfig(n_particles=60, n_exclusive=30, n_message=30)
TRACK_SHOUTER = ShouterConfig(n_centres=60, n_orientations=8, n_refine=20, refine_rounds=2)


def retrain(path: Path) -> None:
    body = load_body_model()
    geo = part_geometry(body)
    seqs = [training_motion(body, m, s, FPS) for m in TRAIN_MOTIONS for s in TRAIN_SEEDS]
    wide = [training_motion(body, RANGE_MOTION, s, FPS, amplitude=RANGE_AMPLITUDE) for s in RANGE_SEEDS]
    model = train_model(body, geo, seqs, FPS, spatial_sequences=wide, provenance={
        "motions": list(TRAIN_MOTIONS), "seeds": list(TRAIN_SEEDS), "frames": int(sum(len(s) for s in seqs)),
        "perturbation": "part_potentials.training_motion amplitude 0.3 rad, random heading",
        "spatial_only": {"motion": RANGE_MOTION, "seeds": list(RANGE_SEEDS), "amplitude_rad": RANGE_AMPLITUDE,
                         "frames": int(sum(len(s) for s in wide))},
        "not_in_training": f"{TEST_MOTION} from {TEST_START_S} s (the bench's test motion)"})
    save_model(model, path)
    print(f"wrote {path} ({len(seqs)} sequences, {sum(len(s) for s in seqs)} frames)")


class Scene:
    """One rendered test scene: images per frame, background, truth."""

    def __init__(self, body, cams, seed: int, t0: float, n_frames: int, contrast: float, noise: float):
        self.renderer = Renderer(body, cams, seed)
        self.cams = cams
        self.bg = {c.name: self.renderer.background(c) for c in cams}
        self.thetas = [pose_at(TEST_MOTION, t0 + k / FPS, body) for k in range(n_frames)]
        self.joints = body.joint_positions(np.array(self.thetas))
        self.contrast, self.noise, self.seed = contrast, noise, seed

    def images(self, k: int) -> dict[str, np.ndarray]:
        imgs = self.renderer.render(self.thetas[k], noise_sigma=2.0, frame_index=k)
        out = {}
        rng = np.random.default_rng([self.seed, k, 99])
        for c, im in zip(self.cams, imgs, strict=True):
            if self.contrast < 1.0 or self.noise > 0:
                bg = self.bg[c.name].astype(np.float32)
                im = bg + self.contrast * (im.astype(np.float32) - bg) + rng.normal(0, self.noise, im.shape)
                im = np.clip(np.rint(im), 0, 255).astype(np.uint8)
            out[c.name] = im
        return out

    def views(self, k: int, lcfg=None):
        ims = self.images(k)
        return [view_evidence(c, ims[c.name], self.bg[c.name], lcfg) for c in self.cams]


def plot(curves: dict[str, tuple[np.ndarray, np.ndarray]], xlabel: str, path: Path, title: str) -> None:
    """Mean ± sd curves (x = index) drawn with OpenCV."""
    w, h, m = 720, 420, 60
    img = np.full((h, w, 3), 255, np.uint8)
    ymax = max(float(np.nanmax(mu + sd)) for mu, sd in curves.values()) * 1.1
    n = max(len(mu) for mu, _ in curves.values())

    def px(i, v):
        return int(m + (w - 2 * m) * i / max(n - 1, 1)), int(h - m - (h - 2 * m) * min(v, ymax) / ymax)

    cv2.rectangle(img, (m, m), (w - m, h - m), (0, 0, 0), 1)
    for v in np.linspace(0, ymax, 6):
        cv2.putText(img, f"{v:.0f}", (5, px(0, v)[1] + 4), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (0, 0, 0), 1)
    cols = [(200, 60, 30), (30, 140, 30), (30, 30, 200), (150, 0, 150)]
    for ci, (name, (mu, sd)) in enumerate(curves.items()):
        col = cols[ci % len(cols)]
        pts = [px(i, v) for i, v in enumerate(mu) if np.isfinite(v)]
        for a, b in zip(pts[:-1], pts[1:], strict=True):
            cv2.line(img, a, b, col, 2, cv2.LINE_AA)
        for i, (v, s) in enumerate(zip(mu, sd, strict=True)):
            if np.isfinite(v):
                cv2.line(img, px(i, v - s), px(i, v + s), col, 1)
        cv2.putText(img, name, (m + 10, m + 20 + 18 * ci), cv2.FONT_HERSHEY_SIMPLEX, 0.5, col, 1, cv2.LINE_AA)
    cv2.putText(img, title, (m, 35), cv2.FONT_HERSHEY_SIMPLEX, 0.55, (0, 0, 0), 1, cv2.LINE_AA)
    cv2.putText(img, xlabel, (w // 2 - 40, h - 20), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (0, 0, 0), 1, cv2.LINE_AA)
    cv2.putText(img, "MPJPE mm", (5, m - 10), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (0, 0, 0), 1, cv2.LINE_AA)
    path.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(path), img)


RECOVERY_FRAMES = 30
CORRUPT_AT = 5
CORRUPT_SHIFT_M = 0.6
LOST_SCORE = -20.0    #: mean part log-likelihood below which the tracker declares itself lost (truth: ≈ −11)
REGAINED_MM = 200.0   #: a frame counts as regained below this MPJPE


def recovery(args, model, body, geo, cams, lik, results: dict) -> None:
    """Section 3: the tracker's belief is shifted by 0.6 m at frame 5; with loss detection (mean part
    log-likelihood < LOST_SCORE) it re-initialises from the shouters; frames until MPJPE < 200 mm."""
    variants = {"lost detection + re-init": LOST_SCORE, "no lost detection": None}
    errs = {v: np.full((args.recovery_seeds, RECOVERY_FRAMES), np.nan) for v in variants}
    regain = {v: [] for v in variants}
    for s in range(args.recovery_seeds):
        scene = Scene(body, cams, seed=200 + s, t0=TEST_START_S, n_frames=RECOVERY_FRAMES, contrast=1.0, noise=0.0)
        views = [scene.views(k) for k in range(RECOVERY_FRAMES)]
        p0, q0 = parts_from_theta(body, geo, scene.thetas[0])
        for v, lost in variants.items():
            bp = LooseLimbedBP(model, geo, lik, TRACK_NBP, seed=s)
            tr = LooseLimbedTracker(bp, Shouter(geo, lik, seed=s), TrackerConfig(
                init_iterations=args.iterations, track_iterations=args.track_iterations, lost_score=lost))
            tr.start_at(p0, q0)
            for k in range(RECOVERY_FRAMES):
                if k == CORRUPT_AT and tr.previous:
                    for b in tr.previous.values():
                        b.pos = b.pos + [CORRUPT_SHIFT_M, 0.0, 0.0]
                J = tr.step(views[k])
                errs[v][s, k] = mpjpe(J[None], scene.joints[k][None])[0]
            after = np.flatnonzero(errs[v][s, CORRUPT_AT:] < REGAINED_MM)
            regain[v].append(int(after[0]) if len(after) else None)
        print(f"recovery seed {s}: " + "  ".join(f"{v} regained after {regain[v][-1]} frames" for v in variants),
              file=sys.stderr, flush=True)
    print(f"\n3. Recovery: belief shifted {CORRUPT_SHIFT_M} m at frame {CORRUPT_AT}, {args.recovery_seeds} seeds, "
          f"normal contrast; 'regained' = MPJPE < {REGAINED_MM:.0f} mm")
    print("frame  " + "  ".join(f"{v:>26s}" for v in variants))
    for k in range(RECOVERY_FRAMES):
        print(f"{k:5d}  " + "  ".join(f"{np.nanmean(errs[v][:, k]):26.1f}" for v in variants))
    for v in variants:
        print(f"{v}: frames from the corruption until regained, per seed: {regain[v]}")
    plot({v: (np.nanmean(errs[v], axis=0), np.nanstd(errs[v], axis=0)) for v in variants}, "frame",
         args.out / "recovery_per_frame.png", f"Recovery: belief shifted {CORRUPT_SHIFT_M} m at frame {CORRUPT_AT}")
    results["recovery_frames_to_regain"] = regain


LOOP_SIZE = (320, 240)
LOOP_BLACKOUT = (2.5, 1.0)  #: s: start, length
LOOP_AFTER_S = 1.0          #: scene time after the blackout
LOOP_REGAIN = 10            #: the acceptance: tracking regained within this many frames


def _loop_run(body, model, cfg: SceneConfig, with_ll: bool, relocalise: bool, iterations: int, particles: int,
              seed: int, min_score: float, start: bool = False):
    """One closed-loop run of a blackout scene, ordered as the lockstep graph: the loose_limbed node infers
    on frame t if the skeleton's body of t-1 was LOST (InitialiserPolicy); its TRACKING body of t re-seeds
    the skeleton before the skeleton estimates t. Returns (status (N,), MPJPE mm (N,; inf while nothing is
    estimated), frames at which the skeleton was re-seeded, loose-limbed seconds)."""
    from artrack.loose_limbed_stage import InitialiserPolicy, LooseLimbedStage, StageConfig
    from artrack.pipeline import ClosedLoopPipeline, load_pipeline_config

    cams = scene_cameras(cfg)
    pipe = ClosedLoopPipeline(body, cams, load_pipeline_config())
    pipe.skeleton.estimator.cfg.tracking.relocalise_from_blobs = relocalise
    stage = LooseLimbedStage(body, pipe.cameras, model, StageConfig(init_iterations=iterations, n_particles=particles,
                                                                   seed=seed, min_score=min_score)) if with_ll else None
    policy = InitialiserPolicy(start=start)
    status, err, reseeds, t_ll = [], [], [], 0.0
    for fr in generate_scene(cfg, body, cams):
        if stage is not None:
            t0 = time.perf_counter()
            ll = policy.step(stage, fr.stamp_ns, fr.images)
            t_ll += time.perf_counter() - t0
            taken = ll is not None and ll.status == STATUS_TRACKING
            if taken and pipe.skeleton.estimator.reseed(ll.stamp_ns, ll.joints):
                reseeds.append(fr.index)
        est = pipe.step(fr.stamp_ns, fr.images).estimate
        policy.skeleton(est.status)
        status.append(est.status)
        ok = fr.joints is not None and np.isfinite(est.joints).all()
        err.append(float(np.linalg.norm(est.joints - fr.joints, axis=1).mean() * 1e3) if ok else np.inf)
    return np.array(status), np.array(err), reseeds, t_ll


def loop_recovery(args, model, body, results: dict) -> None:
    """Section 5: closed-loop recovery from a 1 s blackout, with and without the loose_limbed initialiser."""
    fps = FPS
    first, last = int(round(LOOP_BLACKOUT[0] * fps)), int(round(sum(LOOP_BLACKOUT) * fps))
    rows, out = [], {}
    for bg, empty_s in (("clean", 1.5), ("ghosts", 0.0)):
        for s in range(args.loop_seeds):
            cfg = SceneConfig(width=LOOP_SIZE[0], height=LOOP_SIZE[1], fps=fps, seed=3 + s, empty_s=empty_s,
                              duration_s=sum(LOOP_BLACKOUT) + LOOP_AFTER_S, blackout=LOOP_BLACKOUT)
            variants = (("without", False, True), ("with loose_limbed", True, True),
                        ("LL only (no relocal.)", True, False))
            for name, with_ll, relocalise in variants:
                t0 = time.perf_counter()
                st, err, reseeds, t_ll = _loop_run(body, model, cfg, with_ll, relocalise, args.iterations,
                                                   args.loop_particles, s, args.loop_min_score, args.loop_ll_start)
                pre = float(np.mean(err[first - 15:first]))
                bound = max(2.0 * pre, 200.0)
                ok = [i - last for i in range(last, len(st)) if st[i] == STATUS_TRACKING and err[i] < bound]
                regain = ok[0] if ok else None
                lost = [i for i in range(first, len(st)) if st[i] == STATUS_LOST]
                row = {"background": bg, "seed": cfg.seed, "variant": name, "pre_mm": round(pre, 1),
                       "bound_mm": round(bound, 1), "lost_at": lost[0] if lost else None,
                       "frames_to_regain": regain, "after_mm": round(float(np.mean(err[last:last + LOOP_REGAIN])), 1),
                       "end_mm": round(float(np.mean(err[-10:])), 1), "reseeded_at": reseeds,
                       "ll_s": round(t_ll, 1), "run_s": round(time.perf_counter() - t0, 1)}
                rows.append(row)
                print(f"loop {bg} seed {cfg.seed} {name}: regained after {regain} frames; MPJPE per frame from "
                      f"the blackout's end {np.round(err[last:]).tolist()}", file=sys.stderr, flush=True)
    print(f"\n5. Closed-loop recovery: every camera sees the empty room {LOOP_BLACKOUT[0]}-{sum(LOOP_BLACKOUT)} s "
          f"(frames {first}-{last - 1}), {LOOP_SIZE[0]}x{LOOP_SIZE[1]}, baseline skeleton; loose_limbed "
          f"{args.iterations} iterations x {args.loop_particles} particles, min_score {args.loop_min_score:g}")
    print("(LL only: the skeleton's own re-initialisation from blobs off, tracking.relocalise_from_blobs false)"
          + ("; the loose-limbed body also starts the skeleton (--loop-ll-start)" if args.loop_ll_start else ""))
    print("background  seed  variant                pre mm  bound mm  LOST at  frames to regain  after mm (10 fr)"
          "  last 10 fr mm  re-seeded at  LL s")
    for r in rows:
        print(f"{r['background']:10s}  {r['seed']:4d}  {r['variant']:21s}  {r['pre_mm']:6.1f}  {r['bound_mm']:8.1f}  "
              f"{r['lost_at']!s:>7s}  {r['frames_to_regain']!s:>16s}  {r['after_mm']:15.1f}  {r['end_mm']:13.1f}  "
              f"{str(r['reseeded_at']):>12s}  {r['ll_s']:4.1f}")
    for r in rows:
        key = {"without": "no_ll", "with loose_limbed": "ll"}.get(r["variant"], "ll_only")
        out.setdefault(f"{r['background']}_{key}", []).append(
            {k: r[k] for k in ("seed", "pre_mm", "frames_to_regain", "after_mm", "end_mm", "lost_at")})
    results["loop_recovery"] = out
    results["loop_recovery_setup"] = {"iterations": args.iterations, "particles": args.loop_particles,
                                      "min_score": args.loop_min_score, "regain_frames_target": LOOP_REGAIN}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="smoke run: 2 init scenes, 2 seeds x 8 frames")
    ap.add_argument("--retrain", action="store_true", help="re-learn the model file and exit")
    ap.add_argument("--model", type=Path, default=None, help="model YAML (default config/loose_limbed_model.yaml)")
    ap.add_argument("--init-scenes", type=int, default=5)
    ap.add_argument("--iterations", type=int, default=10, help="BP iterations for initialisation")
    ap.add_argument("--init-particles", type=int, default=100, help="belief samples per part for initialisation")
    ap.add_argument("--init-repeats", type=int, default=1,
                    help="runs per initialisation scene with different random streams (default 1)")
    ap.add_argument("--seeds", type=int, default=10, help="tracking seeds")
    ap.add_argument("--seed-start", type=int, default=0, help="first tracking seed (seeds start.. start+N-1)")
    ap.add_argument("--records", type=Path, default=None,
                    help="append each tracking seed's per-frame errors (JSON lines) to this file")
    ap.add_argument("--summarise-tracking", nargs="+", default=None, metavar="RECORDS",
                    help="print section 2 over the seeds in these records files (runs split over processes) and exit")
    ap.add_argument("--frames", type=int, default=50, help="tracking frames")
    ap.add_argument("--track-iterations", type=int, default=2, help="BP iterations per tracked frame")
    ap.add_argument("--size", default="640x480")
    ap.add_argument("--contrast", type=float, default=0.4, help="low-contrast factor of the tracking scenes")
    ap.add_argument("--noise", type=float, default=6.0, help="extra pixel noise sigma of the tracking scenes")
    ap.add_argument("--skip-apf", action="store_true", help="leave out the annealed filter")
    ap.add_argument("--recovery-seeds", type=int, default=2, help="seeds of the recovery run (section 3)")
    ap.add_argument("--loop-seeds", type=int, default=1, help="scene seeds of the closed-loop recovery (section 5; "
                    "0: skip)")
    ap.add_argument("--loop-particles", type=int, default=100, help="loose_limbed node particles in section 5")
    ap.add_argument("--loop-ll-start", action="store_true",
                    help="section 5: the loose-limbed body also starts the skeleton (node start_skeleton)")
    ap.add_argument("--loop-min-score", type=float, default=-14.5,
                    help="loose_limbed node min_score in section 5 (the node's default; -1000: no gate)")
    ap.add_argument("--out", type=Path, default=Path("out/loose_limbed"))
    args = ap.parse_args()
    path = args.model or default_model_path()
    if args.retrain:
        retrain(path)
        return 0
    if args.summarise_tracking:
        return summarise_tracking(args)
    if args.quick:
        args.init_scenes, args.seeds, args.frames, args.recovery_seeds = 2, 2, 8, 1
    try:
        model = load_model(path)
    except ArtrackError as exc:
        print(f"bench/loose_limbed.py: {exc}", file=sys.stderr)
        return 1
    width, height = (int(v) for v in args.size.split("x"))
    body = load_body_model()
    geo = part_geometry(body)
    cams = default_rig(4, width, height)
    lik = PartLikelihood(geo)
    results: dict = {"model": str(path), "size": args.size}

    # ---------------------------------------------------------------- 1. initialisation
    if args.init_scenes > 0:
        initialisation(args, model, body, geo, cams, lik, results)
    if args.seeds > 0:
        tracking(args, model, body, geo, cams, lik, results)
    if args.recovery_seeds > 0:
        recovery(args, model, body, geo, cams, lik, results)
    if args.loop_seeds > 0:
        loop_recovery(args, model, body, results)
    print(f"plots: {args.out / 'init_per_iteration.png'}, {args.out / 'tracking_per_frame.png'}")
    print(json.dumps({"loose_limbed": results}))
    return 0


def initialisation(args, model, body, geo, cams, lik, results: dict) -> None:
    """Section 1: automatic initialisation from no prior pose, error per BP iteration: the tracker's
    estimate (the joint MAP over the candidates so far, ``loose_limbed.MapAssembler``) and, for
    comparison, each part's marginal mode alone (``joints_estimate``). Each scene is run
    ``--init-repeats`` times with different random streams (seeds s + 1000 r)."""
    runs = [(s, r) for s in range(args.init_scenes) for r in range(args.init_repeats)]
    per_iter = np.full((len(runs), args.iterations), np.nan)
    per_iter_mode = np.full((len(runs), args.iterations), np.nan)
    mirrored = np.full(len(runs), np.nan)
    names = list(body.joint_names)
    mirror = [names.index(n.replace("l_", "#").replace("r_", "l_").replace("#", "r_")) for n in names]
    t_iter, t_shout, t_map, stage = [], [], [], {"likelihood": 0.0, "products": 0.0, "messages": 0.0}
    for k, (s, r) in enumerate(runs):
        if r == 0:
            scene = Scene(body, cams, seed=s, t0=TEST_START_S + 0.4 * s, n_frames=1, contrast=1.0, noise=0.0)
            views = scene.views(0)
        nbp = NBPConfig(n_particles=args.init_particles, n_exclusive=args.init_particles // 2)
        bp = LooseLimbedBP(model, geo, lik, nbp, seed=s + 1000 * r)
        tracker = LooseLimbedTracker(bp, Shouter(geo, lik, seed=s + 1000 * r),
                                     TrackerConfig(init_iterations=args.iterations))

        def cb(it, beliefs, assembler, k=k, scene=scene):
            e = np.linalg.norm(joints_estimate(geo, beliefs, 0) - scene.joints[0], axis=1) * 1000
            per_iter_mode[k, it] = float(np.nanmean(e))
            pos, quat = assembler.last
            per_iter[k, it] = mpjpe(joints_from_parts(geo, pos, quat)[None], scene.joints[0][None])[0]

        t0 = time.perf_counter()
        shouts = tracker.shouter.shout(views)
        t_shout.append(time.perf_counter() - t0)
        t0 = time.perf_counter()
        joints = tracker.initialise(views, callback=cb, shouts=shouts)
        t_iter.append((time.perf_counter() - t0) / args.iterations)
        t_map.append(tracker.map_seconds / args.iterations)
        mirrored[k] = mpjpe(joints[mirror][None], scene.joints[0][None])[0]
        for key in stage:
            stage[key] += bp.timing[key] / args.iterations / len(runs)
        print(f"init scene {s} run {r}: MAP " + " ".join(f"{v:.0f}" for v in per_iter[k]) + "  | marginal modes "
              + " ".join(f"{v:.0f}" for v in per_iter_mode[k]), file=sys.stderr, flush=True)
    mu, sd = np.nanmean(per_iter, axis=0), np.nanstd(per_iter, axis=0)
    mu_m, sd_m = np.nanmean(per_iter_mode, axis=0), np.nanstd(per_iter_mode, axis=0)
    final = per_iter[:, -1]
    print(f"\n1. Automatic initialisation from no prior pose ({args.init_scenes} scenes x {args.init_repeats} "
          f"random streams, {args.size}, 4 views)")
    print("iteration  MAP estimate: MPJPE mean (mm)  sd (mm)  | marginal modes: mean (mm)  sd (mm)")
    for it in range(args.iterations):
        print(f"{it:9d}  {mu[it]:29.1f}  {sd[it]:7.1f}  | {mu_m[it]:25.1f}  {sd_m[it]:7.1f}")
    print(f"last iteration: median {np.median(final):.1f} mm, {int(np.sum(final <= 120.0))} of {len(final)} runs "
          f"<= 120 mm; the estimate mirrored (left <-> right) would be nearer the truth in "
          f"{int(np.sum(mirrored < final))} runs")
    plot({"joint MAP (the estimate)": (mu, sd), "marginal modes": (mu_m, sd_m)}, "BP iteration",
         args.out / "init_per_iteration.png", "Initialisation error per BP iteration")
    results["init_runs"] = len(runs)
    results["init_mpjpe_per_iteration_mm"] = [round(float(v), 1) for v in mu]
    results["init_mpjpe_final_mm"] = round(float(mu[-1]), 1)
    results["init_mpjpe_final_median_mm"] = round(float(np.median(final)), 1)
    results["init_best_iteration_mm"] = round(float(np.nanmin(mu)), 1)
    results["init_marginal_modes_per_iteration_mm"] = [round(float(v), 1) for v in mu_m]
    results["time_per_bp_iteration_s"] = round(float(np.mean(t_iter)), 3)
    results["time_map_per_iteration_s"] = round(float(np.mean(t_map)), 3)
    results["time_shouters_s"] = round(float(np.mean(t_shout)), 3)
    results["time_per_iteration_stage_s"] = {k: round(v, 3) for k, v in stage.items()}


def tracking(args, model, body, geo, cams, lik, results: dict) -> None:
    """Section 2: 50-frame low-contrast tracking, three trackers, error per frame."""
    methods = ["LL + shouters", "LL, no shouters"] + ([] if args.skip_apf else ["annealed PF"])
    seeds = list(range(args.seed_start, args.seed_start + args.seeds))
    errs = {m: np.full((len(seeds), args.frames), np.nan) for m in methods}
    t_frame = {m: [] for m in methods}
    for row, s in enumerate(seeds):
        scene = Scene(body, cams, seed=100 + s, t0=TEST_START_S, n_frames=args.frames, contrast=args.contrast,
                      noise=args.noise)
        views = [scene.views(k) for k in range(args.frames)]
        p0, q0 = parts_from_theta(body, geo, scene.thetas[0])
        trackers = {}
        for m in methods[:2]:
            bp = LooseLimbedBP(model, geo, lik, TRACK_NBP, seed=s)
            tr = LooseLimbedTracker(bp, Shouter(geo, lik, TRACK_SHOUTER, seed=s),
                                    TrackerConfig(track_iterations=args.track_iterations,
                                                  use_shouters=(m == methods[0])))
            tr.start_at(p0, q0)
            trackers[m] = tr
        if not args.skip_apf:
            apf = AnnealedParticleFilter(body, geo, lik, AnnealingConfig(), seed=s)
            apf.start_at(scene.thetas[0])
        for k in range(args.frames):
            for m in methods:
                t0 = time.perf_counter()
                if m == "annealed PF":
                    J = body.joint_positions(apf.step(views[k]))
                else:
                    J = trackers[m].step(views[k])
                t_frame[m].append(time.perf_counter() - t0)
                errs[m][row, k] = mpjpe(J[None], scene.joints[k][None])[0]
        print(f"track seed {s}: " + "  ".join(f"{m} {np.nanmean(errs[m][row]):.0f}" for m in methods),
              file=sys.stderr, flush=True)
        if args.records:  # one line per seed: runs on several processes can be summarised together
            with open(args.records, "a") as fh:
                fh.write(json.dumps({"seed": s, "frames": args.frames, "contrast": args.contrast, "noise": args.noise,
                                     "errors_mm": {m: errs[m][row].tolist() for m in methods},
                                     "time_s": {m: t_frame[m][-args.frames:] for m in methods}}) + "\n")
    report_tracking(args, errs, t_frame, methods, len(seeds), results)


def report_tracking(args, errs: dict, t_frame: dict, methods: list, n_seeds: int, results: dict) -> None:
    """Section 2's table, plot and JSON fields from errors (seeds, frames) per method."""
    print(f"\n2. Tracking, low contrast (x{args.contrast}, +{args.noise} noise), {n_seeds} seeds x "
          f"{args.frames} frames, start from the true first pose")
    print("frame  " + "  ".join(f"{m:>22s}" for m in methods))
    for k in range(args.frames):
        print(f"{k:5d}  " + "  ".join(f"{np.nanmean(errs[m][:, k]):12.1f} ± {np.nanstd(errs[m][:, k]):6.1f}"
                                       for m in methods))
    skip = min(3, args.frames - 1)
    print(f"mean over frames {skip}..:  " + "  ".join(
        f"{m} {np.nanmean(errs[m][:, skip:]):.1f} mm" for m in methods))
    print("time per frame (s):  " + "  ".join(f"{m} {np.mean(t_frame[m]):.2f}" for m in methods))
    plot({m: (np.nanmean(errs[m], axis=0), np.nanstd(errs[m], axis=0)) for m in methods}, "frame",
         args.out / "tracking_per_frame.png", "Low-contrast tracking, mean +- sd over seeds")
    results["tracking_mean_mm_after_frame3"] = {m: round(float(np.nanmean(errs[m][:, skip:])), 1) for m in methods}
    results["tracking_time_per_frame_s"] = {m: round(float(np.mean(t_frame[m])), 2) for m in methods}
    results["tracking_seeds"], results["tracking_frames"] = n_seeds, args.frames


def summarise_tracking(args) -> int:
    """Section 2 over the records of one or more runs (--records), one row per seed."""
    try:
        recs = [json.loads(line) for path in args.summarise_tracking
                for line in Path(path).read_text().splitlines() if line.strip()]
        recs = list({r["seed"]: r for r in recs}.values())  # a seed run twice counts once
        methods = list(recs[0]["errors_mm"])
        args.frames, args.contrast, args.noise = recs[0]["frames"], recs[0]["contrast"], recs[0]["noise"]
        errs = {m: np.array([r["errors_mm"][m] for r in recs], float) for m in methods}
        t_frame = {m: [t for r in recs for t in r["time_s"][m]] for m in methods}
    except (OSError, ValueError, KeyError, IndexError) as exc:
        print(f"bench/loose_limbed.py: --summarise-tracking: {exc}", file=sys.stderr)
        return 1
    results: dict = {"tracking_seed_list": sorted(r["seed"] for r in recs)}
    args.out.mkdir(parents=True, exist_ok=True)
    report_tracking(args, errs, t_frame, methods, len(recs), results)
    print(json.dumps({"loose_limbed": results}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
