#!/usr/bin/env python3
"""Where the tracker's 3-D blobs centre on their links, and the body model's blob centres that
match them (ALGORITHMS.md §1, "3-D blobs": the appearance model's bias, measured).

The 3-D stage triangulates each part's 2-D blob means and weights every view by the inverse of
the blob's 2-D spread (``artrack.triangulation``). Where a part shows different patches to
different views, the triangulated point is not the centre of its visible surface that
``centre: auto`` in config/body_model.yaml computes: the head shows its face from the front but
only the neck below the hair from behind, and that small, tight patch counts most; the torso's
blob takes in the shirt-coloured sleeves. The offset is the same in every frame, so the fit
reads it as a pose error (the head pulled down and back) unless the model's centre sits where
the tracker's blob does.

For each ``--seeds`` scene (held out: the benches score seeds 1-30) this runs
``bench/label_diagnosis.py --true-priors FRAME`` (the skeleton re-seeded from the true pose at
every frame from FRAME on: the labelling given right priors, without the loop's errors), which
reports, per label, the median offset in the true link's frame of the triangulated blob (seen
in 3 or more views) from the model's centre. Prints per label the per-seed offsets, their mean,
the current centre and the calibrated one (current + mean offset, link frame, m), the YAML to
paste into config/body_model.yaml (``--labels`` only), and one JSON line. Deterministic; run
from the repository root (about 30 s a seed at 320x240)::

    .venv/bin/python bench/blob_centres.py                       # seeds 40 41 42, pelvis, torso and head
    .venv/bin/python bench/blob_centres.py --labels torso head l_shin r_shin --width 640 --height 480

After pasting, a second run should print offsets near zero (the check that the measurement
and the model agree).
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "src" / "artrack_nodes"))
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse  # noqa: E402
import json  # noqa: E402
import subprocess  # noqa: E402

import numpy as np  # noqa: E402

from artrack.body_model import load_body_model  # noqa: E402

DIAGNOSIS = Path(__file__).resolve().parent / "label_diagnosis.py"


def mm_cells(v) -> str:
    return ("".join(f"{x:6.0f}" for x in v) if v is not None else "-").rjust(22)


def m_cells(v) -> str:
    return "".join(f" {x:7.3f}" for x in v).rjust(26)


def seed_offsets(seed: int, args) -> dict[str, list[float] | None]:
    """label -> median offset (mm, link frame) of one seed, from label_diagnosis.py's JSON line."""
    cmd = [sys.executable, str(DIAGNOSIS), "--seed", str(seed), "--true-priors", str(args.true_priors),
           "--width", str(args.width), "--height", str(args.height), "--duration", str(args.duration),
           "--cache", args.cache, "--every", "100000"]
    out = subprocess.run(cmd, capture_output=True, text=True)
    if out.returncode != 0:
        print(out.stderr.strip().splitlines()[-1] if out.stderr.strip() else f"{DIAGNOSIS.name} failed",
              file=sys.stderr)
        raise SystemExit(1)
    summary = json.loads(out.stdout.strip().splitlines()[-1])
    return {lab: s["centre_offset_mm"] for lab, s in summary["labels"].items()}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seeds", type=int, nargs="+", default=[40, 41, 42],
                    help="synthetic scene seeds to measure on (keep them apart from the ones you score)")
    ap.add_argument("--labels", nargs="+", default=["pelvis", "torso", "head"],
                    help="labels whose calibrated centres are printed as YAML")
    ap.add_argument("--true-priors", type=int, default=30, metavar="FRAME",
                    help="re-seed the skeleton with the true pose at every frame from this one")
    ap.add_argument("--width", type=int, default=320)
    ap.add_argument("--height", type=int, default=240)
    ap.add_argument("--duration", type=float, default=6.0)
    ap.add_argument("--cache", default="/tmp/artrack_bench")
    args = ap.parse_args()
    body = load_body_model()
    unknown = [lab for lab in args.labels if lab not in body.blob_labels]
    if unknown:
        print(f"--labels: {unknown} carry no blob in the body model (blobs: {body.blob_labels})", file=sys.stderr)
        return 2
    current = {lab: body.link(lab).blob.centre for lab in body.blob_labels}  # link frame, m ('auto' resolved)
    per_seed = {}
    for seed in args.seeds:
        print(f"seed {seed} ...", file=sys.stderr, flush=True)
        per_seed[seed] = seed_offsets(seed, args)

    print(f"blob centre offsets, triangulated blob - body model centre, true link frame, mm "
          f"(medians over frames, true priors from frame {args.true_priors}, {args.width}x{args.height})")
    print(f"{'label':<9}" + "".join(f"{'seed ' + str(s):>22}" for s in args.seeds)
          + f"{'mean':>22}{'current centre m':>26}{'calibrated m':>26}")
    result = {}
    for lab in body.blob_labels:
        offs = [per_seed[s][lab] for s in args.seeds if per_seed[s][lab] is not None]
        if not offs:
            print(f"{lab:<9}  not seen in 3 views")
            continue
        mean = np.mean(offs, axis=0)
        calibrated = current[lab] + 1e-3 * mean
        result[lab] = {"offsets_mm": offs, "mean_offset_mm": mean.round(1).tolist(),
                       "current_m": current[lab].round(4).tolist(), "calibrated_m": calibrated.round(3).tolist()}
        print(f"{lab:<9}" + "".join(mm_cells(per_seed[s][lab]) for s in args.seeds) + mm_cells(mean)
              + m_cells(current[lab]) + m_cells(calibrated))
    print("\nconfig/body_model.yaml (blob: {centre: [x, y, z]} of these links):")
    for lab in args.labels:
        if lab in result:
            x, y, z = result[lab]["calibrated_m"]
            print(f"  {lab}: centre: [{x:.3f}, {y:.3f}, {z:.3f}]")
    print(json.dumps({"seeds": args.seeds, "width": args.width, "height": args.height,
                      "true_priors": args.true_priors, "labels": result}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
