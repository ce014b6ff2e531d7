#!/usr/bin/env python3
"""The live node graph in real time: free-running replay of a recording, how much keeps up.

``make demo`` replays in lockstep (the next frame only once the body of the last one is back), so
every frame is estimated and the graph equals the offline pipeline. A camera does not wait. This
runs the same graph (``config/graph.yaml``, separate processes over DDS) free-running: the
``bag_player`` sends each frame at its stamp's time, scaled by ``--rates`` (0.25 plays the 60 frames/s
recording at 15 frames/s), and the graph estimates what it can. Per run it prints:

* frames sent, bodies back, bodies per second (the loop's rate) and their share of the frames;
* latency: from sending a frame to receiving its body, median and max (the player's clock);
* CPU seconds by node while the graph ran (``artrack launch``'s accounting, start-up included);
* accuracy on the bodies that came back: on a recording with ``/artrack/ground_truth`` (``artrack
  synth``) the MPJPE of ``artrack eval``; otherwise the checks of ``bench/real_video.py`` (joints
  inside the dilated foreground over all frames, frames without a body counting as misses, and
  over the tracked frames).

``--loop-wait`` sets the feature nodes' ``loop_wait_s`` (0: each node takes every image as it comes
instead of waiting for the loop to close; FrameQueue in artrack_nodes/common.py). Ends with one JSON
line: one record per run. Run from the repository root, after ``. scripts/env.sh``::

    python bench/live_graph.py                                  # the make-demo bag at 15 frames/s
    python bench/live_graph.py --rates 0.25 0.5 --loop-wait 0.5 0.0
    python bench/live_graph.py --bag scene.mcap --fps 30 --rates 1.0 --synthetic \
        --blob-config "" --skeleton-config "" --body-model ""       # artrack synth's scene, the defaults
"""

from __future__ import annotations

import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "src" / "artrack_nodes"))

import argparse  # noqa: E402
import json  # noqa: E402
import re  # noqa: E402
import shutil  # noqa: E402
import subprocess  # noqa: E402
import time  # noqa: E402

ARTRACK = REPO / "ros2_ws" / "install" / "artrack_nodes" / "lib" / "artrack_nodes" / "artrack"
DONE = re.compile(r"done: (\d+) frames; (?:(\d+) bodies in ([\d.]+) s: ([\d.]+) frames per second \(closed loop\)"
                  r"(?:; (\d+) of \d+ frames got a body, (\d+) ms \(median\) and (\d+) ms \(max\))?|no body came back)")


def parse_player_log(text: str) -> dict:
    """The bag_player's closing line as numbers (ValueError if it is missing)."""
    m = DONE.search(text)
    if m is None:
        raise ValueError("bag_player.log: no 'done:' line (did the graph start?)")
    sent = int(m.group(1))
    if m.group(2) is None:
        return {"frames_sent": sent, "bodies": 0, "bodies_per_s": 0.0, "latency_median_ms": None,
                "latency_max_ms": None}
    return {"frames_sent": sent, "bodies": int(m.group(2)), "bodies_per_s": float(m.group(4)),
            "latency_median_ms": int(m.group(6)) if m.group(6) else None,
            "latency_max_ms": int(m.group(7)) if m.group(7) else None}


def run_graph(args, out: Path, rate: float, loop_wait: float) -> dict:
    """One free-running replay; returns the player's figures."""
    if out.exists():
        shutil.rmtree(out)
    sets = [f"bag={args.bag}", f"out={out / 'graph'}", f"fps={args.fps}", "lockstep=false", f"rate={rate}",
            f"loop_wait_s={float(loop_wait)}"]
    for key in ("blob_config", "skeleton_config", "body_model"):
        value = getattr(args, key)
        if value:
            sets.append(f"{key}={Path(value).resolve()}")
    cmd = [str(ARTRACK), "launch", str(REPO / "config" / "graph.yaml"), "--log-dir", str(out / "logs")]
    for s in sets:
        cmd += ["--set", s]
    t0 = time.monotonic()
    proc = subprocess.run(cmd, cwd=REPO, capture_output=True, text=True, timeout=args.timeout)
    log = out / "logs" / "bag_player.log"
    if proc.returncode != 0 or not log.exists():
        raise SystemExit(f"live_graph: the graph failed (exit {proc.returncode}); logs in {out / 'logs'}\n"
                         f"{proc.stderr[-2000:]}")
    figures = parse_player_log(log.read_text(errors="replace"))
    figures["wall_s"] = round(time.monotonic() - t0, 1)
    cpu = out / "logs" / "cpu.json"  # (artrack launch: each node's CPU s while the graph ran)
    figures["cpu_s"] = json.loads(cpu.read_text())["cpu_s"] if cpu.exists() else {}
    return figures


def check(args, pred: Path) -> dict:
    """Accuracy of the recorded bodies: MPJPE against ground truth, or the real-video checks."""
    if args.synthetic:
        proc = subprocess.run([str(ARTRACK), "eval", "--truth", str(args.bag), "--pred", str(pred)],
                              cwd=REPO, capture_output=True, text=True, timeout=600)
        m = re.search(r"MPJPE ([\d.]+) mm", proc.stdout)
        return {"mpjpe_mm": float(m.group(1)) if m else None}
    cmd = [sys.executable, str(REPO / "bench" / "real_video.py"), "--bag", str(args.bag), "--pred", str(pred),
           "--no-loo", "--quiet"]
    for key in ("blob_config", "skeleton_config", "body_model"):
        value = getattr(args, key)
        if value:
            cmd += [f"--{key.replace('_', '-')}", str(value)]
    proc = subprocess.run(cmd, cwd=REPO, capture_output=True, text=True, timeout=1200)
    lines = [ln for ln in proc.stdout.splitlines() if ln.startswith("{")]
    if proc.returncode != 0 or not lines:
        raise SystemExit(f"live_graph: bench/real_video.py failed on {pred}:\n"
                         f"{proc.stdout[-1500:]}{proc.stderr[-1500:]}")
    res = json.loads(lines[-1])
    m = re.search(r"over the (\d+) tracked frames: ([\d.]+) %", proc.stdout)
    return {"inside_share": res["inside_foreground_share"], "tracked_frames": res["tracked_frames"],
            "inside_share_tracked": float(m.group(2)) / 100 if m else None}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--bag", type=Path, default=REPO / "bags" / "pose2sim_single.mcap",
                    help="recording to replay (default: the make-demo bag; `make demo` writes it)")
    ap.add_argument("--fps", type=float, default=60.0, help="the recording's frame rate (graph variable fps)")
    ap.add_argument("--rates", type=float, nargs="+", default=[0.25],
                    help="playback speed factors (0.25: a quarter of the recording's rate)")
    ap.add_argument("--loop-wait", type=float, nargs="+", default=[0.5],
                    help="the feature nodes' loop_wait_s, s (0: every image as it comes)")
    ap.add_argument("--blob-config", default=str(REPO / "config" / "pose2sim_demo.yaml"))
    ap.add_argument("--skeleton-config", default=str(REPO / "config" / "pose2sim_skeleton.yaml"))
    ap.add_argument("--body-model", default=str(REPO / "config" / "pose2sim_body_model.yaml"))
    ap.add_argument("--synthetic", action="store_true",
                    help="the bag has ground truth (artrack synth): score by MPJPE; pass the synthetic configs "
                         "(or empty strings for the defaults) with it")
    ap.add_argument("--out", type=Path, default=REPO / "out" / "live_graph", help="runs and logs go here")
    ap.add_argument("--timeout", type=float, default=600.0, help="per graph run, s")
    args = ap.parse_args()
    if not args.bag.exists():
        print(f"live_graph: {args.bag}: no such recording (`make demo` writes the default one)", file=sys.stderr)
        return 1
    if not ARTRACK.exists():
        print("live_graph: the workspace is not built (make setup)", file=sys.stderr)
        return 1
    records = []
    for loop_wait in args.loop_wait:
        for rate in args.rates:
            out = args.out / f"rate{rate:g}_wait{loop_wait:g}"
            print(f"run: {args.bag.name} at {rate:g} x {args.fps:g} frames/s, loop_wait_s {loop_wait:g} ...",
                  file=sys.stderr, flush=True)
            rec = {"rate": rate, "input_fps": rate * args.fps, "loop_wait_s": loop_wait,
                   **run_graph(args, out, rate, loop_wait)}
            rec.update(check(args, out / "graph"))
            records.append(rec)
    acc = "MPJPE mm" if args.synthetic else "inside % all / tracked"
    print(f"{'input fps':>9} {'wait s':>6} {'sent':>5} {'bodies':>6} {'bodies/s':>8} {'latency ms med/max':>19}  {acc}")
    for r in records:
        lat = (f"{r['latency_median_ms']} / {r['latency_max_ms']}" if r["latency_median_ms"] is not None else "-")
        if args.synthetic:
            a = f"{r['mpjpe_mm']:.1f}" if r.get("mpjpe_mm") is not None else "-"
        else:
            tr = r.get("inside_share_tracked")
            a = f"{100 * r['inside_share']:.1f}" + (f" / {100 * tr:.1f}" if tr is not None else "")
        print(f"{r['input_fps']:9.1f} {r['loop_wait_s']:6.2f} {r['frames_sent']:5d} {r['bodies']:6d} "
              f"{r['bodies_per_s']:8.2f} {lat:>19}  {a}")
    print("(bodies/s: the loop's rate, from the first frame sent to the last body back; latency: sending a frame "
          "to its body)")
    nodes = sorted({n for r in records for n in r["cpu_s"]}, key=lambda n: -max(r["cpu_s"].get(n, 0) for r in records))
    if nodes:
        print("\nCPU s by node while the graph ran (start-up included), one column per run; ms per body below")
        print(f"{'node':<22}" + "".join(f"{r['input_fps']:>6.1f}/{r['loop_wait_s']:<5g}" for r in records))
        for n in [*nodes, "total"]:
            vals = [sum(r["cpu_s"].values()) if n == "total" else r["cpu_s"].get(n, float("nan")) for r in records]
            print(f"{n:<22}" + "".join(f"{v:12.2f}" for v in vals))
        print(f"{'total ms per body':<22}" + "".join(
            f"{1e3 * sum(r['cpu_s'].values()) / max(r['bodies'], 1):12.1f}" for r in records))
    print(json.dumps({"runs": records}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
