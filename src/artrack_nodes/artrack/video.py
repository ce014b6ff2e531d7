"""Synchronised multi-camera video files, checked against the calibration.

``open_videos(paths, cameras, scale)`` pairs one video file with each calibrated
camera and yields frames ``(index, stamp_ns, {camera name: (H, W, 3) uint8 BGR})``
at the working resolution ``scale`` x calibrated size (``cv2.resize``,
INTER_AREA when shrinking); ``VideoSet.cameras`` are the matching
``Camera.scaled(scale)`` cameras. Stamps come from the frame rate:
``start_stamp_ns + round(index * 1e9 / fps)`` ns.

Size check: every video must have the calibrated size, except that a video
narrower by at most 8 px with the same height is accepted and padded on the
right (edge pixels replicated) with K unchanged. This is the documented
Qualisys case (/work/shared/DATA.md): the 1080-wide Pose2Sim demo videos lack
the 8 rightmost columns of the 1088-wide ``fov_video`` calibration. Anything
else raises :class:`~artrack.errors.InputError` naming the file and both sizes.

Pass the CALIBRATED cameras: the scaling is done here (passing cameras that are
already scaled fails the size check, by design, rather than scaling twice).
"""

from __future__ import annotations

import contextlib
import math
import os
import re
import sys
import tempfile
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from .cameras import Camera
from .errors import InputError

__all__ = ["MAX_RIGHT_PAD_PX", "VideoSet", "open_videos"]

#: Largest number of missing right-hand columns accepted (Qualisys 1080 vs 1088).
MAX_RIGHT_PAD_PX = 8
#: Relative frame-rate difference above which videos are not considered synchronised.
_FPS_TOLERANCE = 1e-3


@dataclass
class _Source:
    path: Path
    camera: Camera  # calibrated
    working: Camera  # scaled
    video_w: int
    video_h: int
    pad_right: int
    fps: float
    n_frames: int  # as the container reports it (may be approximate or 0)


@contextlib.contextmanager
def _captured_stderr() -> Iterator[list[str]]:
    """Collect what C libraries (FFmpeg, OpenCV) print on file descriptor 2 meanwhile.

    Yields a list that holds the non-empty lines once the block ends."""
    lines: list[str] = []
    try:
        saved = os.dup(2)
    except OSError:  # no usable stderr: nothing to capture
        yield lines
        return
    with tempfile.TemporaryFile() as tmp:
        sys.stderr.flush()
        os.dup2(tmp.fileno(), 2)
        try:
            yield lines
        finally:
            os.dup2(saved, 2)
            os.close(saved)
            tmp.seek(0)
            lines.extend(ln.strip() for ln in tmp.read().decode(errors="replace").splitlines() if ln.strip())


#: FFmpeg's log prefix, e.g. "[mov,mp4,m4a,3gp,3g2,mj2 @ 0x5649be9b7780] ".
_AV_PREFIX = re.compile(r"^\[[^\]]* @ 0x[0-9a-f]+\]\s*")


def _open(path: Path) -> cv2.VideoCapture:
    """Open a video; failure is one InputError line (FFmpeg's complaint in brackets, not on stderr)."""
    with _captured_stderr() as noise:
        cap = cv2.VideoCapture(str(path))
        ok = cap.isOpened()
    if not ok:
        cap.release()
        detail = f": {_AV_PREFIX.sub('', noise[-1])}" if noise else ""
        raise InputError(f"{path}: cannot open video (unsupported format or codec{detail})")
    if noise:  # opened after all: pass the library's messages on unchanged
        print("\n".join(noise), file=sys.stderr)
    return cap


class VideoSet:
    """Several video files read in lockstep; iterate for ``(index, stamp_ns, {name: BGR})``.

    cameras: working-resolution cameras (calibrated cameras scaled by ``scale``), in order;
    fps: the common frame rate; n_frames: the shortest container frame count (approximate
    for some formats; iteration stops when the first video ends). Re-iterable: each
    iteration reopens the files.
    """

    def __init__(self, sources: list[_Source], scale: float, fps: float, start_stamp_ns: int,
                 max_frames: int | None):
        self._sources = sources
        self.scale = scale
        self.fps = fps
        self.start_stamp_ns = int(start_stamp_ns)
        self.max_frames = max_frames
        self.cameras = [s.working for s in sources]
        self.paths = [s.path for s in sources]
        counts = [s.n_frames for s in sources if s.n_frames > 0]
        n = min(counts) if counts else None
        if n is not None and max_frames is not None:
            n = min(n, max_frames)
        self.n_frames = n

    def stamp_ns(self, index: int) -> int:
        """Stamp of frame ``index``, ns."""
        return self.start_stamp_ns + int(round(index * 1e9 / self.fps))

    def __len__(self) -> int:
        return self.n_frames or 0

    def __iter__(self) -> Iterator[tuple[int, int, dict[str, np.ndarray]]]:
        caps = []
        try:
            for s in self._sources:
                caps.append(_open(s.path))
            index = 0
            while self.max_frames is None or index < self.max_frames:
                images = {}
                for s, cap in zip(self._sources, caps, strict=True):
                    ok, frame = cap.read()
                    if not ok or frame is None:
                        return
                    images[s.camera.name] = self._prepare(s, frame, index)
                yield index, self.stamp_ns(index), images
                index += 1
        finally:
            for cap in caps:
                cap.release()

    def _prepare(self, s: _Source, frame: np.ndarray, index: int) -> np.ndarray:
        if frame.ndim == 2:
            frame = cv2.cvtColor(frame, cv2.COLOR_GRAY2BGR)
        h, w = frame.shape[:2]
        if (w, h) != (s.video_w, s.video_h):
            raise InputError(
                f"{s.path}: frame {index} is {w}x{h}, the video header says {s.video_w}x{s.video_h}"
            )
        if s.pad_right:
            frame = cv2.copyMakeBorder(frame, 0, 0, 0, s.pad_right, cv2.BORDER_REPLICATE)
        if (s.working.width, s.working.height) != (s.camera.width, s.camera.height):
            interp = cv2.INTER_AREA if self.scale < 1.0 else cv2.INTER_LINEAR
            frame = cv2.resize(frame, (s.working.width, s.working.height), interpolation=interp)
        return np.ascontiguousarray(frame, dtype=np.uint8)


def open_videos(
    paths: Sequence[str | os.PathLike] | Mapping[str, str | os.PathLike],
    cameras: Sequence[Camera],
    scale: float = 1.0,
    *,
    fps: float | None = None,
    start_stamp_ns: int = 0,
    max_frames: int | None = None,
) -> VideoSet:
    """Open one video per camera and check it against the calibration (see the module docstring).

    paths: a sequence paired in order with ``cameras`` (same length), or a mapping
    camera name -> file (only the named cameras are used, in calibration order; an
    unknown name raises InputError). cameras: CALIBRATED cameras. scale: working
    resolution factor (> 0). fps: overrides the containers' frame rate (needed when
    they report none). Raises InputError naming the file and the problem.
    """
    scale = float(scale)
    if not (scale > 0 and math.isfinite(scale)):
        raise InputError(f"video scale must be a positive number, got {scale}")
    cams = list(cameras)
    if isinstance(paths, Mapping):
        by_name = {c.name: c for c in cams}
        unknown = [n for n in paths if n not in by_name]
        if unknown:
            raise InputError(
                f"{paths[unknown[0]]}: video for unknown camera '{unknown[0]}' "
                f"(calibration has: {', '.join(by_name) or 'none'})"
            )
        pairs = [(Path(paths[c.name]), c) for c in cams if c.name in paths]
    else:
        plist = [Path(p) for p in paths]
        if len(plist) != len(cams):
            raise InputError(f"{len(plist)} video file(s) for {len(cams)} camera(s): give one per camera")
        pairs = list(zip(plist, cams, strict=True))
    if not pairs:
        raise InputError("no video files given")

    sources = []
    for path, cam in pairs:
        if not path.is_file():
            raise InputError(f"{path}: video file not found (camera '{cam.name}')")
        cap = _open(path)
        try:
            vw = int(round(cap.get(cv2.CAP_PROP_FRAME_WIDTH)))
            vh = int(round(cap.get(cv2.CAP_PROP_FRAME_HEIGHT)))
            vfps = float(cap.get(cv2.CAP_PROP_FPS))
            count = int(cap.get(cv2.CAP_PROP_FRAME_COUNT) or 0)
        finally:
            cap.release()
        pad = cam.width - vw
        if vh != cam.height or not 0 <= pad <= MAX_RIGHT_PAD_PX:
            raise InputError(
                f"{path}: video is {vw}x{vh} but camera '{cam.name}' is calibrated for "
                f"{cam.width}x{cam.height}"
                + (" (pass the calibrated cameras; open_videos applies the scale)" if scale != 1.0 else "")
            )
        if fps is None and not (math.isfinite(vfps) and 0 < vfps < 10_000):
            raise InputError(f"{path}: video reports no usable frame rate ({vfps}); pass fps")
        working = cam.scaled(scale) if scale != 1.0 else cam
        sources.append(_Source(path, cam, working, vw, vh, pad, vfps, max(count, 0)))

    if fps is None:
        rate = sources[0].fps
        for s in sources[1:]:
            if abs(s.fps - rate) > _FPS_TOLERANCE * rate:
                raise InputError(
                    f"{s.path}: frame rate {s.fps:g} differs from {sources[0].path} ({rate:g}); "
                    "videos must be synchronised (or pass fps)"
                )
    else:
        rate = float(fps)
        if not (rate > 0 and math.isfinite(rate)):
            raise InputError(f"fps must be positive, got {fps}")
    return VideoSet(sources, scale, rate, start_stamp_ns, max_frames)
