"""Health of the skeleton's inputs and output for /diagnostics and the log: which cameras
report, which went silent (and came back), tracking status and quality of the last body."""

from __future__ import annotations

import math
import time
from collections.abc import Callable

from artrack.types import STATUS_INITIALIZING, STATUS_LOST, STATUS_TRACKING

STATUS_NAMES = {STATUS_INITIALIZING: "initializing", STATUS_TRACKING: "tracking", STATUS_LOST: "lost"}


class CameraWatch:
    """A camera is *silent* when it has sent nothing for ``silent_after_s`` (default: the longer
    of 1 s and 10 frames) while another camera did; the tracker goes on with the others and
    says so: one warning line when a camera goes silent, one info line when it is back, and
    the diagnostics name the silent cameras (level WARN)."""

    def __init__(self, names: list[str], fps: float, silent_after_s: float | None = None):
        self.names = list(names)
        self.silent_after_s = silent_after_s if silent_after_s is not None else max(1.0, 10.0 / fps)
        self.last: dict[str, float] = {}
        self.t_first: float | None = None  # first message of any camera
        self.silent: set[str] = set()
        self.status: int | None = None
        self.quality = math.nan
        self.used: list[str] = []

    def seen(self, camera: str) -> None:
        self.last[camera] = time.monotonic()
        if self.t_first is None:
            self.t_first = self.last[camera]

    def estimated(self, estimate, cameras: list[str]) -> None:
        self.status, self.quality, self.used = int(estimate.status), float(estimate.quality), list(cameras)

    def silent_now(self, now: float) -> set[str]:
        if not self.last:
            return set()
        newest = max(self.last.values())
        if now - newest > self.silent_after_s:
            return set()  # nobody reports: no input at all, not one camera's fault
        # a camera that never reported counts from the first message of any camera
        since = {c: self.last.get(c, self.t_first if self.t_first is not None else newest) for c in self.names}
        return {c for c in self.names if now - since[c] > self.silent_after_s}

    def report(self, node) -> Callable:
        """The NodeDiagnostics update hook of ``node``."""

        def update(diag) -> None:
            now = time.monotonic()
            silent = self.silent_now(now)
            log = node.get_logger()
            reporting = [c for c in self.names if c not in silent and c in self.last]
            for c in sorted(silent - self.silent):
                age = now - self.last[c] if c in self.last else math.inf
                log.warning(f"camera {c} silent for {age:.1f} s: tracking with {', '.join(reporting) or 'none'}")
            for c in sorted(self.silent - silent):
                log.info(f"camera {c} is back")
            self.silent = silent
            diag.set("cameras_reporting", ",".join(reporting))
            diag.set("cameras_silent", ",".join(sorted(silent)))
            diag.set("cameras_in_last_frame", ",".join(self.used))
            diag.set("tracking_status", STATUS_NAMES.get(self.status, "none") if self.status is not None else "none")
            diag.set("track_quality", self.quality)
            if silent:
                diag.warn(f"camera(s) {', '.join(sorted(silent))} silent")
            if self.status == STATUS_LOST:
                diag.warn("body lost")

        return update
