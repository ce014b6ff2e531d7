#!/usr/bin/env python3
"""Particle filtering with spatial priors and a held stick (ALGORITHMS.md §3): error and time per
prior on synthetic RGB-D scenes with ground truth.

Scenes (``artrack.stick_scene``): one RGB-D camera 2.6 m in front of a standing person holding a
stick in both hands; ``stick_side`` (side to side, then overhead and behind the head, 5 s) and
``stick_sword`` (sword-like slashes, 3.2 s); depth noise σ_z = 0.002·z² with 5 % dropouts and
missing depth edges; the points pass a workspace box around the person (no floor, no walls).
Each seed changes the depth noise and dropouts and the filter's random numbers; the motions are
the same. The filter (``artrack.particles.ParticleFilter``) starts from the true first pose and the
true hand positions on the stick, as the paper's did. ``p_stick3d`` gets the true 3-D stick each
frame; ``p_stick2d`` the 2-D stick detector's ends on the rendered colour image (``artrack.
stick_detection``, what the object_features node runs; a frame without a detection falls back to
``p_proj``), or with ``--stick2d-source projection`` the true ends projected plus 1 px noise.

Per prior and motion (mean ± standard deviation over seeds of the per-sequence means):
  marker cm   eq. (10): distance of 16 markers on the arms' skin (true pose) to the estimated
              capsule skin, averaged over frames (the paper's measure);
  MPJPE mm    the 15 output joints; arms mm: elbows and wrists only;
  s/frame     CPU seconds per frame (prior + likelihood, one core: BLAS/OpenMP limited to one
              thread); cv = the frame-to-frame coefficient of variation of that time,
              also for the prior and the likelihood alone (the likelihood does the same
              work every frame — 400 points x 500 particles — so its cv is the machine's
              timing noise: a prior with the same cv costs the same every frame);
  hand mm     mean distance of the particles' hands to the stick after the prior;
  capped      p_kkb: mean (max over frames) share of particles that hit 5000 rejections.

Ends with one JSON line. Progress on stderr. Run from the repository root::

    .venv/bin/python bench/particles.py --quick                 # smoke run, ~30 s
    .venv/bin/python bench/particles.py                         # 5 seeds x 2 motions x 5 priors, 500 particles
    .venv/bin/python bench/particles.py --jobs 2                # the same on two processes (one core each)
    .venv/bin/python bench/particles.py --records R.jsonl       # also keep every sequence's per-frame record
    .venv/bin/python bench/particles.py --summarise R.jsonl     # the table of the sequences recorded so far

Sequences run seed by seed (both motions of seed 0, then seed 1, ...), so a run stopped early
still has the same seeds for both motions; --summarise then reports those.
"""

from __future__ import annotations

import os

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ[_v] = "1"  # one core per process: set before numpy is imported

import sys  # noqa: E402
from pathlib import Path  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "src" / "artrack_nodes"))

import argparse  # noqa: E402
import json  # noqa: E402
import time  # noqa: E402
from multiprocessing import Pool  # noqa: E402

import numpy as np  # noqa: E402

from artrack.body_model import load_body_model  # noqa: E402
from artrack.particles import PRIORS, ParticleConfig, ParticleFilter, Stick2D, Stick3D, gamma_on_stick  # noqa: E402
from artrack.pointcloud import crop_box, marker_error, workspace_box, world_from_camera_points  # noqa: E402
from artrack.pose_manifold import PoseManifold  # noqa: E402
from artrack.realtime import keep_freed_memory  # noqa: E402
from artrack.stick_detection import detect_stick  # noqa: E402
from artrack.stick_scene import STICK_MOTIONS, generate_stick_scene, rgbd_camera  # noqa: E402

ARM_JOINTS = ("l_elbow", "l_wrist", "r_elbow", "r_wrist")


def run_sequence(task: tuple) -> list[dict]:
    """All priors on one (motion, seed) scene; returns one record per prior."""
    motion, seed, priors, n_particles, fps, duration, overrides, records_path, stick2d_source = task
    keep_freed_memory()  # steady cost per frame (see artrack/realtime.py); per process (--jobs)
    body = load_body_model()
    cam = rgbd_camera()
    detect = "stick2d" in priors and stick2d_source == "detector"
    frames = list(generate_stick_scene(motion, seed=seed, fps=fps, duration_s=duration, camera=cam, colour=detect))
    lo, hi = workspace_box(frames[0].theta[:3])
    clouds = [crop_box(world_from_camera_points(cam, f.points_cam), lo, hi) for f in frames]
    rng = np.random.default_rng([seed, 2024])
    sticks2d, stick2d_err = [], []
    for f in frames:
        uv, _ = cam.project(f.stick)
        if detect:   # the 2-D stick detector on the rendered colour image (what object_features runs)
            d = detect_stick(f.image)
            sticks2d.append(None if d is None else Stick2D(d.a_uv, d.b_uv, cam))
            if d is not None:   # end-point error in px, of the better of the two orders
                e = np.stack([np.linalg.norm(np.stack([d.a_uv, d.b_uv]) - uv, axis=1),
                              np.linalg.norm(np.stack([d.b_uv, d.a_uv]) - uv, axis=1)]).mean(axis=1)
                stick2d_err.append(float(e.min()))
        else:
            uv = uv + rng.normal(0.0, 1.0, uv.shape)
            sticks2d.append(Stick2D(uv[0], uv[1], cam))
    M = PoseManifold(body, frames[0].theta)
    gamma0 = gamma_on_stick(frames[0].stick[0], frames[0].stick[1], M.hands(M.active(frames[0].theta)[None])[0])
    arm = [body.joint_names.index(j) for j in ARM_JOINTS]
    out = []
    for prior in priors:
        cfg = ParticleConfig(prior=prior, n_particles=n_particles, seed=seed, **overrides)
        pf = ParticleFilter(body, frames[0].theta, cfg, gamma0)
        rec = {"motion": motion, "seed": seed, "prior": prior, "marker_m": [], "mpjpe_m": [], "arms_m": [],
               "cpu_s": [], "prior_s": [], "likelihood_s": [], "hand_m": [], "capped": []}
        for k, f in enumerate(frames[1:], start=1):
            stick = sticks2d[k] if prior == "stick2d" else Stick3D(f.stick[0], f.stick[1])
            t0 = time.process_time()
            est, st = pf.step(clouds[k], cam.center, stick)
            rec["cpu_s"].append(time.process_time() - t0)
            rec["prior_s"].append(st.prior_s)
            rec["likelihood_s"].append(st.likelihood_s)
            err = np.linalg.norm(body.joint_positions(est) - f.joints, axis=1)
            rec["marker_m"].append(marker_error(body, est, f.theta))
            rec["mpjpe_m"].append(float(err.mean()))
            rec["arms_m"].append(float(err[arm].mean()))
            rec["hand_m"].append(st.hand_stick_distance)
            rec["capped"].append(st.kkb_capped_share)
        print(f"  {motion} seed {seed} {prior}: marker {np.mean(rec['marker_m']) * 100:.2f} cm, "
              f"{np.mean(rec['cpu_s']):.3f} s/frame", file=sys.stderr, flush=True)
        rec.update(n_particles=n_particles, fps=fps, overrides=overrides)
        if prior == "stick2d":
            rec.update(stick2d_source=stick2d_source,
                       stick2d_detected=sum(x is not None for x in sticks2d[1:]) / max(1, len(frames) - 1),
                       stick2d_end_px=float(np.mean(stick2d_err)) if stick2d_err else float("nan"))
        out.append(rec)
        if records_path:
            with open(records_path, "a") as fh:  # one short line per record: appends do not interleave
                fh.write(json.dumps(rec) + "\n")
    return out


def summarise(records: list[dict], motions, priors) -> list[dict]:
    import warnings

    warnings.simplefilter("ignore", RuntimeWarning)  # nanmean of p_stick2d's hand distances (no 3-D stick)
    rows = []
    for motion in motions:
        for prior in priors:
            rs = [r for r in records if r["motion"] == motion and r["prior"] == prior]
            if not rs:
                continue
            per = {k: np.array([np.nanmean(r[k]) for r in rs]) for k in ("marker_m", "mpjpe_m", "arms_m", "cpu_s",
                                                                         "hand_m")}
            cpu = np.concatenate([r["cpu_s"] for r in rs])
            cv = float(np.mean([np.std(r["cpu_s"]) / np.mean(r["cpu_s"]) for r in rs]))
            cvs = {k: float(np.mean([np.std(r[k]) / np.mean(r[k]) for r in rs])) if k in rs[0] else float("nan")
                   for k in ("prior_s", "likelihood_s")}
            capped = np.concatenate([r["capped"] for r in rs]) if prior == "kkb" else np.array([np.nan])
            rows.append({
                "motion": motion, "prior": prior, "seeds": len(rs), "frames": len(rs[0]["cpu_s"]),
                "marker_cm": round(float(per["marker_m"].mean()) * 100, 2),
                "marker_cm_sd": round(float(per["marker_m"].std()) * 100, 2),
                "mpjpe_mm": round(float(per["mpjpe_m"].mean()) * 1000, 1),
                "mpjpe_mm_sd": round(float(per["mpjpe_m"].std()) * 1000, 1),
                "arms_mm": round(float(per["arms_m"].mean()) * 1000, 1),
                "s_per_frame": round(float(cpu.mean()), 3),
                "s_per_frame_max": round(float(cpu.max()), 3),
                "time_cv": round(cv, 3),
                "s_per_frame_median": round(float(np.median(cpu)), 3),
                "prior_cv": round(cvs["prior_s"], 3),
                "likelihood_cv": round(cvs["likelihood_s"], 3),
                "hand_stick_mm": round(float(per["hand_m"].mean()) * 1000, 1),
                "stick2d_detected": (round(float(np.mean([r["stick2d_detected"] for r in rs])), 3)
                                     if "stick2d_detected" in rs[0] else None),
                "stick2d_end_px": (round(float(np.nanmean([r["stick2d_end_px"] for r in rs])), 2)
                                   if "stick2d_end_px" in rs[0] else None),
                "kkb_capped_share": None if prior != "kkb" else round(float(np.nanmean(capped)), 4),
                "kkb_capped_share_max": None if prior != "kkb" else round(float(np.nanmax(capped)), 4),
            })
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seeds", type=int, default=5, help="number of seeds 0..N-1 (default 5)")
    ap.add_argument("--motions", nargs="+", default=list(STICK_MOTIONS), choices=STICK_MOTIONS)
    ap.add_argument("--priors", nargs="+", default=list(PRIORS), choices=PRIORS)
    ap.add_argument("--particles", type=int, default=500)
    ap.add_argument("--fps", type=float, default=15.0, help="camera frame rate (default 15, as the paper)")
    ap.add_argument("--duration", type=float, default=None, help="seconds per motion (default: the whole motion)")
    ap.add_argument("--jobs", type=int, default=1, help="parallel processes, one (motion, seed) each")
    ap.add_argument("--stick2d-source", default="detector", choices=["detector", "projection"],
                    help="p_stick2d's stick image: the 2-D detector on the rendered colour images (default) or "
                         "the true ends projected plus 1 px noise")
    ap.add_argument("--set", action="append", default=[], metavar="FIELD=VALUE",
                    help="override a ParticleConfig field for every prior (e.g. likelihood_sigma=0.03)")
    ap.add_argument("--quick", action="store_true", help="smoke run: 1 seed, 1 s per motion, 200 particles")
    ap.add_argument("--records", default=None, help="append every sequence's record (JSON lines) to this file")
    ap.add_argument("--summarise", default=None, metavar="RECORDS",
                    help="print the table of a records file (complete seeds only) instead of running")
    args = ap.parse_args()
    if args.summarise:
        summarise_file(args.summarise)
        return
    if args.quick:
        args.seeds, args.duration, args.particles = 1, 1.0, 200
    if args.seeds < 1 or args.particles < 1 or args.fps <= 0 or (args.duration is not None and args.duration <= 0):
        print("bench/particles.py: --seeds, --particles, --fps and --duration must be positive", file=sys.stderr)
        sys.exit(1)
    overrides = {}
    for item in args.set:
        key, _, value = item.partition("=")
        kind = type(getattr(ParticleConfig(), key, None))
        try:
            if key in ("prior", "n_particles", "seed"):
                raise ValueError("use --priors, --particles, --seeds")
            if kind not in (int, float, str) or not value:
                raise ValueError("expected FIELD=VALUE with a number or text field of ParticleConfig")
            overrides[key] = kind(value)
            ParticleConfig(**overrides).check()
        except ValueError as exc:
            print(f"bench/particles.py: --set {item}: {exc}", file=sys.stderr)
            sys.exit(1)
    tasks = [(m, s, args.priors, args.particles, args.fps, args.duration, overrides, args.records,
              args.stick2d_source)
             for s in range(args.seeds) for m in args.motions]
    t0 = time.perf_counter()
    if args.jobs > 1:
        with Pool(args.jobs) as pool:
            chunks = pool.map(run_sequence, tasks, chunksize=1)
    else:
        chunks = [run_sequence(t) for t in tasks]
    records = [r for c in chunks for r in c]
    report(records, args.motions, args.priors, args.particles, args.seeds, args.fps,
           f"wall {time.perf_counter() - t0:.0f} s ({args.jobs} job(s))")


def summarise_file(path: str) -> None:
    """The table of a records file, over the seeds complete for every motion and prior found."""
    try:
        records = [json.loads(line) for line in Path(path).read_text().splitlines() if line.strip()]
    except (OSError, json.JSONDecodeError) as exc:
        print(f"bench/particles.py: {path}: {exc}", file=sys.stderr)
        sys.exit(1)
    if not records:
        print(f"bench/particles.py: {path}: no records", file=sys.stderr)
        sys.exit(1)
    motions = [m for m in STICK_MOTIONS if any(r["motion"] == m for r in records)]
    priors = [p for p in PRIORS if any(r["prior"] == p for r in records)]
    have = {(r["motion"], r["seed"], r["prior"]) for r in records}
    seeds = sorted({r["seed"] for r in records if all((m, r["seed"], p) in have for m in motions for p in priors)})
    records = [r for r in records if r["seed"] in seeds]
    report(records, motions, priors, records[0]["n_particles"], len(seeds), records[0]["fps"],
           f"seeds {seeds} from {path}")


def report(records, motions, priors, n_particles, n_seeds, fps, note: str) -> None:
    rows = summarise(records, motions, priors)
    print(f"§3 particle filter: {n_particles} particles, {n_seeds} seed(s), {fps:g} fps, {note}")
    head = (f"{'motion':<12} {'prior':<8} {'marker cm':>13} {'MPJPE mm':>13} {'arms mm':>8} {'s/frame':>8} "
            f"{'max s':>6} {'cv':>5} {'prior cv':>8} {'lik cv':>6} {'hand mm':>8} {'capped':>14}")
    print(head)
    print("-" * len(head))
    for r in rows:
        capped = ("" if r["kkb_capped_share"] is None
                  else f"{r['kkb_capped_share']:.3f} ({r['kkb_capped_share_max']:.2f})")
        print(f"{r['motion']:<12} {r['prior']:<8} {r['marker_cm']:>6.2f} ± {r['marker_cm_sd']:<4.2f} "
              f"{r['mpjpe_mm']:>6.1f} ± {r['mpjpe_mm_sd']:<4.1f} {r['arms_mm']:>8.1f} {r['s_per_frame']:>8.3f} "
              f"{r['s_per_frame_max']:>6.2f} {r['time_cv']:>5.2f} {r['prior_cv']:>8.2f} {r['likelihood_cv']:>6.2f} "
              f"{r['hand_stick_mm']:>8.1f} {capped:>14}")
    for r in rows:
        if r["stick2d_detected"] is not None:
            print(f"{r['motion']}: p_stick2d from the 2-D detector: stick found in {100 * r['stick2d_detected']:.0f} % "
                  f"of frames, ends {r['stick2d_end_px']:.2f} px from the true projection")
    ratios = {}
    for m in motions:
        k = {r["prior"]: r["s_per_frame"] for r in rows if r["motion"] == m}
        if "kkb" in k and "stick3d" in k:
            ratios[m] = round(k["kkb"] / k["stick3d"], 2)
            print(f"{m}: p_kkb / p_stick3d time per frame = {ratios[m]:.2f}")
    print(json.dumps({"particles": rows, "kkb_over_stick3d_time": ratios, "n_particles": n_particles,
                      "seeds": n_seeds, "fps": fps, "note": note}))


if __name__ == "__main__":
    main()
