"""Domain errors. Each message names the file, topic or field that is wrong."""

from __future__ import annotations

from pathlib import Path


class ArtrackError(Exception):
    """Base class of every error artrack raises on bad input."""


class CalibrationError(ArtrackError):
    """A calibration file is missing a field or holds an impossible value."""


class BodyModelError(ArtrackError):
    """The body-model file is inconsistent (unknown parent, bad joint type...)."""


class BagError(ArtrackError):
    """A bag is truncated, corrupt, or lacks a topic or field we need."""


class InputError(ArtrackError):
    """Any other bad input: video size mismatch, unknown camera name, ..."""


def check_output_path(path: Path) -> None:
    """InputError if ``path`` cannot be created because an existing ancestor is not a folder."""
    blocker = next((a for a in Path(path).parents if a.exists() or a.is_symlink()), None)
    if blocker is not None and not blocker.is_dir():
        raise InputError(f"{path}: cannot create output ({blocker} is not a directory)")
