"""A minimal progress bar for long offline runs (stderr, only on a terminal or when forced)."""

from __future__ import annotations

import sys
import time
from collections.abc import Iterable, Iterator
from typing import TypeVar

T = TypeVar("T")


class Progress(Iterator[T]):
    """Wraps an iterable; draws `label [#####.....] i/total  fps  eta` on stderr."""

    def __init__(self, items: Iterable[T], total: int | None = None, label: str = "", quiet: bool = False,
                 width: int = 30):
        self.it = iter(items)
        self.total = total
        self.label = label
        self.width = width
        self.enabled = not quiet and sys.stderr.isatty()
        self.i = 0
        self.t0 = time.perf_counter()
        self.last_draw = 0.0

    def __iter__(self) -> Progress[T]:
        return self

    def __next__(self) -> T:
        try:
            item = next(self.it)
        except StopIteration:
            self._draw(final=True)
            raise
        self.i += 1
        self._draw()
        return item

    def _draw(self, final: bool = False) -> None:
        if not self.enabled:
            return
        now = time.perf_counter()
        if not final and now - self.last_draw < 0.1:
            return
        self.last_draw = now
        rate = self.i / max(now - self.t0, 1e-9)
        if self.total:
            frac = min(self.i / self.total, 1.0)
            bar = "#" * int(frac * self.width) + "." * (self.width - int(frac * self.width))
            eta = (self.total - self.i) / rate if rate > 0 else 0.0
            text = f"\r{self.label} [{bar}] {self.i}/{self.total} {rate:5.1f}/s eta {eta:4.0f}s"
        else:
            text = f"\r{self.label} {self.i} {rate:5.1f}/s"
        sys.stderr.write(text + ("\n" if final else ""))
        sys.stderr.flush()
