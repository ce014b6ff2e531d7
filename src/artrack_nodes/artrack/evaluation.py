"""Accuracy against ground truth: MPJPE, joints CSV files, error-over-time plot.

MPJPE (mean per-joint position error) is the Euclidean distance between predicted
and true 3-D joint positions (world frame), averaged over joints and frames, in
millimetres. Frames are paired by stamp (:func:`match_by_stamp`), joints by name.
NaN joints (e.g. a lost track) are left out of the means.

Joints CSV (written by ``artrack track`` as ``joints.csv``), one row per frame and joint::

    frame,stamp,joint,x,y,z
    0,1700000000000000000,pelvis,0.01,-0.2,0.93

frame: 0-based index; stamp: int ns; x, y, z: world frame (z up), metres.
The plot is drawn with OpenCV only (no matplotlib).
"""

from __future__ import annotations

import csv
import math
import os
import secrets
import warnings
from dataclasses import dataclass
from decimal import Decimal, InvalidOperation
from pathlib import Path

import cv2
import numpy as np

from .bags import GROUND_TRUTH_TOPIC, JointTrack, read_body_topic
from .errors import InputError, check_output_path

__all__ = [
    "EvalResult",
    "JointTrack",
    "compare_paired",
    "evaluate",
    "format_report",
    "label_confusion",
    "load_truth",
    "match_by_stamp",
    "mpjpe",
    "plot_error_over_time",
    "read_body_topic",
    "read_joints_csv",
    "write_joints_csv",
]

CSV_COLUMNS = ("frame", "stamp", "joint", "x", "y", "z")


# =========================================================================== metrics
def match_by_stamp(pred_stamps, truth_stamps, tol_ns: int) -> tuple[np.ndarray, np.ndarray]:
    """Pair predicted and true frames by nearest stamp.

    pred_stamps (P,), truth_stamps (T,): int ns. Each predicted frame takes the nearest
    true stamp if within ``tol_ns``; each true frame is used at most once (by its nearest
    prediction). Returns index arrays (pred_idx (M,), truth_idx (M,)) in increasing truth stamp.
    """
    p = np.asarray(pred_stamps, dtype=np.int64).reshape(-1)
    t = np.asarray(truth_stamps, dtype=np.int64).reshape(-1)
    if p.size == 0 or t.size == 0:
        return np.zeros(0, np.intp), np.zeros(0, np.intp)
    order = np.argsort(t, kind="stable")
    ts = t[order]
    hi = np.clip(np.searchsorted(ts, p), 0, ts.size - 1)
    lo = np.clip(hi - 1, 0, ts.size - 1)
    d_hi, d_lo = np.abs(ts[hi] - p), np.abs(ts[lo] - p)
    near = np.where(d_lo <= d_hi, lo, hi)
    dist = np.minimum(d_lo, d_hi)
    cand = np.flatnonzero(dist <= int(tol_ns))
    # one prediction per true frame: the closest (then the earliest prediction)
    cand = cand[np.lexsort((cand, dist[cand], near[cand]))]
    keep = np.ones(cand.size, bool)
    keep[1:] = near[cand][1:] != near[cand][:-1]
    cand = cand[keep]
    return cand.astype(np.intp), order[near[cand]].astype(np.intp)


def mpjpe(pred: np.ndarray, truth: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """MPJPE of already paired frames.

    pred, truth: (T, J, 3) world positions, m. Returns (overall mm, per-joint mm (J,),
    per-frame mm (T,)); NaN joints are skipped (a frame / joint with no valid value is NaN).
    """
    pred = np.asarray(pred, dtype=np.float64)
    truth = np.asarray(truth, dtype=np.float64)
    if pred.shape != truth.shape or pred.ndim != 3 or pred.shape[2] != 3:
        raise ValueError(f"mpjpe: pred {pred.shape} and truth {truth.shape} must both be (T, J, 3)")
    err = np.linalg.norm(pred - truth, axis=2) * 1000.0  # (T, J) mm
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN slices -> NaN
        overall = float(np.nanmean(err)) if err.size else math.nan
        return overall, np.nanmean(err, axis=0), np.nanmean(err, axis=1)


def label_confusion(observed: dict[str, np.ndarray], truth: dict[str, np.ndarray]) -> dict[str, tuple[str, float]]:
    """Which true part each labelled observation lies nearest to (diagnosis of blob labelling,
    ALGORITHMS.md §1: a swapped or stolen label shows as a label whose nearest true part is
    another one).

    observed: label -> (D,) observed position (e.g. a triangulated 3-D blob mean, or a 2-D
    blob mean in px); truth: label -> (D,) true position of every part, same units. Returns
    label -> (nearest true label, distance to its own true part) for the observed labels that
    have a truth.
    """
    names = sorted(truth)
    if not names:
        return {}
    T = np.array([np.asarray(truth[n], float).reshape(-1) for n in names])
    out = {}
    for lab, x in observed.items():
        if lab not in truth:
            continue
        d = np.linalg.norm(T - np.asarray(x, float).reshape(1, -1), axis=1)
        out[lab] = (names[int(np.argmin(d))], float(d[names.index(lab)]))
    return out


def compare_paired(before: dict, after: dict, tie_mm: float = 1.0) -> dict:
    """Paired comparison of two runs of the same scenes (e.g. MPJPE per seed, mm) before and after
    a change: the closed loop is chaotic (single seeds swing by ±50–100 mm with rounding-level
    changes), so a change is judged by how many paired runs it improves, not by one run.

    before, after: key (e.g. a seed) -> value, lower is better; only keys in both with finite
    values are paired. Differences within ``tie_mm`` are ties. Returns n (pairs), mean_before,
    mean_after, median_before, median_after, better, worse, ties, sign_test_p: the two-sided
    exact binomial (sign) test of better vs worse under "no effect", and wilcoxon_p: the two-sided
    Wilcoxon signed-rank test of the differences (ties dropped; it also weighs how much better or
    worse, so it finds a consistent shift with fewer pairs than the sign test); both 1.0 when
    all are ties. InputError for fewer than one pair or a negative ``tie_mm``."""
    from scipy.stats import binomtest, wilcoxon

    if not tie_mm >= 0:
        raise InputError(f"compare_paired: tie_mm must be >= 0, got {tie_mm}")
    keys = [k for k in before if k in after and math.isfinite(before[k]) and math.isfinite(after[k])]
    if not keys:
        raise InputError("compare_paired: no key with a finite value in both runs")
    b = np.array([float(before[k]) for k in keys])
    a = np.array([float(after[k]) for k in keys])
    d = a - b
    better, worse = int(np.sum(d < -tie_mm)), int(np.sum(d > tie_mm))
    p = binomtest(better, better + worse, 0.5).pvalue if better + worse else 1.0
    untied = d[np.abs(d) > tie_mm]
    w = wilcoxon(untied).pvalue if untied.size else 1.0
    return {"n": len(keys), "mean_before": float(b.mean()), "mean_after": float(a.mean()),
            "median_before": float(np.median(b)), "median_after": float(np.median(a)),
            "better": better, "worse": worse, "ties": len(keys) - better - worse, "sign_test_p": float(p),
            "wilcoxon_p": float(w)}


@dataclass
class EvalResult:
    """Outcome of :func:`evaluate`. Errors in mm; stamps_ns (M,) the matched true stamps."""

    overall_mm: float
    per_joint_mm: np.ndarray
    per_frame_mm: np.ndarray
    stamps_ns: np.ndarray
    joint_names: list[str]
    n_pred: int
    n_truth: int

    @property
    def n_matched(self) -> int:
        return int(self.stamps_ns.size)


def evaluate(pred, truth, tolerance_ns: int = 5_000_000) -> EvalResult:
    """MPJPE of a prediction against ground truth.

    pred, truth: (stamps (N,) int ns, joint_names (J,), joints (N, J, 3) m), e.g. a
    :class:`JointTrack`. Frames are matched by stamp within ``tolerance_ns``; joints by
    name (every true joint must be predicted). Raises InputError when nothing matches.
    """
    p_stamps, p_names, p_joints = pred
    t_stamps, t_names, t_joints = truth
    p_joints = np.asarray(p_joints, dtype=np.float64)
    t_joints = np.asarray(t_joints, dtype=np.float64)
    index = {n: i for i, n in enumerate(p_names)}
    missing = [n for n in t_names if n not in index]
    if missing:
        raise InputError(f"prediction has no joint '{missing[0]}' (has: {', '.join(p_names)})")
    cols = [index[n] for n in t_names]
    pi, ti = match_by_stamp(p_stamps, t_stamps, tolerance_ns)
    if pi.size == 0:
        raise InputError(
            f"no predicted frame is within {tolerance_ns / 1e6:g} ms of a ground-truth stamp "
            f"({len(p_stamps)} predicted, {len(t_stamps)} true frames)"
        )
    overall, per_joint, per_frame = mpjpe(p_joints[pi][:, cols], t_joints[ti])
    return EvalResult(
        overall_mm=overall,
        per_joint_mm=per_joint,
        per_frame_mm=per_frame,
        stamps_ns=np.asarray(t_stamps, dtype=np.int64)[ti],
        joint_names=list(t_names),
        n_pred=len(p_stamps),
        n_truth=len(t_stamps),
    )


def format_report(result: EvalResult) -> str:
    """Per-joint table, then the summary line ``MPJPE <x> mm`` (1 decimal) last."""
    width = max([len("joint")] + [len(n) for n in result.joint_names])
    lines = [f"{'joint':<{width}}  MPJPE (mm)"]
    for name, e in zip(result.joint_names, result.per_joint_mm, strict=True):
        lines.append(f"{name:<{width}}  {e:10.1f}")
    lines.append(
        f"frames matched: {result.n_matched} ({result.n_pred} predicted, {result.n_truth} ground truth)"
    )
    lines.append(f"MPJPE {result.overall_mm:.1f} mm")
    return "\n".join(lines)


# =========================================================================== files
def _atomic_write_bytes(path: Path, data: bytes) -> None:
    """Write to a hidden sibling, then rename (usual umask permissions)."""
    check_output_path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{secrets.token_hex(4)}.tmp")
    try:
        with tmp.open("xb") as f:
            f.write(data)
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


def write_joints_csv(path: str | os.PathLike, stamps, joint_names, joints) -> None:
    """Write joints as CSV (columns frame, stamp, joint, x, y, z; world frame, m).

    stamps (T,) int ns; joint_names (J,); joints (T, J, 3). Floats are written exactly
    (repr); the file appears only when complete (temporary file + rename).
    """
    stamps = np.asarray(stamps, dtype=np.int64).reshape(-1)
    joints = np.asarray(joints, dtype=np.float64)
    names = list(joint_names)
    if joints.shape != (stamps.size, len(names), 3):
        raise ValueError(f"{path}: joints {joints.shape} do not match {stamps.size} x {len(names)} joints")
    rows = [",".join(CSV_COLUMNS)]
    for i, (s, frame) in enumerate(zip(stamps.tolist(), joints.tolist(), strict=True)):
        for name, (x, y, z) in zip(names, frame, strict=True):
            rows.append(f"{i},{s},{name},{x!r},{y!r},{z!r}")
    _atomic_write_bytes(Path(path), ("\n".join(rows) + "\n").encode())


def _parse_int(text: str) -> int:
    try:
        return int(text)
    except ValueError:
        d = Decimal(text)  # e.g. "1.7e18": exact, no float rounding
        if d != d.to_integral_value():
            raise ValueError(text) from None
        return int(d)


def read_joints_csv(path: str | os.PathLike) -> JointTrack:
    """Read a joints CSV (see the module docstring) -> JointTrack(stamps (T,), names (J,), joints (T, J, 3)).

    Frames are returned in the order of their ``frame`` column; every frame must list the same
    joints. Raises InputError naming the file, line and column of any problem.
    """
    p = Path(path)
    where = str(path)
    if not p.is_file():
        raise InputError(f"{where}: joints CSV not found")
    with p.open(newline="") as fh:
        reader = csv.reader(fh)
        header = next(reader, None)
        if header is None:
            raise InputError(f"{where}: empty file (expected columns {', '.join(CSV_COLUMNS)})")
        header = [h.strip().lower() for h in header]
        for col in CSV_COLUMNS:
            if col not in header:
                raise InputError(f"{where}: no column '{col}' (expected {', '.join(CSV_COLUMNS)})")
        ci = {c: header.index(c) for c in CSV_COLUMNS}
        frames: dict[int, tuple[int, dict[str, tuple[float, float, float]]]] = {}
        names: list[str] = []
        for line_no, row in enumerate(reader, start=2):
            if not row or all(not c.strip() for c in row):
                continue
            if len(row) < len(header):
                raise InputError(f"{where}: line {line_no} has {len(row)} fields, expected {len(header)}")
            col = "frame"
            try:
                frame = _parse_int(row[ci["frame"]].strip())
                col = "stamp"
                stamp = _parse_int(row[ci["stamp"]].strip())
                xyz = []
                for col in ("x", "y", "z"):
                    xyz.append(float(row[ci[col]]))
            except (ValueError, InvalidOperation):
                raise InputError(f"{where}: line {line_no} column '{col}' is not a number") from None
            joint = row[ci["joint"]].strip()
            if not joint:
                raise InputError(f"{where}: line {line_no} column 'joint' is empty")
            entry = frames.setdefault(frame, (stamp, {}))
            if entry[0] != stamp:
                raise InputError(f"{where}: line {line_no} column 'stamp': frame {frame} has two stamps")
            if joint in entry[1]:
                raise InputError(f"{where}: line {line_no}: joint '{joint}' twice in frame {frame}")
            entry[1][joint] = tuple(xyz)
            if joint not in names:
                names.append(joint)
    if not frames:
        raise InputError(f"{where}: no rows")
    order = sorted(frames)
    joints = np.empty((len(order), len(names), 3))
    for k, f in enumerate(order):
        got = frames[f][1]
        if len(got) != len(names):
            lacking = next(n for n in names if n not in got)
            raise InputError(f"{where}: frame {f} has no row for joint '{lacking}'")
        joints[k] = [got[n] for n in names]
    stamps = np.array([frames[f][0] for f in order], dtype=np.int64)
    return JointTrack(stamps, names, joints)


def load_truth(path: str | os.PathLike) -> JointTrack:
    """Ground truth from a joints CSV (``.csv``) or a bag's ``/artrack/ground_truth`` topic."""
    if Path(path).suffix.lower() == ".csv":
        return read_joints_csv(path)
    return read_body_topic(path, GROUND_TRUTH_TOPIC)


# =========================================================================== plot
def _nice_step(span: float, n: int = 6) -> float:
    """A 1/2/5 x 10^k step giving about ``n`` intervals over ``span``."""
    if not (span > 0 and math.isfinite(span)):
        return 1.0
    raw = span / n
    mag = 10 ** math.floor(math.log10(raw))
    for m in (1, 2, 5, 10):
        if m * mag >= raw:
            return m * mag
    return 10 * mag


def _fmt_tick(v: float, step: float) -> str:
    decimals = max(0, -math.floor(math.log10(step))) if step < 1 else 0
    return f"{v:.{decimals}f}"


def plot_error_over_time(
    per_frame_mm,
    stamps_ns,
    path: str | os.PathLike,
    title: str = "MPJPE over time",
    size: tuple[int, int] = (960, 420),
) -> Path:
    """Draw per-frame error (mm) against time (s since the first stamp) as a PNG with OpenCV.

    per_frame_mm (T,), stamps_ns (T,) int ns. Axes with ticks and labels, the error as a
    polyline (gaps at NaN), the mean as a dashed line. Written atomically; returns the path.
    """
    err = np.asarray(per_frame_mm, dtype=np.float64).reshape(-1)
    stamps = np.asarray(stamps_ns, dtype=np.int64).reshape(-1)
    if err.shape != stamps.shape:
        raise ValueError(f"{path}: {err.size} errors for {stamps.size} stamps")
    W, H = size
    left, right, top, bottom = 78, 24, 44, 58
    img = np.full((H, W, 3), 255, np.uint8)
    font, aa = cv2.FONT_HERSHEY_SIMPLEX, cv2.LINE_AA
    black, grid, blue, red = (0, 0, 0), (225, 225, 225), (180, 90, 20), (40, 40, 200)

    t = (stamps - stamps[0]) * 1e-9 if stamps.size else np.zeros(0)
    finite = np.isfinite(err)
    t_max = float(t[-1]) if t.size and t[-1] > 0 else 1.0
    e_top = float(np.max(err[finite])) * 1.1 if finite.any() else 1.0
    e_top = max(e_top, 1e-3)
    x_step, y_step = _nice_step(t_max), _nice_step(e_top, 5)
    t_max = math.ceil(t_max / x_step - 1e-9) * x_step
    e_top = math.ceil(e_top / y_step - 1e-9) * y_step
    x0, x1, y0, y1 = left, W - right, H - bottom, top

    def px(tt, ee):
        return x0 + (x1 - x0) * tt / t_max, y0 - (y0 - y1) * ee / e_top

    # grid, ticks and tick labels
    for k in range(int(round(t_max / x_step)) + 1):
        v = k * x_step
        x = int(round(px(v, 0)[0]))
        cv2.line(img, (x, y1), (x, y0), grid, 1)
        cv2.line(img, (x, y0), (x, y0 + 5), black, 1)
        label = _fmt_tick(v, x_step)
        (tw, th), _ = cv2.getTextSize(label, font, 0.42, 1)
        cv2.putText(img, label, (x - tw // 2, y0 + 8 + th), font, 0.42, black, 1, aa)
    for k in range(int(round(e_top / y_step)) + 1):
        v = k * y_step
        y = int(round(px(0, v)[1]))
        cv2.line(img, (x0, y), (x1, y), grid, 1)
        cv2.line(img, (x0 - 5, y), (x0, y), black, 1)
        label = _fmt_tick(v, y_step)
        (tw, th), _ = cv2.getTextSize(label, font, 0.42, 1)
        cv2.putText(img, label, (x0 - 8 - tw, y + th // 2), font, 0.42, black, 1, aa)
    cv2.rectangle(img, (x0, y1), (x1, y0), black, 1)

    # axis labels and title
    (tw, th), _ = cv2.getTextSize("time (s)", font, 0.5, 1)
    cv2.putText(img, "time (s)", ((x0 + x1 - tw) // 2, H - 12), font, 0.5, black, 1, aa)
    label = "error (mm)"
    (tw, th), base = cv2.getTextSize(label, font, 0.5, 1)
    patch = np.full((th + base + 4, tw + 4, 3), 255, np.uint8)
    cv2.putText(patch, label, (2, th + 2), font, 0.5, black, 1, aa)
    patch = cv2.rotate(patch, cv2.ROTATE_90_COUNTERCLOCKWISE)
    py = (y0 + y1 - patch.shape[0]) // 2
    img[py : py + patch.shape[0], 8 : 8 + patch.shape[1]] = np.minimum(
        img[py : py + patch.shape[0], 8 : 8 + patch.shape[1]], patch
    )
    (tw, th), _ = cv2.getTextSize(title, font, 0.55, 1)
    cv2.putText(img, title, (max(4, (W - tw) // 2), 26), font, 0.55, black, 1, aa)

    # the series (split at NaN), then the mean
    if finite.any():
        pts = np.stack(px(t, np.where(finite, err, 0.0)), axis=1)
        start = None
        for i in range(err.size + 1):
            ok = i < err.size and finite[i]
            if ok and start is None:
                start = i
            elif not ok and start is not None:
                seg = np.round(pts[start:i] * 16).astype(np.int32)  # 4 fractional bits
                if seg.shape[0] == 1:
                    cv2.circle(img, tuple(seg[0]), 2 * 16, blue, -1, aa, 4)
                else:
                    cv2.polylines(img, [seg], False, blue, 2, aa, 4)
                start = None
        mean = float(np.mean(err[finite]))
        y = int(round(px(0, mean)[1]))
        for xa in range(x0, x1, 14):
            cv2.line(img, (xa, y), (min(xa + 7, x1), y), red, 1, aa)
        text = f"mean {mean:.1f} mm"  # key in the top-right corner, on white
        (tw, th), base = cv2.getTextSize(text, font, 0.45, 1)
        bx, by = x1 - tw - 44, y1 + 8
        cv2.rectangle(img, (bx - 6, by - 4), (x1 - 4, by + th + base + 4), (255, 255, 255), -1)
        cv2.rectangle(img, (bx - 6, by - 4), (x1 - 4, by + th + base + 4), grid, 1)
        cv2.line(img, (bx, by + th // 2 + 1), (bx + 7, by + th // 2 + 1), red, 1, aa)
        cv2.line(img, (bx + 14, by + th // 2 + 1), (bx + 21, by + th // 2 + 1), red, 1, aa)
        cv2.putText(img, text, (bx + 30, by + th), font, 0.45, red, 1, aa)
    else:
        cv2.putText(img, "no data", ((x0 + x1) // 2 - 30, (y0 + y1) // 2), font, 0.6, red, 1, aa)

    out = Path(path)
    ok, buf = cv2.imencode(".png", img)
    if not ok:
        raise InputError(f"{out}: PNG encoding failed")
    _atomic_write_bytes(out, buf.tobytes())
    return out
