"""Drawing on camera images: projected skeleton, 2-D blobs and priors, montages, MP4.

Everything is OpenCV on (H, W, 3) uint8 BGR images. Joints are world positions (m)
projected through the calibrated :class:`~artrack.cameras.Camera` (with lens
distortion); pixels have (0, 0) at the centre of the top-left pixel. Ellipses
are drawn at 2 sigma of the 2x2 pixel covariance: observed blobs solid, projected
priors (ALGORITHMS.md §1, inverse observation model) thinner and dashed.
Files are written to a temporary sibling and renamed, so nothing is half-written.
"""

from __future__ import annotations

import math
import os
import re
import secrets
import zlib
from collections.abc import Iterable, Sequence
from pathlib import Path

import cv2
import numpy as np

from .cameras import Camera
from .errors import InputError, check_output_path
from .types import VISIBLE, Blob2D, Prior2D

__all__ = [
    "BONES",
    "PRED_COLOR",
    "TRUTH_COLOR",
    "draw_body",
    "montage",
    "render_overlay",
    "write_montage_png",
    "write_mp4",
]

#: Skeleton of the 15 output joints: (proximal, distal) joint names.
BONES: list[tuple[str, str]] = [
    ("pelvis", "thorax"), ("thorax", "head"),
    ("thorax", "l_shoulder"), ("l_shoulder", "l_elbow"), ("l_elbow", "l_wrist"),
    ("thorax", "r_shoulder"), ("r_shoulder", "r_elbow"), ("r_elbow", "r_wrist"),
    ("pelvis", "l_hip"), ("l_hip", "l_knee"), ("l_knee", "l_ankle"),
    ("pelvis", "r_hip"), ("r_hip", "r_knee"), ("r_knee", "r_ankle"),
]  # fmt: skip
TRUTH_COLOR = (60, 200, 60)
PRED_COLOR = (255, 60, 255)
_SHIFT = 4  # fractional bits for sub-pixel drawing
_AA = cv2.LINE_AA
_FONT = cv2.FONT_HERSHEY_SIMPLEX


def _label_color(label: str) -> tuple[int, int, int]:
    """A stable, saturated BGR colour per blob label."""
    h = zlib.crc32(label.encode()) % 180
    hsv = np.array([[[h, 220, 255]]], np.uint8)
    b, g, r = cv2.cvtColor(hsv, cv2.COLOR_HSV2BGR)[0, 0]
    return int(b), int(g), int(r)


def _fixed(p: np.ndarray) -> tuple[int, int]:
    return int(round(p[0] * (1 << _SHIFT))), int(round(p[1] * (1 << _SHIFT)))


def _ellipse_points(mean: np.ndarray, cov: np.ndarray, n_sigma: float = 2.0,
                    n: int = 64) -> np.ndarray | None:
    """(n, 2) points of the n_sigma ellipse of a 2x2 pixel covariance, or None if degenerate."""
    cov = np.asarray(cov, dtype=float).reshape(2, 2)
    mean = np.asarray(mean, dtype=float).reshape(2)
    if not (np.all(np.isfinite(cov)) and np.all(np.isfinite(mean))):
        return None
    w, V = np.linalg.eigh(0.5 * (cov + cov.T))
    w = np.clip(w, 0.0, None)
    if w.max() <= 0:
        return None
    t = np.linspace(0.0, 2 * np.pi, n, endpoint=False)
    circle = np.stack([np.cos(t), np.sin(t)], axis=1)
    return mean + n_sigma * (circle * np.sqrt(w)) @ V.T


def _text(img: np.ndarray, text: str, org: tuple[int, int], scale: float, color, bg=(0, 0, 0)) -> int:
    """Text with a filled background box; returns the box height."""
    thick = max(1, int(round(scale * 2)))
    (tw, th), base = cv2.getTextSize(text, _FONT, scale, thick)
    x, y = org
    cv2.rectangle(img, (x - 2, y - th - 3), (x + tw + 2, y + base + 1), bg, -1)
    cv2.putText(img, text, (x, y), _FONT, scale, color, thick, _AA)
    return th + base + 4


def draw_body(
    image: np.ndarray,
    camera: Camera,
    joints: np.ndarray | None,
    joint_names: Sequence[str],
    blobs2d: Sequence[Blob2D] | None = None,
    priors: Sequence[Prior2D] | None = None,
    color: tuple[int, int, int] = PRED_COLOR,
    *,
    camera_label: str | None = None,
    frame: int | None = None,
    thickness: int | None = None,
) -> np.ndarray:
    """Draw a projected skeleton (and optionally 2-D blobs / priors) on a copy of ``image``.

    image: (H, W, 3) uint8 BGR of ``camera`` (working resolution); joints: (J, 3) world, m,
    named by ``joint_names`` (bones in :data:`BONES` between known names; joints behind the
    camera or NaN are skipped; right-side bones drawn darker); blobs2d: observed blobs, solid
    2-sigma ellipses in a colour per label; priors: projected priors, thin dashed 2-sigma
    ellipses (only VISIBLE ones). ``camera_label`` (default the camera name) and ``frame``
    are written top-left. Returns the new image.
    """
    out = np.ascontiguousarray(image, dtype=np.uint8).copy()
    if out.ndim == 2:
        out = cv2.cvtColor(out, cv2.COLOR_GRAY2BGR)
    h, w = out.shape[:2]
    th = thickness or max(1, int(round(min(w, h) / 240)))
    lim = 8.0 * max(w, h)  # beyond this, a projection is meaningless for drawing

    if priors:
        for p in priors:
            if p.visibility != VISIBLE:
                continue
            pts = _ellipse_points(p.mean, p.cov)
            if pts is None or np.abs(pts).max() > lim:
                continue
            col = _label_color(p.label)
            fixed = np.round(pts * (1 << _SHIFT)).astype(np.int32)
            for k in range(0, len(fixed), 2):  # dashed: every other segment
                cv2.line(out, tuple(fixed[k]), tuple(fixed[(k + 1) % len(fixed)]), col, 1, _AA, _SHIFT)
            cv2.drawMarker(out, (int(round(p.mean[0])), int(round(p.mean[1]))), col, cv2.MARKER_CROSS,
                           6 + 2 * th, 1, _AA)

    if blobs2d:
        for b in blobs2d:
            pts = _ellipse_points(b.mean, b.cov)
            if pts is None or np.abs(pts).max() > lim:
                continue
            col = _label_color(b.label)
            cv2.polylines(out, [np.round(pts * (1 << _SHIFT)).astype(np.int32)], True, col, th, _AA, _SHIFT)
            c = np.asarray(b.mean, dtype=float)
            cv2.circle(out, _fixed(c), (1 + th) << _SHIFT, col, -1, _AA, _SHIFT)
            cv2.putText(out, b.label, (int(c[0]) + 4, int(c[1]) - 4), _FONT, 0.3 + 0.1 * th, col, 1, _AA)

    if joints is not None:
        J = np.asarray(joints, dtype=float).reshape(-1, 3)
        names = list(joint_names)
        if J.shape[0] != len(names):
            raise ValueError(f"draw_body: {J.shape[0]} joints for {len(names)} joint names")
        finite = np.all(np.isfinite(J), axis=1)
        uv = np.full((J.shape[0], 2), np.nan)
        if finite.any():
            uv_f, depth = camera.project(J[finite])
            ok = (depth > 1e-6) & np.all(np.abs(uv_f) < lim, axis=1)
            uv_f[~ok] = np.nan
            uv[finite] = uv_f
        idx = {n: i for i, n in enumerate(names)}
        dark = tuple(int(c * 0.55) for c in color)
        for a, b in BONES:
            if a not in idx or b not in idx:
                continue
            pa, pb = uv[idx[a]], uv[idx[b]]
            if np.isnan(pa).any() or np.isnan(pb).any():
                continue
            col = dark if b.startswith("r_") else color
            cv2.line(out, _fixed(pa), _fixed(pb), col, th + 1, _AA, _SHIFT)
        r_ring, r_dot = int((th + 1.5) * (1 << _SHIFT)), int((th + 0.5) * (1 << _SHIFT))
        for i, p in enumerate(uv):
            if not np.isnan(p).any():
                cv2.circle(out, _fixed(p), r_ring, (255, 255, 255), -1, _AA, _SHIFT)
                col = dark if names[i].startswith("r_") else color
                cv2.circle(out, _fixed(p), r_dot, col, -1, _AA, _SHIFT)

    label = camera.name if camera_label is None else camera_label
    if frame is not None:
        label = f"{label}  frame {frame}"
    if label:
        scale = max(0.4, min(w, h) / 600)
        _text(out, label, (6, int(8 + 22 * scale)), scale, (255, 255, 255))
    return out


def montage(images: Sequence[np.ndarray], cols: int = 2) -> np.ndarray:
    """Tile images row-major into one (rows * H, cols * W, 3) uint8 BGR image.

    Every tile takes the size (H, W) of the first image (others are resized, INTER_AREA);
    missing tiles in the last row are black. ``cols`` is clipped to [1, len(images)].
    """
    if not images:
        raise ValueError("montage: no images")
    tiles = []
    h, w = images[0].shape[:2]
    for im in images:
        im = np.asarray(im, dtype=np.uint8)
        if im.ndim == 2:
            im = cv2.cvtColor(im, cv2.COLOR_GRAY2BGR)
        if im.shape[:2] != (h, w):
            im = cv2.resize(im, (w, h), interpolation=cv2.INTER_AREA)
        tiles.append(im)
    cols = max(1, min(int(cols), len(tiles)))
    rows = (len(tiles) + cols - 1) // cols
    out = np.zeros((rows * h, cols * w, 3), np.uint8)
    for k, im in enumerate(tiles):
        r, c = divmod(k, cols)
        out[r * h : (r + 1) * h, c * w : (c + 1) * w] = im
    return out


def _temp_sibling(path: Path, suffix: str) -> Path:
    """An unused hidden name next to ``path`` (not created: files get the usual umask permissions)."""
    check_output_path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    while True:
        tmp = path.with_name(f".{path.name}.{secrets.token_hex(4)}{suffix}")
        if not tmp.exists():
            return tmp


def write_montage_png(images: Sequence[np.ndarray], path: str | os.PathLike, cols: int = 2) -> Path:
    """:func:`montage` of ``images`` written as a PNG (atomically). Returns the path."""
    out = Path(path)
    ok, buf = cv2.imencode(".png", montage(images, cols))
    if not ok:
        raise InputError(f"{out}: PNG encoding failed")
    tmp = _temp_sibling(out, ".tmp")
    try:
        with tmp.open("xb") as fh:
            fh.write(buf.tobytes())
        os.replace(tmp, out)
    finally:
        tmp.unlink(missing_ok=True)
    return out


def write_mp4(frames: Iterable[np.ndarray], path: str | os.PathLike, fps: float = 30.0) -> int:
    """Write (H, W, 3) uint8 BGR frames as an MP4 (mp4v); returns the number of frames.

    The size is the first frame's (later frames are resized to it). Written to a temporary
    sibling and renamed when complete; no frames or an unusable writer raise InputError.
    """
    out = Path(path)
    if not (fps > 0 and math.isfinite(fps)):
        raise InputError(f"{out}: fps must be positive, got {fps}")
    tmp = _temp_sibling(out, ".tmp.mp4")
    writer = None
    n = 0
    try:
        for img in frames:
            img = np.ascontiguousarray(img, dtype=np.uint8)
            if img.ndim == 2:
                img = cv2.cvtColor(img, cv2.COLOR_GRAY2BGR)
            if writer is None:
                h, w = img.shape[:2]
                writer = cv2.VideoWriter(str(tmp), cv2.VideoWriter_fourcc(*"mp4v"), float(fps), (w, h))
                if not writer.isOpened():
                    raise InputError(f"{out}: cannot open an MP4 writer (mp4v) for {w}x{h}")
            elif img.shape[:2] != (h, w):
                img = cv2.resize(img, (w, h), interpolation=cv2.INTER_AREA)
            writer.write(img)
            n += 1
        if writer is None:
            raise InputError(f"{out}: no frames to write")
        writer.release()
        writer = None
        os.replace(tmp, out)
    finally:
        if writer is not None:
            writer.release()
        tmp.unlink(missing_ok=True)
    return n


# ------------------------------------------------------------------ `artrack overlay`
def _parse_frames(spec: str | None, n_frames: int, video: bool) -> range:
    """'i', 'a:b' (b exclusive, either may be empty or negative) or None (middle frame / all)."""
    if spec is None or spec == "":
        return range(0, n_frames) if video else range(n_frames // 2, n_frames // 2 + 1)
    m = re.fullmatch(r"\s*(-?\d+)?\s*(:)?\s*(-?\d+)?\s*", spec)
    if not m or (m.group(1) is None and m.group(2) is None):
        raise InputError(f"--frames '{spec}': expected an index 'i' or a range 'a:b'")
    a = int(m.group(1)) if m.group(1) else 0
    if m.group(2) is None:
        a = a + n_frames if a < 0 else a
        return range(a, a + 1)
    b = int(m.group(3)) if m.group(3) else n_frames
    return range(*slice(a, b).indices(n_frames))


def render_overlay(
    scene,
    pred=None,
    out: str | os.PathLike = "overlay.png",
    *,
    frames: str | None = None,
    cols: int = 2,
    fps: float = 30.0,
    quiet: bool = True,
    tolerance_ns: int = 5_000_000,
) -> Path:
    """Draw ground truth (green, from the scene) and a prediction (magenta) on every camera.

    scene: :class:`artrack.bags.Scene`; pred: (stamps (T,) ns, joint_names, joints (T, J, 3))
    or None, matched to frames by the nearest stamp within ``tolerance_ns``. ``out`` ending in
    ``.png``: a montage of one frame (default the middle one; ``frames`` 'i' or the first of
    'a:b'); ``.mp4``: a montage video of the selected frames (default all). Returns ``out``.
    """
    from .progress import Progress

    out = Path(out)
    kind = out.suffix.lower()
    if kind not in (".png", ".mp4"):
        raise InputError(f"{out}: output must end in .png or .mp4")
    n = int(scene.n_frames or 0)
    sel = _parse_frames(frames, n, video=kind == ".mp4")
    if len(sel) == 0 or sel.start >= n or sel.start < 0:
        raise InputError(f"{scene.path}: frame selection '{frames}' is outside the {n} frames")
    if kind == ".png":
        sel = range(sel.start, sel.start + 1)
    truth = scene.truth
    p_stamps = np.asarray(pred[0], dtype=np.int64) if pred is not None else np.zeros(0, np.int64)
    by_name = {c.name: c for c in scene.cameras}

    def nearest(stamps: np.ndarray, s: int) -> int | None:
        if stamps.size == 0:
            return None
        i = int(np.argmin(np.abs(stamps - s)))
        return i if abs(int(stamps[i]) - s) <= tolerance_ns else None

    def tiles():
        for index, (stamp, images) in enumerate(scene.frames()):
            if index >= sel.stop:
                return
            if index not in sel:
                continue
            t_i = nearest(truth.stamps, stamp) if truth is not None else None
            p_i = nearest(p_stamps, stamp)
            drawn = []
            for name in scene.camera_names:
                if name not in images:
                    continue
                img, cam = images[name], by_name[name]
                base = max(1, int(round(min(img.shape[:2]) / 240)))
                if t_i is not None:  # truth wider, underneath the prediction
                    img = draw_body(img, cam, truth.joints[t_i], truth.joint_names, color=TRUTH_COLOR,
                                    camera_label="", thickness=base + 1)
                if p_i is not None:
                    img = draw_body(img, cam, pred[2][p_i], pred[1], color=PRED_COLOR, camera_label="",
                                    thickness=base)
                img = draw_body(img, cam, None, [], frame=index)
                scale = max(0.4, min(img.shape[:2]) / 600)
                y = img.shape[0] - 8
                if p_i is not None:
                    y -= _text(img, "prediction", (6, y), scale, PRED_COLOR)
                if t_i is not None:
                    _text(img, "ground truth", (6, y), scale, TRUTH_COLOR)
                drawn.append(img)
            yield montage(drawn, cols)

    it = Progress(tiles(), total=len(sel), label="overlay", quiet=quiet)
    if kind == ".png":
        first = next(iter(it), None)
        if first is None:
            raise InputError(f"{scene.path}: frame {sel.start} could not be read")
        write_montage_png([first], out, cols=1)
    else:
        write_mp4(it, out, fps)
    return out
