"""The `artrack` command: synth, track, bag-from-videos, eval, overlay, launch.

    artrack synth --seed N --out scene.mcap [options]
    artrack track INPUT --out DIR [--allow-truncated]     (INPUT a bag)
    artrack track --videos V1 V2 ... --calib FILE --out DIR
    artrack bag-from-videos --videos V1 V2 ... --calib FILE --out recording.mcap [--scale S]
    artrack eval --truth BAG_OR_CSV --pred DIR_OR_BAG      (prints "MPJPE <x> mm")
    artrack overlay INPUT --pred DIR_OR_BAG --out montage.png|video.mp4
    artrack launch config/graph.yaml [--set key=value ...]

Bad input is one line on stderr naming the file and field, exit status 1,
and no half-written output.
"""

from __future__ import annotations

import argparse
import math
import os
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from .errors import ArtrackError, InputError, check_output_path
from .progress import Progress

TRACK_BAG = "track"  # rosbag2 folder written by `artrack track` inside --out
JOINTS_CSV = "joints.csv"


# ------------------------------------------------------------------ synth


def _check_synth_args(args: argparse.Namespace) -> None:
    if args.cameras < 1:
        raise InputError(f"--cameras {args.cameras}: need at least one camera")
    for opt in ("width", "height"):
        if getattr(args, opt) < 1:
            raise InputError(f"--{opt} {getattr(args, opt)}: must be a positive number of pixels")
    for opt in ("fps", "duration"):
        v = getattr(args, opt)
        if not (math.isfinite(v) and v > 0):
            raise InputError(f"--{opt} {v:g}: must be positive")
    if round(args.duration * args.fps) < 1:
        raise InputError(f"--duration {args.duration:g}: shorter than one frame at --fps {args.fps:g}")
    if not (math.isfinite(args.empty_start) and 0 <= args.empty_start < args.duration):
        raise InputError(f"--empty-start {args.empty_start:g}: must be >= 0 and shorter than --duration")
    if not (math.isfinite(args.noise) and args.noise >= 0):
        raise InputError(f"--noise {args.noise:g}: must be >= 0")


def _parse_blackout(text: str, duration: float) -> tuple[float, float]:
    """--blackout START:SECONDS -> (start_s, seconds); InputError unless both are finite, start >= 0,
    seconds > 0 and the span starts inside the scene."""
    try:
        start, seconds = (float(x) for x in text.split(":"))
    except ValueError:
        raise InputError(f"--blackout {text}: expected START:SECONDS, e.g. 2.0:1.0") from None
    if not (math.isfinite(start) and math.isfinite(seconds) and 0 <= start < duration and seconds > 0):
        raise InputError(f"--blackout {text}: need 0 <= START < --duration and SECONDS > 0")
    return start, seconds


def cmd_synth(args: argparse.Namespace) -> int:
    """`artrack synth`: render a synthetic scene with ground truth into a bag."""
    from .bags import write_scene_bag
    from .body_model import load_body_model
    from .synth import SceneConfig, generate_scene, scene_cameras

    _check_synth_args(args)
    blackout = _parse_blackout(args.blackout, args.duration) if args.blackout else None
    if args.motion.startswith("stick_"):
        return _synth_stick(args)
    config = SceneConfig(
        n_cameras=args.cameras, width=args.width, height=args.height, fps=args.fps, duration_s=args.duration,
        seed=args.seed, noise_sigma=args.noise, motion=args.motion, occlusion=args.occlusion,
        distractor=args.distractor, empty_s=args.empty_start, blackout=blackout,
    )
    body = load_body_model(args.body_model)
    cameras = scene_cameras(config)
    n_frames = int(round(config.duration_s * config.fps))
    frames = Progress(generate_scene(config, body), total=n_frames, label="synth", quiet=args.quiet)
    write_scene_bag(args.out, cameras, frames, joint_names=body.joint_names, image_format=args.image_format)
    print(f"wrote {args.out}: {n_frames} frames x {len(cameras)} cameras")
    return 0


def _synth_stick(args: argparse.Namespace) -> int:
    """A stick motion (ALGORITHMS.md §3): one RGB-D camera, points and the stick pose in the bag."""
    from .bags import write_scene_bag
    from .body_model import load_body_model
    from .messages import rosbags_factory
    from .stick_scene import (
        STICK_MOTIONS,
        STICK_TOPIC,
        generate_stick_scene,
        points_topic,
        rgbd_camera,
        scene_bag_messages,
    )

    if args.motion not in STICK_MOTIONS:
        raise InputError(f"--motion {args.motion}: unknown stick motion (expected one of {', '.join(STICK_MOTIONS)})")
    body = load_body_model(args.body_model)
    cam = rgbd_camera(args.width, args.height)
    f = rosbags_factory()
    n_frames = int(round(args.duration * args.fps))

    def frames():
        for fr in generate_stick_scene(args.motion, seed=args.seed, fps=args.fps, duration_s=args.duration,
                                       camera=cam, body=body, pixel_noise=args.noise):
            fr.extra_messages = scene_bag_messages(fr, cam, f)
            yield fr

    write_scene_bag(args.out, [cam], Progress(frames(), total=n_frames, label="synth", quiet=args.quiet),
                    joint_names=body.joint_names, image_format=args.image_format,
                    extra_topics={points_topic(cam.name): "sensor_msgs/msg/PointCloud2",
                                  STICK_TOPIC: "geometry_msgs/msg/PoseStamped"})
    print(f"wrote {args.out}: {n_frames} frames of camera {cam.name} (RGB-D) with {STICK_TOPIC}")
    return 0


# ------------------------------------------------------------------ track


def _open_input(args: argparse.Namespace):
    """(cameras, frame iterator of (stamp_ns, {camera: image}), n_frames or None, fps or None)."""
    if args.videos:
        videos = _open_video_input(args)
        frames = ((stamp, images) for _, stamp, images in videos)
        return list(videos.cameras), frames, videos.n_frames or None, videos.fps
    if not args.input:
        raise ArtrackError("give a bag (INPUT) or --videos ... --calib FILE")
    from .bags import read_scene

    scene = read_scene(args.input, allow_truncated=args.allow_truncated)
    if scene.truncated:
        print(f"artrack track: warning: {args.input}: {scene.problem}; tracking the readable part",
              file=sys.stderr)
    cameras = scene.cameras
    if args.camera_names:
        missing = [n for n in args.camera_names if n not in {c.name for c in cameras}]
        if missing:
            raise ArtrackError(f"{args.input}: no camera named '{missing[0]}'")
        cameras = [c for c in cameras if c.name in args.camera_names]
    names = {c.name for c in cameras}
    frames = ((stamp, {n: im for n, im in images.items() if n in names}) for stamp, images in scene.frames())
    return cameras, frames, scene.n_frames, None


def _check_track_out(out: Path) -> None:
    """Refuse an --out we could not (or must not) fill, before any work is done."""
    from .bags import looks_like_bag_dir

    if (out.exists() or out.is_symlink()) and not out.is_dir():
        raise InputError(f"{out}: exists and is not a directory")
    if out.is_dir():
        bag = out / TRACK_BAG
        if (bag.exists() or bag.is_symlink()) and not (bag.is_dir() and looks_like_bag_dir(bag)):
            raise InputError(f"{bag}: exists and is not a rosbag2 directory; not overwriting")
        if (out / JOINTS_CSV).is_dir():
            raise InputError(f"{out / JOINTS_CSV}: is a directory; not overwriting")
    check_output_path(out)


def _start_track_out(out: Path) -> tuple[Path, list[Path]]:
    """A hidden temporary sibling of --out to write into, and the parent folders created for it."""
    created = [a for a in reversed(out.parents) if not (a.exists() or a.is_symlink())]
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
        tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.", suffix=".tmp", dir=out.parent))
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o777 & ~umask)  # the folder becomes --out: usual permissions, not mkdtemp's 0700
    except OSError as exc:
        _remove_empty_dirs(created)
        raise InputError(f"{out}: cannot create output ({exc.strerror or exc})") from None
    return tmp, created


def _remove_empty_dirs(dirs: list[Path]) -> None:
    for d in reversed(dirs):  # innermost first
        try:
            d.rmdir()
        except OSError:
            break


def _finish_track_out(tmp: Path, out: Path) -> None:
    """Move the finished output into place: the whole folder, or, into an existing --out folder,
    its track/ bag (replacing an older one) and joints.csv; other files there are left alone."""
    try:
        if not (out.exists() or out.is_symlink()):
            os.rename(tmp, out)
            return
        for name in (TRACK_BAG, JOINTS_CSV):
            dst = out / name
            if dst.is_dir() and not dst.is_symlink():
                os.rename(dst, tmp / f".old.{name}")
            os.replace(tmp / name, dst)
    except OSError as exc:
        raise InputError(f"{out}: cannot move the output into place ({exc.strerror or exc})") from None
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def cmd_track(args: argparse.Namespace) -> int:
    """`artrack track`: the closed loop offline over a bag or videos (the graph's core, one process)."""
    for flag, value in (("--refine-passes", args.refine_passes), ("--refine-min-interval", args.refine_min_interval),
                        ("--startup-refine-frames", args.startup_refine_frames),
                        ("--startup-refine-passes", args.startup_refine_passes)):
        if not value >= 0:
            raise InputError(f"{flag} {value:g}: must be >= 0")
    out = Path(args.out)
    _check_track_out(out)
    cameras, frames, total, input_fps = _open_input(args)
    from .body_model import load_body_model  # after the input checks: bad input fails fast
    from .pipeline import ClosedLoopPipeline, load_pipeline_config

    body = load_body_model(args.body_model)
    fps = args.fps or input_fps or 30.0
    config = load_pipeline_config(estimator=args.estimator, feedback=not args.no_feedback, fps=fps,
                                  blob_config=args.blob_config, skeleton_config=args.skeleton_config,
                                  edges=args.edges, edge_config=args.edge_config)
    config.refine_passes, config.refine_min_interval_s = args.refine_passes, args.refine_min_interval
    config.startup_refine_frames, config.startup_refine_passes = args.startup_refine_frames, args.startup_refine_passes
    pipe = ClosedLoopPipeline(body, cameras, config)
    tmp, created = _start_track_out(out)
    try:
        _track_into(tmp, args, pipe, body, config, frames, total)
        _finish_track_out(tmp, out)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        _remove_empty_dirs(created)
        raise
    print(f"wrote {out / TRACK_BAG} and {out / JOINTS_CSV}")
    return 0


def _track_into(out: Path, args: argparse.Namespace, pipe, body, config, frames, total) -> None:
    """Run the closed loop over ``frames``, writing ``out``/track (bag) and ``out``/joints.csv."""
    from .bags import BagWriter
    from .evaluation import write_joints_csv
    from .messages import blob_array_msg, body_msg, prior_array_msg, rosbags_factory

    f = rosbags_factory()
    stamps, joints = [], []
    stage_ms: dict[str, list[float]] = {}
    t0 = time.perf_counter()
    with BagWriter(out / TRACK_BAG) as bag:
        bag.add_topic("/artrack/body", "artrack_msgs/msg/TrackedBody")
        bag.add_topic("/artrack/prediction", "artrack_msgs/msg/TrackedBody")
        for cam in pipe.cameras:
            bag.add_topic(f"/cameras/{cam.name}/blobs", "artrack_msgs/msg/Blob2DArray")
            bag.add_topic(f"/cameras/{cam.name}/blob_priors", "artrack_msgs/msg/BlobPrior2DArray")
        for stamp, images in Progress(frames, total=total, label="track", quiet=args.quiet):
            if args.max_frames and len(stamps) >= args.max_frames:
                break
            res = pipe.step(stamp, images)
            for k, v in res.timings_ms.items():
                stage_ms.setdefault(k, []).append(v)
            for cam in pipe.cameras:
                if cam.name in res.blobs:
                    used = res.priors_used.get(cam.name)
                    prior_stamp = used[0].stamp_ns if used else None
                    bag.write(f"/cameras/{cam.name}/blobs", stamp,
                              blob_array_msg(f, stamp, cam.name, cam.frame_id, res.blobs[cam.name], prior_stamp))
                bag.write(f"/cameras/{cam.name}/blob_priors", stamp,
                          prior_array_msg(f, res.prediction.stamp_ns, cam.name, cam.frame_id,
                                          res.next_priors.get(cam.name, [])))
            bag.write("/artrack/prediction", stamp, body_msg(f, res.prediction))
            bag.write("/artrack/body", stamp, body_msg(f, res.estimate))
            stamps.append(stamp)
            joints.append(res.estimate.joints)
    elapsed = time.perf_counter() - t0
    if not stamps:
        raise ArtrackError(f"{args.input or args.videos[0]}: no frames")
    write_joints_csv(out / JOINTS_CSV, stamps, body.joint_names, np.asarray(joints))
    print(f"tracked {len(stamps)} frames in {elapsed:.1f} s: {len(stamps) / elapsed:.1f} frames per second")
    print("per-stage ms/frame: " + ", ".join(f"{k} {np.mean(v):.2f}" for k, v in stage_ms.items()))


# -------------------------------------------------------- bag-from-videos


def _open_video_input(args: argparse.Namespace):
    """The --videos / --calib / --camera-names / --scale / --fps of `track` and `bag-from-videos`:
    a :class:`artrack.video.VideoSet` (working-resolution cameras, stamps from the frame rate)."""
    from .cameras import load_calibration
    from .video import open_videos

    if not args.calib:
        raise ArtrackError("--videos needs --calib FILE")
    cameras = load_calibration(args.calib)
    if args.camera_names:
        by_name = {c.name: c for c in cameras}
        for n in args.camera_names:
            if n not in by_name:
                raise ArtrackError(f"{args.calib}: no camera named '{n}'")
        cameras = [by_name[n] for n in args.camera_names]
    if len(cameras) < len(args.videos):
        raise ArtrackError(f"{args.calib}: {len(cameras)} cameras for {len(args.videos)} videos")
    return open_videos(args.videos, cameras[: len(args.videos)], args.scale, fps=args.fps,
                       max_frames=getattr(args, "max_frames", None) or None)


def cmd_bag_from_videos(args: argparse.Namespace) -> int:
    """Synchronised videos + calibration -> rosbag2 .mcap: per camera CompressedImage on
    /cameras/<cam>/image_raw/compressed, CameraInfo (working resolution) and the extrinsics,
    stamped ``index / fps`` (the layout `artrack synth` writes, without ground truth)."""
    from types import SimpleNamespace

    from .bags import write_scene_bag

    videos = _open_video_input(args)
    frames = (SimpleNamespace(stamp_ns=stamp, images=images, joints=None) for _, stamp, images in videos)
    n = write_scene_bag(args.out, videos.cameras, Progress(frames, total=len(videos) or None, label="bag",
                                                           quiet=args.quiet),
                        truth=False, image_format=args.image_format)
    if n == 0:
        out = Path(args.out)
        shutil.rmtree(out, ignore_errors=True) if out.is_dir() else out.unlink(missing_ok=True)
        raise InputError(f"{args.videos[0]}: no frames")
    size = videos.cameras[0]
    print(f"wrote {args.out}: {n} frames x {len(videos.cameras)} cameras at {size.width}x{size.height}, "
          f"{videos.fps:g} frames per second")
    return 0


# ------------------------------------------------------------------- eval


def load_predictions(path: str):
    """(stamps, joint_names, joints (T, J, 3)) from a track DIR (joints.csv or its bag) or an output bag."""
    from .evaluation import read_body_topic, read_joints_csv

    p = Path(path)
    if p.is_dir() and (p / JOINTS_CSV).is_file():
        return read_joints_csv(p / JOINTS_CSV)
    if p.suffix == ".csv":
        return read_joints_csv(p)
    if p.is_dir() and (p / TRACK_BAG).is_dir():
        p = p / TRACK_BAG
    elif p.is_dir() and not (p / "metadata.yaml").exists() and not any(p.glob("*.mcap")):
        raise InputError(f"{p}: no {JOINTS_CSV} and no {TRACK_BAG}/ bag (expected an `artrack track` --out folder)")
    return read_body_topic(p, "/artrack/body")


def cmd_eval(args: argparse.Namespace) -> int:
    """`artrack eval`: MPJPE of a tracking output against a bag's ground truth, and its error-over-time plot."""
    from .evaluation import evaluate, format_report, load_truth, plot_error_over_time

    truth = load_truth(args.truth)
    pred = load_predictions(args.pred)
    result = evaluate(pred, truth, tolerance_ns=args.tolerance_ms * 1_000_000)
    print(format_report(result))
    pred_path = Path(args.pred)
    if args.plot:
        plot = Path(args.plot)
    elif pred_path.is_dir() and (pred_path / JOINTS_CSV).is_file():
        plot = pred_path / "error_over_time.png"  # an `artrack track` folder
    else:
        plot = pred_path.parent / f"{pred_path.stem}_error_over_time.png"  # beside a bag or CSV
    plot_error_over_time(result.per_frame_mm, result.stamps_ns, plot, title=f"MPJPE over time: {args.pred}")
    print(f"wrote {plot}")
    return 0


# ---------------------------------------------------------------- overlay


def cmd_overlay(args: argparse.Namespace) -> int:
    """`artrack overlay`: the projected skeleton and blobs drawn on a bag's images."""
    from .bags import read_scene
    from .overlay import render_overlay

    scene = read_scene(args.input)
    pred = load_predictions(args.pred) if args.pred else None
    render_overlay(scene, pred, args.out, frames=args.frames, cols=args.cols, fps=args.fps, quiet=args.quiet)
    print(f"wrote {args.out}")
    return 0


# ----------------------------------------------------------------- launch


def cmd_launch(args: argparse.Namespace) -> int:
    """`artrack launch`: a graph file's nodes as processes (:mod:`artrack.launcher`)."""
    from .launcher import launch, parse_overrides

    return launch(args.graph, parse_overrides(args.set or []), timeout_s=args.timeout, log_dir=args.log_dir,
                  only=args.only)


# ------------------------------------------------------------------- main


def build_parser() -> argparse.ArgumentParser:
    """The `artrack` argument parser, one sub-command per ``cmd_*``."""
    ap = argparse.ArgumentParser(prog="artrack", description=__doc__.split("\n\n")[0])
    sub = ap.add_subparsers(dest="command", required=True)

    s = sub.add_parser("synth", help="render a synthetic multi-camera scene with ground truth into a bag")
    s.add_argument("--out", required=True, help="output bag (rosbag2 .mcap)")
    s.add_argument("--seed", type=int, default=0)
    s.add_argument("--cameras", type=int, default=4,
                   help="number of cameras (default 4) on a ring at the room's corners, 90° apart when fewer than 4")
    s.add_argument("--width", type=int, default=640)
    s.add_argument("--height", type=int, default=480)
    s.add_argument("--fps", type=float, default=30.0)
    s.add_argument("--duration", type=float, default=10.0, help="seconds (default 10)")
    s.add_argument("--noise", type=float, default=2.0, help="pixel noise sigma, grey levels")
    s.add_argument("--motion", default="default", help="scripted motion (default: walk, wave, reach); "
                   "stick_side / stick_sword: one RGB-D camera (--width/--height; 320x240 recommended), "
                   "a held stick on /artrack/stick and points on /cameras/rgbd/points (ALGORITHMS.md §3)")
    s.add_argument("--occlusion", action="store_true", help="include a self-occlusion segment")
    s.add_argument("--distractor", action="store_true", help="a second person walks through")
    s.add_argument("--empty-start", type=float, default=0.0, metavar="S",
                   help="the room is empty for the first S seconds, then the person appears (default 0)")
    s.add_argument("--blackout", default=None, metavar="START:SECONDS",
                   help="every camera sees only the empty room from START for SECONDS (the person keeps moving, "
                        "ground truth is kept): an 'occlude everything' event, e.g. 2.0:1.0")
    s.add_argument("--image-format", default="raw", choices=["raw", "png", "jpeg"],
                   help="raw sensor_msgs/Image, or CompressedImage (png lossless, jpeg small)")
    s.add_argument("--body-model", default=None)
    s.add_argument("--quiet", action="store_true", help="no progress bar")
    s.set_defaults(func=cmd_synth)

    t = sub.add_parser("track", help="run the closed-loop tracker offline (same core as the graph)")
    t.add_argument("input", nargs="?", help="input bag (rosbag2 mcap/sqlite3 or ROS 1 .bag)")
    t.add_argument("--out", required=True, help="output folder: track/ bag and joints.csv")
    t.add_argument("--videos", nargs="+", help="video files, one per camera (instead of a bag)")
    t.add_argument("--calib", help="calibration for --videos (.yaml, Calib.toml, .qca.txt)")
    t.add_argument("--camera-names", nargs="+", help="cameras to use (default: all)")
    t.add_argument("--scale", type=float, default=1.0, help="downscale videos to a working resolution")
    t.add_argument("--estimator", default="baseline", choices=["baseline", "kinematic", "dynamic"],
                   help="3-D estimator (default baseline: the fastest; kinematic: more accurate on blobs alone, "
                   "~2/3 the speed; see docs/MEASUREMENTS.md)")
    t.add_argument("--no-feedback", action="store_true", help="blob trackers ignore the 3-D priors once they track "
                   "(priors only label the start-up blobs)")
    t.add_argument("--fps", type=float, default=None,
                   help="nominal frame rate (first prediction step; videos: overrides the container's); default 30")
    t.add_argument("--edges", action="store_true",
                   help="also measure contour edges at the prediction and fuse them into the skeleton "
                        "(baseline estimator; ALGORITHMS.md §2)")
    t.add_argument("--edge-config", default=None, help="edge tracker tunables (default config/edge_features.yaml)")
    t.add_argument("--refine-passes", type=int, default=0, metavar="K",
                   help="a frame at least --refine-min-interval after the previous one goes round the loop up "
                        "to K more times, the priors from the last pass's body (low-frame-rate input; the graph: "
                        "refine_passes, lockstep; default 0)")
    t.add_argument("--refine-min-interval", type=float, default=0.05, metavar="S",
                   help="frame interval, s, from which --refine-passes applies (default 0.05: below 20 frames/s)")
    t.add_argument("--startup-refine-frames", type=int, default=10, metavar="N",
                   help="the N frames after the one a track started on go round the loop --startup-refine-passes "
                        "more times (the start-up pose is crude; 0: off; default 10)")
    t.add_argument("--startup-refine-passes", type=int, default=2, metavar="K",
                   help="extra passes of those frames (default 2)")
    t.add_argument("--blob-config", default=None)
    t.add_argument("--skeleton-config", default=None)
    t.add_argument("--body-model", default=None)
    t.add_argument("--max-frames", type=int, default=0)
    t.add_argument("--allow-truncated", action="store_true",
                   help="a truncated MCAP bag: track the messages before the damage (default: refuse)")
    t.add_argument("--quiet", action="store_true")
    t.set_defaults(func=cmd_track)

    b = sub.add_parser("bag-from-videos", help="write synchronised videos + calibration as a rosbag2 .mcap "
                       "(CompressedImage + CameraInfo per camera) for replay through the graph")
    b.add_argument("--videos", nargs="+", required=True, help="video files, one per camera (calibration order)")
    b.add_argument("--calib", required=True, help="calibration (.yaml, Calib.toml, .qca.txt)")
    b.add_argument("--out", required=True, help="output bag (.mcap file or rosbag2 folder)")
    b.add_argument("--camera-names", nargs="+", help="cameras of the calibration the videos belong to (default: "
                   "the first ones, in file order)")
    b.add_argument("--scale", type=float, default=1.0,
                   help="working resolution: images and intrinsics scaled by this factor (default 1)")
    b.add_argument("--fps", type=float, default=None, help="frame rate for the stamps (default: the videos')")
    b.add_argument("--image-format", default="jpeg", choices=["jpeg", "png"],
                   help="CompressedImage encoding (default jpeg)")
    b.add_argument("--max-frames", type=int, default=0, help="stop after this many frames (0: all)")
    b.add_argument("--quiet", action="store_true", help="no progress bar")
    b.set_defaults(func=cmd_bag_from_videos)

    e = sub.add_parser("eval", help="MPJPE against ground truth, with an error-over-time plot")
    e.add_argument("--truth", required=True, help="bag with /artrack/ground_truth, or joints CSV")
    e.add_argument("--pred", required=True, help="output folder of `artrack track`, or an output bag")
    e.add_argument("--plot", default=None, help="PNG path (default: PRED/error_over_time.png)")
    e.add_argument("--tolerance-ms", type=float, default=5.0, help="stamp matching tolerance")
    e.set_defaults(func=cmd_eval)

    o = sub.add_parser("overlay", help="draw the projected skeleton on every camera (PNG montage or MP4)")
    o.add_argument("input", help="input bag")
    o.add_argument("--pred", default=None, help="tracking output (folder or bag); default: ground truth only")
    o.add_argument("--out", required=True, help="montage .png or video .mp4")
    o.add_argument("--frames", default=None,
                   help="frame index or range a:b (default: middle frame for PNG, all for MP4)")
    o.add_argument("--cols", type=int, default=2)
    o.add_argument("--fps", type=float, default=30.0)
    o.add_argument("--quiet", action="store_true")
    o.set_defaults(func=cmd_overlay)

    la = sub.add_parser("launch", help="start the node graph as separate processes")
    la.add_argument("graph", help="graph file, e.g. config/graph.yaml")
    la.add_argument("--set", action="append", metavar="KEY=VALUE", help="override a graph variable")
    la.add_argument("--timeout", type=float, default=None, help="stop the graph after this many seconds")
    la.add_argument("--log-dir", default=None, help="write each node's output to LOG_DIR/<node>.log")
    la.add_argument("--only", action="append", metavar="PATTERN",
                    help="start only the nodes whose name matches (fnmatch, repeatable): one host's share of "
                         "the graph, e.g. --only 'blob_features_*' --only bag_player (see scripts/two_hosts.sh)")
    la.set_defaults(func=cmd_launch)
    return ap


def main(argv: list[str] | None = None) -> int:
    """Entry point: a bad input (ArtrackError, or a file that cannot be read or written) is one line
    on stderr and exit 1."""
    args = build_parser().parse_args(argv)
    try:
        return int(args.func(args) or 0)
    except ArtrackError as exc:
        print(f"artrack {args.command}: {exc}", file=sys.stderr)
        return 1
    except OSError as exc:  # a file we could not read or write (no file named: a genuine bug, re-raised)
        if exc.filename is None:
            raise
        name = exc.filename if exc.filename2 is None else f"{exc.filename} -> {exc.filename2}"
        print(f"artrack {args.command}: {name}: {exc.strerror or exc}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        return 130


if __name__ == "__main__":
    sys.exit(main())
