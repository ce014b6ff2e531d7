#!/usr/bin/env python3
"""Measure a colour class's start model (the blob tracker's ``colour_defaults``) from a recording.

A colour class listed in ``colour_defaults`` (config/blob_features.yaml) starts from a configured
Gaussian over the pixel colour features (r, g, I) (``artrack.colour_model.colour_features``: chroma
r = R/S, g = G/S, intensity I = S/765) instead of being bootstrapped from its labels' first prior
cores. config/pose2sim_demo.yaml configures two for the Pose2Sim man: the cyan cap ('hair') and the
black shorts ('trousers'). This script reproduces those measurements, for that recording or another:

* the pixels are chosen per view and frame by an HSV range (``--hsv``, OpenCV's H 0-179: a colour
  the room lacks, e.g. the cap), by an intensity ceiling (``--max-intensity``: a dark garment), or
  both;
* with ``--in-foreground`` only pixels inside the whole-clip reference foreground mask of
  ``bench/real_video.py`` (``artrack.silhouette.reference_foreground``, eroded by ``--erode-px``)
  count, so that the room's own dark or coloured surfaces are left out;
* frames ``--first`` .. ``--last`` (inclusive) of the clip.

Prints the pixel count, mean, standard deviation and median of (r, g, I) per view and over all
views, and ends with the mean and sd as one ``colour_defaults`` YAML entry (``--name``). Configure
the sigmas somewhat wider than the sd (a range test cuts the tails; config/pose2sim_demo.yaml uses
about 1.2-1.7x). Examples, from the repository root::

    .venv/bin/python bench/colour_model.py --name hair --hsv 84,120,60,100,255,255
    .venv/bin/python bench/colour_model.py --name trousers --max-intensity 0.2 --in-foreground
"""

from __future__ import annotations

import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "src" / "artrack_nodes"))
sys.path.insert(0, str(REPO / "bench"))

import argparse  # noqa: E402
from collections.abc import Mapping, Sequence  # noqa: E402

import cv2  # noqa: E402
import numpy as np  # noqa: E402

from artrack.colour_model import colour_features  # noqa: E402
from artrack.errors import ArtrackError, InputError  # noqa: E402
from artrack.silhouette import reference_foreground  # noqa: E402


def select_pixels(image_bgr: np.ndarray, hsv: Sequence[int] | None = None, max_intensity: float | None = None,
                  mask: np.ndarray | None = None) -> np.ndarray:
    """(H, W) bool: the pixels of one BGR image inside the HSV range ``hsv`` (h, s, v low, then high;
    OpenCV ranges), with intensity I = S / 765 below ``max_intensity``, and inside ``mask``; each
    criterion applies only when given."""
    img = np.asarray(image_bgr)
    keep = np.ones(img.shape[:2], bool) if mask is None else np.asarray(mask, bool).copy()
    if hsv is not None:
        lo, hi = np.array(hsv[:3], np.uint8), np.array(hsv[3:], np.uint8)
        keep &= cv2.inRange(cv2.cvtColor(img, cv2.COLOR_BGR2HSV), lo, hi) > 0
    if max_intensity is not None:
        keep &= colour_features(img)[..., 2] < max_intensity
    return keep


def colour_samples(frames: Sequence[Mapping[str, np.ndarray]], hsv: Sequence[int] | None = None,
                   max_intensity: float | None = None,
                   masks: Sequence[Mapping[str, np.ndarray]] | None = None) -> dict[str, np.ndarray]:
    """{camera: (n, 3) float32 (r, g, I)} of the pixels :func:`select_pixels` keeps in every frame
    ({camera: BGR image}); ``masks``: per frame {camera: (H, W) bool} to select within, or None."""
    out: dict[str, list[np.ndarray]] = {}
    for t, images in enumerate(frames):
        for name, img in images.items():
            mask = None if masks is None else masks[t][name]
            keep = select_pixels(img, hsv, max_intensity, mask)
            out.setdefault(name, []).append(colour_features(np.asarray(img)[keep]))
    return {name: np.concatenate(parts).reshape(-1, 3) for name, parts in out.items()}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--demo", type=Path, default=REPO / ".cache" / "pose2sim/Pose2Sim/Demo_SinglePerson",
                    help="recording folder with videos/camNN.mp4 and calibration/Calib.qca.txt")
    ap.add_argument("--bag", type=Path, default=None, help="read the frames from this bag instead of --demo's videos")
    ap.add_argument("--scale", type=float, default=0.25, help="working resolution factor (default 0.25: 272x480)")
    ap.add_argument("--first", type=int, default=0, help="first frame (default 0)")
    ap.add_argument("--last", type=int, default=30, help="last frame, inclusive (default 30)")
    ap.add_argument("--hsv", default=None, help="HSV range h,s,v,h,s,v (OpenCV: H 0-179, S and V 0-255)")
    ap.add_argument("--max-intensity", type=float, default=None, help="keep pixels with I = S/765 below this")
    ap.add_argument("--in-foreground", action="store_true",
                    help="only pixels in the whole-clip reference foreground mask (bench/real_video.py's)")
    ap.add_argument("--erode-px", type=int, default=1, help="erosion of that mask, px (default 1)")
    ap.add_argument("--name", default="class", help="colour class name for the YAML line (default 'class')")
    args = ap.parse_args()
    try:
        return run(args)
    except ArtrackError as exc:
        print(f"colour_model: {exc}", file=sys.stderr)
        return 1


def run(args) -> int:
    from real_video import load_bag, load_clip

    hsv = None
    if args.hsv is not None:
        try:
            hsv = [int(v) for v in args.hsv.split(",")]
        except ValueError:
            hsv = []
        if len(hsv) != 6 or not all(0 <= v <= 255 for v in hsv):
            raise InputError(f"--hsv '{args.hsv}': expected 6 integers h,s,v,h,s,v in 0..255")
    if hsv is None and args.max_intensity is None:
        raise InputError("give --hsv, --max-intensity or both: no pixel selection")
    if not 0 <= args.first <= args.last:
        raise InputError(f"--first {args.first} / --last {args.last}: need 0 <= first <= last")
    # the reference mask needs the whole clip; without it, only the frames measured are decoded
    max_frames = None if args.in_foreground else args.last + 1
    if args.bag is not None:
        _, frames, _, _, _ = load_bag(args.bag, max_frames)
        source = str(args.bag)
    else:
        _, frames, _, _, _ = load_clip(args.demo, args.scale, max_frames)
        source = f"{args.demo} at --scale {args.scale}"
    if args.last >= len(frames):
        raise InputError(f"--last {args.last}: the clip has {len(frames)} frames")
    masks = None
    if args.in_foreground:
        kernel = np.ones((2 * args.erode_px + 1,) * 2, np.uint8)
        masks = [{name: cv2.erode(m.astype(np.uint8), kernel).astype(bool) for name, m in ref.items()}
                 for ref in reference_foreground(frames)[args.first:args.last + 1]]
    samples = colour_samples(frames[args.first:args.last + 1], hsv, args.max_intensity, masks)
    print(f"{source}, frames {args.first}-{args.last}: (r, g, I) of the selected pixels")
    print(f"{'view':8s} {'pixels':>8s}   {'mean':>21s}   {'sd':>21s}   {'median':>21s}")
    every = np.concatenate(list(samples.values()))
    for name, f in [*sorted(samples.items()), ("all", every)]:
        if len(f) == 0:
            print(f"{name:8s} {0:8d}   (no pixel selected)")
            continue
        row = [" ".join(f"{v:6.3f}" for v in x) for x in (f.mean(0), f.std(0), np.median(f, 0))]
        print(f"{name:8s} {len(f):8d}   {row[0]}   {row[1]}   {row[2]}")
    if len(every) == 0:
        raise InputError("no pixel matched the selection in any view or frame")
    mean, sd = every.mean(0), every.std(0)
    def fmt(v: np.ndarray) -> str:
        return ", ".join(f"{x:.3f}" for x in v)

    print("colour_defaults entry (mean and sd; configure the sigmas somewhat wider):")
    print(f"  {args.name}: {{mean: [{fmt(mean)}], sigma: [{fmt(sd)}]}}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
