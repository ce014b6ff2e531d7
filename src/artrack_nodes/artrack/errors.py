"""Domain errors. Each message names the file, topic or field that is wrong."""


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
