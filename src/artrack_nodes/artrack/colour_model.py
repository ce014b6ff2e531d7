"""Colour classes of the 2-D blob tracker (ALGORITHMS.md §1, "2-D blobs"): pixel colour features
and a Gaussian colour model per class.

Pixel features. Every pixel (i, j) has the observation ``o = (u, v, r, g, I)``:
image position (u = column, v = row, px, (0, 0) the centre of the top-left
pixel) and colour as normalised chroma ``r = R / S``, ``g = G / S`` and intensity
``I = S / 765`` with ``S = R + G + B`` (``colour_features``). Chroma is insensitive
to shading; intensity separates e.g. dark hair from skin of the same chroma.

A colour class's model (:class:`ColourModel`) is a Gaussian over (r, g, I), optionally with hard
floors (``min_intensity``, ``min_red_excess``); skin and the classes of ``colour_defaults`` start
from a configured model (:func:`configured_model`), the others are bootstrapped by the tracker
(:mod:`artrack.blobs`, "Blob classes").
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .blob_config import SKIN, BlobTrackerConfig

__all__ = ["ColourModel", "colour_features", "configured_model", "skin_model", "unknown_model"]

_F32 = np.float32


def colour_features(bgr: np.ndarray) -> np.ndarray:
    """Colour features (r, g, I) of BGR pixels.

    bgr: (..., 3) uint8 (or float grey levels 0..255). Returns (..., 3) float32: normalised
    chroma r = R/S, g = G/S and intensity I = S/765 in [0, 1], S = R + G + B (S < 1 taken as 1).
    """
    f = np.asarray(bgr, dtype=_F32)
    s = f[..., 0] + f[..., 1] + f[..., 2]
    inv = 1.0 / np.maximum(s, 1.0)
    out = np.empty(f.shape, _F32)
    out[..., 0] = f[..., 2] * inv
    out[..., 1] = f[..., 1] * inv
    out[..., 2] = s * _F32(1.0 / 765.0)
    return out


@dataclass
class ColourModel:
    """Gaussian colour model of one colour class over (r, g, I): mean (3,), cov (3, 3).

    ``learned`` is False while the model is still the configured default (replaced, not
    blended, by the first statistics); ``min_intensity`` rejects darker pixels outright, and
    ``min_red_excess`` pixels whose chroma r - g is smaller.
    """

    mean: np.ndarray
    cov: np.ndarray
    learned: bool = False
    min_intensity: float = 0.0
    min_red_excess: float = 0.0
    #: the last whitening computed and what it was computed from (mean, cov, floors, features)
    _whitening: tuple | None = field(default=None, repr=False, compare=False)

    def whitening(self, config: BlobTrackerConfig) -> tuple[np.ndarray, float]:
        """(A (3, 4) float32, log|Σ|): ``A @ [c; 1]`` is the whitened residual, so that
        |A [c; 1]|² is the squared Mahalanobis distance of colour c (variance floors added;
        the intensity row is zero in 'rg' mode, where log|Σ| is that of the chroma marginal).
        Cached until the model's mean or covariance (or those settings) change."""
        key = (np.asarray(self.mean, float).tobytes(), np.asarray(self.cov, float).tobytes(),
               config.colour_min_sigma_chroma, config.colour_min_sigma_intensity, config.colour_features)
        if self._whitening is not None and self._whitening[0] == key:
            A, log_det = self._whitening[1]
            return A.copy(), log_det
        result = self._compute_whitening(config)
        self._whitening = (key, (result[0].copy(), result[1]))
        return result

    def _compute_whitening(self, config: BlobTrackerConfig) -> tuple[np.ndarray, float]:
        floor = config.colour_floor ** 2
        cov = np.asarray(self.cov, float) + np.diag(floor)
        n = 2 if config.colour_features == "rg" else 3
        L = np.linalg.cholesky(cov[:n, :n])
        Linv = np.linalg.inv(L)
        A = np.zeros((3, 4))
        A[:n, :n] = Linv
        A[:n, 3] = -Linv @ np.asarray(self.mean, float)[:n]
        return A.astype(_F32), 2.0 * float(np.sum(np.log(np.diag(L))))

    def distance2(self, colours: np.ndarray, config: BlobTrackerConfig) -> np.ndarray:
        """Squared Mahalanobis distance (N,) of colours (N, 3) (intensity below the minimum: inf)."""
        A, _ = self.whitening(config)
        c = np.asarray(colours, _F32).reshape(-1, 3)
        z = c @ A[:, :3].T + A[:, 3]
        d2 = np.einsum("ij,ij->i", z, z)
        if self.has_floors:
            d2[~self.admits(c)] = np.inf
        return d2

    @property
    def has_floors(self) -> bool:
        """Whether ``admits`` can reject a colour (``min_intensity`` or ``min_red_excess`` set)."""
        return self.min_intensity > 0 or self.min_red_excess > 0

    def admits(self, colours: np.ndarray) -> np.ndarray:
        """(N,) bool: the colours (N, 3) that pass ``min_intensity`` and ``min_red_excess``."""
        c = np.asarray(colours).reshape(-1, 3)
        ok = np.ones(c.shape[0], bool)
        if self.min_intensity > 0:
            ok &= c[:, 2] >= self.min_intensity
        if self.min_red_excess > 0:
            ok &= (c[:, 0] - c[:, 1]) >= self.min_red_excess
        return ok


def skin_model(config: BlobTrackerConfig) -> ColourModel:
    """The configured default skin colour model (``skin_mean``, ``skin_sigma``, ``skin_rg_correlation``,
    ``skin_min_intensity``, ``skin_min_red_excess``)."""
    sr, sg, si = config.skin_sigma
    rho = config.skin_rg_correlation
    cov = np.array([[sr * sr, rho * sr * sg, 0.0], [rho * sr * sg, sg * sg, 0.0], [0.0, 0.0, si * si]])
    return ColourModel(np.array(config.skin_mean, float), cov, False, config.skin_min_intensity,
                       config.skin_min_red_excess)


def configured_model(config: BlobTrackerConfig, colour_class: str) -> ColourModel | None:
    """The configured start model of a colour class: skin's (:func:`skin_model`), one of
    ``colour_defaults`` (diagonal covariance), or None for a class that is bootstrapped."""
    if colour_class == SKIN:
        return skin_model(config)
    d = config.colour_defaults.get(colour_class)
    if d is None:
        return None
    return ColourModel(np.array(d["mean"], float), np.diag(np.square(d["sigma"])), False, 0.0)


def unknown_model(config: BlobTrackerConfig) -> ColourModel:
    """The start model of a class that is bootstrapped (grey chroma, ``unknown_colour_sigma``)."""
    cov = np.diag(np.square(config.unknown_colour_sigma))
    return ColourModel(np.array([1 / 3, 1 / 3, 0.5]), cov, False, 0.0)
