"""Per-camera 2-D blob tracker: background model, MAP pixel classification with
priors, support map, blob statistics, start-up (ALGORITHMS.md §1, "2-D blobs").

Pixel features and colour classes: :mod:`artrack.colour_model`; the
background: :mod:`artrack.background`; the tunables: :mod:`artrack.blob_config`.

Blob classes. Each tracked label k is a Gaussian over ``o`` with a spatial part
(mean (2,), covariance (2, 2), px) and a colour part (mean (3,), covariance
(3, 3)); the colour part is shared by the labels of one colour class (e.g. head
and hands: 'skin'; thighs and shins: 'trousers'). 'skin' starts from a
configured model in normalised chroma, as does any class in ``colour_defaults``
(e.g. a cap of a colour the room lacks); a class without a default is bootstrapped
robustly (median / MAD, then trimmed mean and covariance) from the foreground in
its labels' prior cores (``colour_core_sigma``) on its first labelled frame. All
classes then follow their labelled core pixels that fit the model
(``colour_learn_gate``) at ``colour_learning_rate``, so ghosts and neighbours
cannot widen them. Gated learning cannot repair a model bootstrapped from the wrong
pixels (a start-up pose off the part: e.g. a shirt class learnt from a floor ghost
rejects the shirt for good), so a learned class (not skin) is bootstrapped again from its
labels' cores when the median colour of the foreground in those cores has been outside the
model's ``colour_learn_gate`` for ``colour_relearn_frames`` frames in a row. A bootstrap leaves out
the core pixels whose colour the room next to the person shows too (``colour_room_gate``): the
ghost of the start position is the room seen again, and a start-up prior off the part has its
core on it.
Each foreground pixel inside a label's gate gets the MAP label

    Γ_ij = argmax_k  log N(c_ij; μ_c(k), Σ_c(k)) + w · log(c_k · N((u, v); m_k, S_k))

where the second term is the class prior ``Pr(k at ij)``: with feedback, the
projected 3-D prior (Prior2D mean and covariance, the Gaussian scaled by its
confidence c_k floored at ``prior_min_confidence``, optionally widened by
``prior_confidence_inflation``, w = ``prior_weight``; a prior whose visibility is
not VISIBLE suppresses its label in this view); without a prior, 2-D temporal
smoothness (the previous frame's blob Gaussian, constant-velocity predicted,
inflated by ``temporal_inflation`` and ``temporal_motion_px``, c_k = 1,
w = ``temporal_weight``). Labels only compete inside their gates (``roi_sigma``
spatial Mahalanobis distance, ``colour_gate`` in colour); a foreground pixel
outside every gate stays unlabelled (−1), so a look-alike far from the
prediction (another person's hand) does not steal the label. The person is one
connected silhouette: with ``connected_to`` (e.g. 'torso'; off by default) a pixel keeps its
label only if its 8-connected foreground component (gaps up to ``connected_gap_px``
closed) holds at least a quarter of the most ``connected_to`` pixels any component
holds, so a label cannot settle on a detached region (a ghost of where the person
stood while the background seeded; the ghost, no longer anyone's support, then
heals). Classification runs only on the foreground pixels inside the rectangles
bounding the gates.
Each label's statistics (mean, covariance, colour mean and covariance, pixel
count) are then re-estimated from its pixels (8-connected pieces smaller than
``min_component_fraction`` of its largest piece are dropped first: mixed rim
pixels of neighbouring parts); a label with fewer than ``min_blob_pixels``
pixels is not reported ("not seen in this view").

Start-up (no priors and no blob tracked in 2-D): the tracker reports a
``foreground`` blob (Gaussian of all foreground pixels) and up to
``startup_max_skin_blobs`` ``skin`` blobs (connected components of skin-coloured
foreground pixels, largest first) for the 3-D stage to triangulate, once the
seed is complete and ``startup_settle_frames`` more frames have let the ghost healing
run (or, if ``startup_min_seed_samples`` > 0, once the seed holds that many samples:
a running median of a few samples absorbs a person who hardly moved, leaving only
their outline as foreground); labelled tracking starts with
the first priors and falls back to start-up when priors stop and every label has
been unseen for more than ``temporal_max_missed`` frames.

Lost parts. The spatial gates trust the prior, so a hand that moved faster than its
prediction finds nothing. While tracking, whenever a label of the skin colour class has
no pixels in this view, the tracker also reports up to ``lost_skin_blobs`` unlabelled
skin-coloured foreground components (label ``skin``, as at start-up); the 3-D stage
triangulates them and re-acquires the hand (``skeleton`` ``tracking.reacquire_*``).
The opposite failure, a skin label spread over more skin than its part (the other hand,
the face): a label of the skin class whose pixels outnumber ``max_prior_area_ratio``
times its projected 3-D prior's 2-sigma ellipse area is not reported, and its pixels
come back among those unlabelled skin components. Nor is a skin label nearly all of
whose pixels (``foreign_colour_share``) are likelier under another colour class labelled
in the view: a hand gone behind the body leaves its label on clothing of a skin-like
colour (khaki trousers), which the small prior's spatial term holds against the
trousers' better colour. (Only nearly all: a shaded hand's own pixels are often
likelier khaki too, and a half-hidden hand must keep its label.)

Weak points: a person standing still through the whole seed is background
until they move (the ghost they leave then heals within about
``background_ghost_frames`` frames where its outline is clear, else after
``background_static_frames``); there is no shadow model; clothing or floors with
skin-like chroma (khaki, beige tiles) pass the skin model (components larger
than ``startup_skin_max_fraction`` of the foreground are skipped at start-up);
the spatial gates trust the prior: a prediction off by more than ``roi_sigma``
sigmas of the part's projected extent finds nothing, or a neighbour.

All processing is deterministic (no randomness).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import cv2
import numpy as np
from scipy.spatial import cKDTree

from .background import BackgroundModel
from .blob_config import FOREGROUND, SKIN, BlobTrackerConfig
from .colour_model import ColourModel, colour_features, configured_model, unknown_model
from .errors import InputError
from .types import VISIBLE, Blob2D, Prior2D

__all__ = ["BlobTracker2D", "benchmark"]

_F32 = np.float32
_ROOM_SHARE = 0.002  # share of the room's colour samples near a core pixel that makes it room-coloured
_ROOM_CORE_SHARE = 0.25  # room-coloured share of a class's core from which those pixels are left out


class _RoomColours:
    """The room's colours next to the person in one frame (module docstring, "Blob classes"):
    the background pixels (at most ~8000, evenly subsampled) in a frame around ``rect`` (x0, y0,
    x1, y1, work px) as wide as the rectangle on each side, not inside it (there a person who
    covers their own seed-time ghost matches the model and is background). Sampled on the first
    :meth:`coloured` call only."""

    def __init__(self, img: np.ndarray, fg: np.ndarray, rect: tuple[int, int, int, int],
                 config: BlobTrackerConfig):
        self.img, self.fg, self.rect, self.config = img, fg, rect, config
        self._tree: tuple[cKDTree, int] | None = None

    def coloured(self, colours: np.ndarray) -> np.ndarray:
        """(n,) bool: the colours (n, 3) that at least ``_ROOM_SHARE`` of the room's (and at least 3)
        lie within ``colour_room_gate`` of (in units of the colour floors); all False when the
        gate is 0 or no room is in view."""
        gate = self.config.colour_room_gate
        if gate <= 0 or not len(colours):
            return np.zeros(len(colours), bool)
        if self._tree is None:
            x0, y0, x1, y1 = self.rect
            H, W = self.fg.shape
            w, h = x1 - x0, y1 - y0
            X0, Y0, X1, Y1 = max(0, x0 - w), max(0, y0 - h), min(W, x1 + w), min(H, y1 + h)
            ring = ~self.fg[Y0:Y1, X0:X1]
            ring[max(0, y0 - Y0):max(0, y1 - Y0), max(0, x0 - X0):max(0, x1 - X0)] = False
            ys, xs = np.nonzero(ring)
            step = max(1, ys.size // 4000)
            room = colour_features(self.img[ys[::step] + Y0, xs[::step] + X0]) / self.config.colour_floor
            self._tree = (cKDTree(room), room.shape[0])
        tree, n = self._tree
        if n == 0:
            return np.zeros(len(colours), bool)
        near = tree.query_ball_point(np.asarray(colours, float) / self.config.colour_floor, gate,
                                     return_length=True)
        return near >= max(3.0, _ROOM_SHARE * n)


# =========================================================================== tracker
@dataclass
class _Track:
    """2-D temporal memory of one label: last blob (work px), velocity (px/frame), frames missed."""

    mean: np.ndarray
    cov: np.ndarray
    velocity: np.ndarray = field(default_factory=lambda: np.zeros(2))
    missed: int = 0


@dataclass
class _ClassModel:
    """One label's class for one frame (work px): spatial prior and colour model."""

    index: int
    mean: np.ndarray  # (2,)
    cov: np.ndarray  # (2, 2)
    weight: float
    colour: ColourModel
    log_confidence: float = 0.0  # log of the prior's (floored) confidence; 0 for temporal priors
    rect: tuple[int, int, int, int] = (0, 0, 0, 0)  # x0, y0, x1, y1 (exclusive)
    det: float = 1.0  # det(cov), > 0
    precision: np.ndarray | None = None  # cov⁻¹ (2, 2)
    from_prior: bool = False  # the spatial prior is a projected 3-D prior (not the temporal one)


def _scale_gaussian(mean: np.ndarray, cov: np.ndarray, s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A 2-D Gaussian in pixels (pixel centres at integers) rescaled by s (2,) per axis:
    ``D (mean + ½) − ½`` and ``D cov D`` with D = diag(s), elementwise."""
    m = s * (np.asarray(mean, float).reshape(2) + 0.5) - 0.5
    return m, (s[:, None] * np.asarray(cov, float).reshape(2, 2)) * s[None, :]


def _rect(mean: np.ndarray, cov: np.ndarray, k: float, width: int, height: int) -> tuple[int, int, int, int]:
    """Pixel rectangle bounding the k-sigma ellipse of a 2-D Gaussian, clipped to the image."""
    hx, hy = k * math.sqrt(max(cov[0, 0], 0.0)), k * math.sqrt(max(cov[1, 1], 0.0))
    x0, x1 = max(0, math.floor(mean[0] - hx)), min(width, math.ceil(mean[0] + hx) + 1)
    y0, y1 = max(0, math.floor(mean[1] - hy)), min(height, math.ceil(mean[1] + hy) + 1)
    return x0, y0, max(x0, x1), max(y0, y1)


class BlobTracker2D:
    """One camera's 2-D blob tracker (module docstring; ALGORITHMS.md §1, "2-D blobs").

    camera_name: used in error messages; labels: the body-model blob labels tracked
    (e.g. 'head', 'l_hand'); colour_classes: label -> colour class ('skin', 'shirt',
    'trousers', ...; a label without one is its own class); config: tunables.

    ``step(image_bgr, priors)`` processes one frame. After it, ``support_map`` (H, W)
    int16 holds, per pixel, an index into ``support_labels`` (−1: background or
    unassigned) and ``foreground_mask`` (H, W) bool the foreground, both at the input
    resolution.
    """

    def __init__(
        self,
        camera_name: str,
        labels: list[str],
        colour_classes: dict[str, str] | None = None,
        config: BlobTrackerConfig | None = None,
    ):
        self.camera_name = str(camera_name)
        self.labels = [str(x) for x in labels]
        if len(set(self.labels)) != len(self.labels):
            raise InputError(f"camera '{self.camera_name}': duplicate blob labels {self.labels}")
        if FOREGROUND in self.labels or SKIN in self.labels:
            raise InputError(f"camera '{self.camera_name}': '{FOREGROUND}'/'{SKIN}' are start-up classes, "
                             "not link labels")
        self.config = config or BlobTrackerConfig()
        named = [("part_colours", part) for part in sorted(self.config.part_colours)]
        named += [("connected_to", self.config.connected_to)] if self.config.connected_to else []
        named += [("background_ghost_detached", part) for part in self.config.background_ghost_detached]
        self._ghost_detached_labels = frozenset(self.config.background_ghost_detached)
        for name, part in named:
            if part not in self.labels:
                raise InputError(f"camera '{self.camera_name}': blob tracker config field '{name}' names "
                                 f"unknown part '{part}' (parts: {', '.join(self.labels)})")
        classes = {**(colour_classes or {}), **self.config.part_colours}
        self.colour_classes = {lab: str(classes.get(lab, lab)) for lab in self.labels}
        self.reset()

    # ------------------------------------------------------------------ state
    def reset(self) -> None:
        """Forget everything: background, colour models, temporal memory."""
        self.background = BackgroundModel(self.config)
        self.colour_models: dict[str, ColourModel] = {}
        self.colour_stale_frames: dict[str, int] = {}  # colour class -> frames in a row its cores looked otherwise
        self.colour_relearned: dict[str, int] = {}  # colour class -> times bootstrapped again
        self.tracks: dict[str, _Track] = {}
        self.image_size: tuple[int, int] | None = None  # (W, H) input
        self.work_size: tuple[int, int] | None = None  # (W, H) working resolution
        self.support_labels: list[str] = []
        self.mode = "startup"
        self.timings_ms: dict[str, float] = {}  # per-stage ms of the last step
        self._support_work: np.ndarray | None = None
        self._fg_work: np.ndarray | None = None
        self._support_full: np.ndarray | None = None
        self._fg_full: np.ndarray | None = None

    def colour_model(self, colour_class: str) -> ColourModel:
        """Current colour model of a colour class (the configured default until learned)."""
        m = self.colour_models.get(colour_class)
        if m is None:
            m = configured_model(self.config, colour_class) or unknown_model(self.config)
            self.colour_models[colour_class] = m
        return m

    @property
    def support_map(self) -> np.ndarray:
        """(H, W) int16 at the input resolution: index into ``support_labels``, −1 = none."""
        if self._support_work is None:
            raise InputError(f"camera '{self.camera_name}': no frame processed yet")
        if self._support_full is None:
            self._support_full = self._to_full(self._support_work)
        return self._support_full

    @property
    def foreground_mask(self) -> np.ndarray:
        """(H, W) bool at the input resolution: the last frame's foreground."""
        if self._fg_work is None:
            raise InputError(f"camera '{self.camera_name}': no frame processed yet")
        if self._fg_full is None:
            self._fg_full = self._to_full(self._fg_work.view(np.uint8)).view(bool)
        return self._fg_full

    def _to_full(self, a: np.ndarray) -> np.ndarray:
        if self.work_size == self.image_size:
            return a
        return cv2.resize(a, self.image_size, interpolation=cv2.INTER_NEAREST)

    # ------------------------------------------------------------------ coordinates
    def _scale(self) -> tuple[float, float]:
        (W, H), (w, h) = self.image_size, self.work_size
        return w / W, h / H

    def _to_work(self, mean: np.ndarray, cov: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        sx, sy = self._scale()
        return _scale_gaussian(mean, cov, np.array([sx, sy]))

    def _from_work(self, mean: np.ndarray, cov: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        sx, sy = self._scale()
        return _scale_gaussian(mean, cov, np.array([1.0 / sx, 1.0 / sy]))

    def _min_pixels(self) -> int:
        """min_blob_pixels in working-resolution pixels (scaled with the image width, see config)."""
        sx, sy = self._scale()
        ref = self.config.min_blob_pixels_width
        area = (self.image_size[0] / ref) ** 2 if ref > 0 else 1.0
        return max(1, int(math.ceil(self.config.min_blob_pixels * area * sx * sy)))

    # ------------------------------------------------------------------ step
    def step(self, image_bgr: np.ndarray, priors: list[Prior2D] | None = None) -> list[Blob2D]:
        """Process one frame.

        image_bgr: (H, W, 3) uint8 BGR. priors: the projected 3-D predictions for this
        frame (one per label; labels not tracked here are ignored) or None (no feedback).
        Returns the blobs seen, label order for tracked labels; at start-up
        [``foreground``, ``skin`` (largest first) ...]. Means/covariances in input pixels.
        """
        img = np.asarray(image_bgr)
        if img.ndim != 3 or img.shape[2] != 3 or img.dtype != np.uint8:
            raise InputError(f"camera '{self.camera_name}': image must be (H, W, 3) uint8 BGR, "
                             f"got {img.dtype} {img.shape}")
        size = (img.shape[1], img.shape[0])
        if self.image_size is not None and size != self.image_size:
            self.reset()  # the stream changed resolution: start again
        if self.image_size is None:
            s = self.config.work_scale
            self.image_size = size
            self.work_size = (max(1, round(size[0] * s)), max(1, round(size[1] * s)))
        if self.work_size != self.image_size:
            img = cv2.resize(img, self.work_size, interpolation=cv2.INTER_AREA)
        img = np.ascontiguousarray(img)
        img_f = img.astype(_F32)
        self._support_full = self._fg_full = None
        self.timings_ms = {}
        t0 = time.perf_counter()

        fg = self.background.foreground(img, img_f)
        k = self.config.foreground_median
        if k > 1:
            fg = cv2.medianBlur(fg.view(np.uint8), k | 1).view(bool)
        self._fg_work = fg

        models = self._class_models(priors)
        if models is None:
            self.mode = "startup"
            if self._startup_allowed():
                blobs, explained = self._startup(img, fg)
            else:
                blobs, explained = [], np.zeros_like(fg)
                self._support_work = np.full(fg.shape, -1, np.int16)
                self.support_labels = []
        else:
            self.mode = "tracking"
            blobs, explained = self._track(img, fg, models)
            self.background.cap_variance()
        ghost_tested = None
        if self.mode == "tracking" and self._ghost_detached_labels:
            ghost_tested = self._detached_static_support(fg, explained)
        self.background.update(img, img_f, ~fg, fg & ~explained, ghost_tested)
        t1 = time.perf_counter()
        track = self.timings_ms
        # per-stage wall time of this frame, ms: classification and statistics (set by _track),
        # background (foreground test + model update) = the rest
        self.timings_ms = {"background": 1e3 * (t1 - t0) - sum(track.values()), **track}
        return blobs

    def _startup_allowed(self) -> bool:
        """Whether the background is trustworthy enough for start-up blobs (see
        ``startup_min_seed_samples`` and ``startup_settle_frames``)."""
        bg, cfg = self.background, self.config
        if not bg.ready:
            return 0 < cfg.startup_min_seed_samples <= len(bg.seed)
        return cfg.startup_min_seed_samples > 0 or bg.frames_ready > cfg.startup_settle_frames

    # ------------------------------------------------------------------ class priors
    def _class_models(self, priors: list[Prior2D] | None) -> list[_ClassModel] | None:
        """The per-label class priors of this frame (work px), or None for start-up mode."""
        cfg = self.config
        have_priors = bool(priors)
        if not have_priors and not self.tracks:
            return None
        by_label: dict[str, Prior2D] = {}
        for p in priors or ():
            if p.label in self.colour_classes:
                by_label[p.label] = p
        W, H = self.work_size
        models: list[_ClassModel] = []
        floor = np.eye(2) * cfg.min_sigma_px**2 * self._scale()[0] * self._scale()[1]
        for i, label in enumerate(self.labels):
            colour = self.colour_model(self.colour_classes[label])
            p = by_label.get(label)
            if p is not None:
                mean = np.asarray(p.mean, float).reshape(-1)
                cov = np.asarray(p.cov, float).reshape(-1)
                if p.visibility != VISIBLE or mean.size != 2 or cov.size != 4:
                    continue
                if not (np.all(np.isfinite(mean)) and np.all(np.isfinite(cov))):
                    continue
                conf = float(p.confidence) if math.isfinite(float(p.confidence)) else 0.0
                conf = min(max(conf, cfg.prior_min_confidence), 1.0)
                mean, cov = self._to_work(mean, cov.reshape(2, 2))
                cov = 0.5 * (cov + cov.T) * (1.0 + cfg.prior_confidence_inflation * (1.0 - conf)) + floor
                weight = cfg.prior_weight
                log_conf = math.log(conf)
            else:
                tr = self.tracks.get(label)
                if tr is None:
                    continue
                steps = tr.missed + 1
                mean = tr.mean + cfg.temporal_velocity * tr.velocity * steps
                sx, sy = self._scale()
                motion = (cfg.temporal_motion_px**2) * steps * np.diag([sx * sx, sy * sy])
                cov = cfg.temporal_inflation * tr.cov + motion + floor
                weight = cfg.temporal_weight
                log_conf = 0.0
            m = _ClassModel(i, mean, cov, weight, colour, log_conf, from_prior=p is not None)
            m.rect = _rect(mean, cov, cfg.roi_sigma, W, H)
            if m.rect[2] > m.rect[0] and m.rect[3] > m.rect[1]:
                models.append(m)
        if not models:
            return models
        # the classes' 2x2 determinants and inverses in one call each (per-matrix the same LAPACK routine)
        dets = np.linalg.det(np.array([m.cov for m in models]))
        models = [m for m, d in zip(models, dets, strict=True) if d > 0]
        if models:
            precisions = np.linalg.inv(np.array([m.cov for m in models]))
            for m, d, P in zip(models, dets[dets > 0], precisions, strict=True):
                m.det, m.precision = float(d), P
        return models

    # ------------------------------------------------------------------ tracking
    def _track(self, img: np.ndarray, fg: np.ndarray, models: list[_ClassModel]
               ) -> tuple[list[Blob2D], np.ndarray]:
        """MAP classification inside the ROIs, statistics, memory and colour updates.

        Returns the blobs and the (H, W) bool mask of labelled pixels (the support)."""
        cfg = self.config
        W, H = self.work_size
        support = np.full((H, W), -1, np.int16)
        self.support_labels = list(self.labels)
        self._support_work = support
        stats: dict[int, tuple[np.ndarray, np.ndarray, np.ndarray, int]] = {}
        core_colours: dict[str, list[np.ndarray]] = {}
        t0 = t1 = time.perf_counter()
        if models:
            # the foreground pixels inside the union of the ROIs, as lists (N,)
            x0 = min(m.rect[0] for m in models)
            y0 = min(m.rect[1] for m in models)
            x1 = max(m.rect[2] for m in models)
            y1 = max(m.rect[3] for m in models)
            ys, xs = np.nonzero(fg[y0:y1, x0:x1])
            ys += y0
            xs += x0
            feat = colour_features(img[ys, xs])
            u, v = xs.astype(_F32), ys.astype(_F32)
            best = np.full(xs.size, -np.inf, _F32)
            lab = np.full(xs.size, -1, np.int16)
            sels, ds2s = [], []
            gs2, gc2 = cfg.roi_sigma**2, cfg.colour_gate**2
            for m in models:
                # np.nonzero lists the pixels row by row: the ROI's rows are one slice of them
                r0, r1 = np.searchsorted(ys, (m.rect[1], m.rect[3]))
                sel = r0 + np.flatnonzero((xs[r0:r1] >= m.rect[0]) & (xs[r0:r1] < m.rect[2]))
                P = m.precision.astype(_F32)
                du, dv = u[sel] - _F32(m.mean[0]), v[sel] - _F32(m.mean[1])
                ds2 = P[0, 0] * du * du + 2 * P[0, 1] * du * dv + P[1, 1] * dv * dv
                gated = ds2 <= gs2  # the spatial gate: the ellipse inside the ROI rectangle
                sels.append(sel[gated])
                ds2s.append(ds2[gated])
            feats = [feat[sel] for sel in sels]  # each label's gated pixels' colours
            # colour class -> the colours (n, 3) of the foreground in its labels' cores (colour_core_sigma)
            core_fg = self._core_colours(models, [f[ds2 <= cfg.colour_core_sigma**2]
                                                  for f, ds2 in zip(feats, ds2s)])
            self._bootstrap_colours(core_fg, _RoomColours(img, fg, (x0, y0, x1, y1), cfg))
            dc2s = []
            for m, sel, ds2, f in zip(models, sels, ds2s, feats):
                A, logdet_c = m.colour.whitening(cfg)
                z = f @ A[:, :3].T + A[:, 3]
                dc2 = np.einsum("ij,ij->i", z, z)
                dc2s.append(dc2)
                ok = dc2 <= gc2
                if m.colour.has_floors:
                    ok &= m.colour.admits(f)
                log_prior = m.log_confidence - 0.5 * math.log(m.det)
                const = m.weight * log_prior - 0.5 * logdet_c
                score = _F32(const) - 0.5 * (dc2 + _F32(m.weight) * ds2)
                better = ok & (score > best[sel])
                idx = sel[better]
                best[idx] = score[better]
                lab[idx] = m.index
            self._keep_connected(fg, models, (x0, y0, x1, y1), xs - x0, ys - y0, lab)
            support[ys, xs] = lab
            t1 = time.perf_counter()
            min_px = self._min_pixels()
            core2, learn2 = cfg.colour_core_sigma**2, cfg.colour_learn_gate**2
            frame_classes = sorted({self.colour_classes[self.labels[m.index]] for m in models})
            for m, sel, ds2, dc2, fs in zip(models, sels, ds2s, dc2s, feats):
                pos = np.flatnonzero(lab[sel] == m.index)  # positions in sel
                n = pos.size
                px, py = xs[sel[pos]], ys[sel[pos]]
                if n >= min_px and cfg.min_component_fraction > 0:
                    box = (slice(int(py.min()), int(py.max()) + 1), slice(int(px.min()), int(px.max()) + 1))
                    sub = support[box]
                    kept = _drop_small_components(sub == m.index, sub, cfg.min_component_fraction)
                    if kept < n:
                        left = support[py, px] == m.index
                        pos, px, py = pos[left], px[left], py[left]
                        n = pos.size
                f = fs[pos]
                if n < min_px or self._oversized(m, n) or self._foreign_coloured(m, f, dc2[pos], frame_classes):
                    support[py, px] = -1
                    continue
                pts = np.stack([px, py], axis=1).astype(float)
                mean = pts.mean(axis=0)
                d = pts - mean
                stats[m.index] = (mean, d.T @ d / n, f, n)
                core = (ds2[pos] <= core2) & (dc2[pos] <= learn2)
                core_colours.setdefault(self.colour_classes[self.labels[m.index]], []).append(f[core])

        blobs = []
        seen = set()
        sx, sy = self._scale()
        for i, label in enumerate(self.labels):
            if i not in stats:
                continue
            mean, cov, colours, n = stats[i]
            cmean, ccov = _colour_stats(colours)
            fmean, fcov = self._from_work(mean, cov)
            blobs.append(Blob2D(label, fmean, fcov, cmean, ccov, int(round(n / (sx * sy)))))
            seen.add(label)
            tr = self.tracks.get(label)
            vel = mean - tr.mean if (tr is not None and tr.missed == 0) else np.zeros(2)
            self.tracks[label] = _Track(mean, cov, vel, 0)
        for label in list(self.tracks):
            if label not in seen:
                self.tracks[label].missed += 1
                if self.tracks[label].missed > self.config.temporal_max_missed:
                    del self.tracks[label]
        self._learn_colours(core_colours)
        if models:
            self._check_stale_colours(core_fg)  # after the learning: a class marked here is bootstrapped next frame
        blobs += self._lost_skin_blobs(img, fg, support, seen)
        self.timings_ms = {"classification": 1e3 * (t1 - t0), "statistics": 1e3 * (time.perf_counter() - t1)}
        return blobs, support >= 0

    def _oversized(self, m: _ClassModel, n: int) -> bool:
        """A skin label whose n pixels (work px) outnumber ``max_prior_area_ratio`` times the area
        of its projected 3-D prior's 2-sigma ellipse (4π√det S) has spread past its part (e.g. a
        hand's label over the face or the other hand): it is not reported, its pixels stay
        unlabelled, and the 3-D stage may re-acquire the part from them (``lost_skin_blobs``)."""
        r = self.config.max_prior_area_ratio
        return (r > 0 and m.from_prior and self.colour_classes[self.labels[m.index]] == SKIN
                and n > r * 4.0 * math.pi * math.sqrt(m.det))

    def _foreign_coloured(self, m: _ClassModel, colours: np.ndarray, dc2: np.ndarray,
                          frame_classes: list[str]) -> bool:
        """A skin label (from a projected 3-D prior) of whose pixels (colour features ``colours``
        (n, 3), squared Mahalanobis distances ``dc2`` (n,) to its own model) more than
        ``foreign_colour_share`` are more likely under the colour model of another class of
        ``frame_classes`` (-½ (d² + log|Σ|)) sits on that class's pixels, not on its part:
        khaki trousers pass the skin gate, and a hand gone behind the body leaves its label
        on them (ALGORITHMS.md §1: the MAP's spatial term of a small blob outweighs a
        moderately worse colour). Not reported; its pixels stay unlabelled."""
        share = self.config.foreign_colour_share
        own = self.colour_classes[self.labels[m.index]]
        if share <= 0 or not m.from_prior or own != SKIN or not m.colour.learned or len(frame_classes) < 2:
            return False  # (an unlearned model is the broad default, which any learned one outscores)
        cfg = self.config
        own_score = dc2 + m.colour.whitening(cfg)[1]
        foreign = np.zeros(colours.shape[0], bool)
        for cls in frame_classes:
            if cls == own:
                continue
            other = self.colour_model(cls)
            if other.learned:
                foreign |= other.distance2(colours, cfg) + other.whitening(cfg)[1] < own_score
        return float(np.count_nonzero(foreign)) > share * colours.shape[0]

    def _detached_static_support(self, fg: np.ndarray, labelled: np.ndarray) -> np.ndarray:
        """(H, W) bool: the pixels labelled with one of ``background_ghost_detached`` outside the
        foreground component (8-connected, gaps up to ``connected_gap_px`` closed) that holds the
        most labelled pixels (``labelled``: every label's), when any of them may reach
        ``background_ghost_frames`` unchanged frames in this frame's update (else none: the
        connected components are skipped).

        A label that settled on a ghost of the start position (a hand's class on the floor where the
        person stood while the background seeded) keeps that ghost as its support, and supports are
        never taken into the background; detached from the person, it is a ghost candidate again
        (``background_ghost_detached``; the edge test of ``BackgroundModel._ghosts`` still decides)."""
        cfg, bg = self.config, self.background
        none = np.zeros(fg.shape, bool)
        if bg.static is None or cfg.background_ghost_frames <= 0:
            return none
        ids = [i for i, lab in enumerate(self.support_labels) if lab in self._ghost_detached_labels]
        if not ids:
            return none
        tested = np.isin(self._support_work, ids)
        if not (tested & (bg.static >= cfg.background_ghost_frames - 1)).any():  # counted up in update()
            return none
        n, comp = self._gap_closed_components(fg)
        per = np.bincount(comp[labelled], minlength=n)
        per[0] = 0
        return tested & (comp != int(np.argmax(per)))

    def _gap_closed_components(self, mask: np.ndarray) -> tuple[int, np.ndarray]:
        """(n, labels) of the 8-connected components of the C-contiguous bool ``mask`` after gaps up to
        ``connected_gap_px`` (input px) are closed by dilation (cv2.connectedComponents; 0 = none)."""
        m = mask.view(np.uint8)
        gap = int(round(self.config.connected_gap_px * self._scale()[0]))
        if gap > 0:
            m = cv2.dilate(m, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * gap + 1, 2 * gap + 1)))
        return cv2.connectedComponents(m, connectivity=8)

    def _keep_connected(self, fg: np.ndarray, models: list[_ClassModel], box: tuple[int, int, int, int],
                        cols: np.ndarray, rows: np.ndarray, lab: np.ndarray) -> None:
        """Unlabel (−1 in ``lab``, in place) the pixels at (rows, cols) of the box (x0, y0, x1, y1)
        whose foreground component holds less than a quarter of the largest share of
        ``connected_to`` pixels (see the config); nothing changes when that label has no pixels."""
        cfg = self.config
        anchor = [m.index for m in models if self.labels[m.index] == cfg.connected_to]
        if not anchor:
            return
        on_anchor = lab == anchor[0]
        if not on_anchor.any():
            return
        x0, y0, x1, y1 = box
        n, comp = self._gap_closed_components(np.ascontiguousarray(fg[y0:y1, x0:x1]))
        ids = comp[rows, cols]
        per = np.bincount(ids[on_anchor], minlength=n)
        keep = per >= 0.25 * per.max()
        keep[0] = False
        lab[~keep[ids]] = -1

    def _core_colours(self, models: list[_ClassModel], cores: list[np.ndarray]) -> dict[str, np.ndarray]:
        """Colour class -> the colour features (n, 3) of its labels' core foreground pixels, from
        ``cores``: per model, the features of its candidate pixels within ``colour_core_sigma``."""
        parts: dict[str, list[np.ndarray]] = {}
        for m, f in zip(models, cores, strict=True):
            parts.setdefault(self.colour_classes[self.labels[m.index]], []).append(f)
        return {cls: np.concatenate(p, axis=0) for cls, p in parts.items()}

    def _bootstrap_colours(self, core_fg: dict[str, np.ndarray], room: _RoomColours | None = None) -> None:
        """Give each colour class still on its broad start model (no configured default) a
        robust estimate from the foreground in its labels' cores (``core_fg``, see
        ``_core_colours``): median, then mean/cov of the pixels within 3 robust sigmas of it.

        ``room``: the room's colours next to the person (:class:`_RoomColours`). With
        ``colour_room_gate``, the room-coloured core pixels are left out first when they are a quarter
        of the core or more (a smaller share is left to the robust trimming, which handles it, so that a
        clean core gives the same model as without the test): where the person stood while
        the background seeded, the foreground is the room seen again (the start position's ghost),
        and a start-up prior off the part has its core on it (default scene, seeds 1-26, before: the
        shirt or trousers class of 6 seeds learnt from the floor in one or two views). A class whose
        core is all room-coloured waits for a later frame."""
        for cls, core in sorted(core_fg.items()):
            model = self.colour_model(cls)
            if model.learned or self.config.has_start_model(cls):
                continue
            c = core.astype(float)
            if c.shape[0] < self._min_pixels():
                continue
            cfg = self.config
            floor = cfg.colour_floor
            if room is not None:
                part = ~room.coloured(c)
                if np.count_nonzero(~part) >= _ROOM_CORE_SHARE * c.shape[0]:  # (fewer: left to the trimming)
                    if np.count_nonzero(part) < self._min_pixels():
                        continue
                    c = c[part]
            med = np.median(c, axis=0)
            mad = 1.4826 * np.median(np.abs(c - med), axis=0)
            keep = np.all(np.abs(c - med) <= 3.0 * (mad + floor), axis=1)
            if np.count_nonzero(keep) < self._min_pixels():
                continue
            model.mean, model.cov = _colour_stats(c[keep])
            model.learned = True

    def _check_stale_colours(self, core_fg: dict[str, np.ndarray]) -> None:
        """Count, per learned colour class (not skin nor one of ``colour_defaults``), the frames in
        a row in which the median colour of the foreground in its labels' cores (``core_fg``, see
        ``_core_colours``) lay outside the model's ``colour_learn_gate``; after
        ``colour_relearn_frames`` such frames the class is marked unlearned, so that the next frame
        bootstraps it again from the cores (``_bootstrap_colours``). Frames with fewer than
        ``min_blob_pixels`` core foreground pixels (the part hidden, or its prior off the person) do
        not count."""
        cfg = self.config
        if cfg.colour_relearn_frames <= 0:
            return
        for cls, c in sorted(core_fg.items()):
            model = self.colour_models.get(cls)
            if cfg.has_start_model(cls) or model is None or not model.learned or c.shape[0] < self._min_pixels():
                continue
            median = np.median(c, axis=0)[None]
            if float(model.distance2(median, cfg)[0]) > cfg.colour_learn_gate**2:
                self.colour_stale_frames[cls] = self.colour_stale_frames.get(cls, 0) + 1
            else:
                self.colour_stale_frames[cls] = 0
            if self.colour_stale_frames[cls] >= cfg.colour_relearn_frames:
                model.learned = False
                self.colour_stale_frames[cls] = 0
                self.colour_relearned[cls] = self.colour_relearned.get(cls, 0) + 1

    def _learn_colours(self, colours_by_class: dict[str, list[np.ndarray]]) -> None:
        """Blend each colour class model towards the statistics of its labels' core pixels."""
        beta = self.config.colour_learning_rate
        if beta <= 0:
            return
        for cls, parts in sorted(colours_by_class.items()):
            c = np.concatenate(parts, axis=0)
            if c.shape[0] < self._min_pixels():
                continue
            mean, cov = _colour_stats(c)
            model = self.colour_model(cls)
            if not model.learned:
                model.mean, model.cov, model.learned = mean, cov, True
            else:
                model.mean = (1 - beta) * model.mean + beta * mean
                model.cov = (1 - beta) * model.cov + beta * cov

    # ------------------------------------------------------------------ start-up
    def _startup(self, img: np.ndarray, fg: np.ndarray) -> tuple[list[Blob2D], np.ndarray]:
        """Foreground blob plus the largest skin-coloured foreground components; the mask of
        protected pixels is empty (nothing is tracked yet)."""
        cfg = self.config
        W, H = self.work_size
        support = np.full((H, W), -1, np.int16)
        self._support_work = support
        self.support_labels = []
        min_px = self._min_pixels()
        ys, xs = np.nonzero(fg)
        if xs.size < min_px:
            return [], np.zeros((H, W), bool)
        colours = colour_features(img[ys, xs])
        blobs = [self._blob_from_pixels(FOREGROUND, xs, ys, colours)]
        support[ys, xs] = 0
        self.support_labels.append(FOREGROUND)

        for idx in self._skin_components(xs, ys, colours, cfg.startup_max_skin_blobs,
                                         cfg.startup_skin_max_fraction * xs.size):
            cx, cy = xs[idx], ys[idx]
            blobs.append(self._blob_from_pixels(SKIN, cx, cy, colours[idx]))
            support[cy, cx] = len(self.support_labels)
            self.support_labels.append(SKIN)
        return blobs, np.zeros((H, W), bool)

    def _skin_components(self, xs: np.ndarray, ys: np.ndarray, colours: np.ndarray,
                         max_blobs: int, max_area: float) -> list[np.ndarray]:
        """The largest 8-connected components of the skin-coloured pixels among (xs, ys) (work px,
        colour features ``colours``): at most ``max_blobs``, each of at least the smallest blob's
        pixel count and at most ``max_area`` pixels (larger ones, clothing of a skin-like colour,
        are skipped). Returns each component's indices into xs / ys / colours, largest first."""
        cfg = self.config
        is_skin = self.colour_model(SKIN).distance2(colours, cfg) <= cfg.colour_gate**2
        if max_blobs <= 0 or not np.any(is_skin):
            return []
        skin_idx = np.flatnonzero(is_skin)
        sx, sy = xs[skin_idx], ys[skin_idx]
        bx, by = int(sx.min()), int(sy.min())
        skin_mask = np.zeros((int(sy.max()) - by + 1, int(sx.max()) - bx + 1), np.uint8)
        skin_mask[sy - by, sx - bx] = 1
        n, sk_lab = cv2.connectedComponents(skin_mask, connectivity=8)
        component = sk_lab[sy - by, sx - bx]  # each skin pixel's component
        areas = np.bincount(component, minlength=n)[1:]
        min_px = self._min_pixels()
        out = []
        for j in np.argsort(-areas, kind="stable") + 1:
            area = areas[j - 1]
            if len(out) >= max_blobs or area < min_px:
                break
            if area > max_area:
                continue
            out.append(skin_idx[component == j])
        return out

    def _lost_skin_blobs(self, img: np.ndarray, fg: np.ndarray, support: np.ndarray, seen: set) -> list[Blob2D]:
        """While tracking: the unlabelled skin-coloured foreground components (``lost_skin_blobs``,
        label 'skin') when a label of the skin colour class is not among the labels ``seen`` in this view,
        else []. ``support``: this frame's label image (work px, -1 unlabelled)."""
        cfg = self.config
        if cfg.lost_skin_blobs <= 0 or all(lab in seen for lab in self.labels if self.colour_classes[lab] == SKIN):
            return []
        ys, xs = np.nonzero(fg & (support < 0))
        if xs.size < self._min_pixels():
            return []
        colours = colour_features(img[ys, xs])
        comps = self._skin_components(xs, ys, colours, cfg.lost_skin_blobs,
                                      cfg.startup_skin_max_fraction * np.count_nonzero(fg))
        return [self._blob_from_pixels(SKIN, xs[idx], ys[idx], colours[idx]) for idx in comps]

    def _blob_from_pixels(self, label: str, xs: np.ndarray, ys: np.ndarray, colours: np.ndarray) -> Blob2D:
        """Blob2D (input px) from pixel coordinates (N,) and their colour features (N, 3)."""
        pts = np.stack([xs, ys], axis=1).astype(float)
        mean = pts.mean(axis=0)
        d = pts - mean
        cov = d.T @ d / pts.shape[0]
        cmean, ccov = _colour_stats(colours)
        fmean, fcov = self._from_work(mean, cov)
        sx, sy = self._scale()
        return Blob2D(label, fmean, fcov, cmean, ccov, int(round(pts.shape[0] / (sx * sy))))


def _drop_small_components(mask: np.ndarray, sub: np.ndarray, fraction: float) -> int:
    """Unlabel (−1 in ``sub``) and remove from ``mask`` the 8-connected components of ``mask``
    smaller than ``fraction`` of its largest one; returns the pixels left."""
    # cv2.connectedComponents and a bincount: ~4x cheaper than ...WithStats on these small boxes
    n, comp = cv2.connectedComponents(mask.view(np.uint8), connectivity=8)
    if n <= 2:
        return int(np.count_nonzero(mask))
    areas = np.bincount(comp.ravel(), minlength=n)[1:]
    keep = np.zeros(n, bool)
    keep[1:] = areas >= fraction * areas.max()
    if not keep[1:].all():
        drop = mask & ~keep[comp]
        sub[drop] = -1
        mask &= ~drop
    return int(areas[keep[1:]].sum())


def _colour_stats(colours: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Mean (3,) and population covariance (3, 3) (float64) of colour features (N, 3)."""
    c = np.asarray(colours, float).reshape(-1, 3)
    mean = c.mean(axis=0)
    d = c - mean
    return mean, d.T @ d / c.shape[0]


# =========================================================================== benchmark
def _benchmark_scene(width: int, height: int, frames: int) -> tuple[list[np.ndarray], list[list[Prior2D]]]:
    """A seeded synthetic sequence: textured room, a shirt torso, skin head and hands moving."""
    rng = np.random.default_rng(0)
    bg = cv2.resize(rng.uniform(40, 220, (12, 16, 3)).astype(np.uint8), (width, height),
                    interpolation=cv2.INTER_CUBIC)
    bg = cv2.add(bg, rng.normal(0, 6, bg.shape).astype(np.int16), dtype=cv2.CV_8U)
    s = width / 320.0
    images, priors = [], []
    for t in range(frames):
        cx = width * (0.3 + 0.4 * (0.5 + 0.5 * math.sin(t * 0.15)))
        cy = height * 0.55
        img = bg.copy()
        parts = [("torso", (cx, cy), (28 * s, 50 * s), (165, 80, 35)),
                 ("head", (cx, cy - 70 * s), (14 * s, 14 * s), (150, 180, 220)),
                 ("l_hand", (cx - 45 * s, cy + 10 * s * (1 + math.sin(t * 0.4))), (7 * s, 7 * s),
                  (150, 180, 220)),
                 ("r_hand", (cx + 45 * s, cy + 10 * s), (7 * s, 7 * s), (150, 180, 220))]
        pri = []
        for label, c, ax, col in parts:
            cv2.ellipse(img, (int(c[0] * 16), int(c[1] * 16)), (int(ax[0] * 16), int(ax[1] * 16)), 0, 0, 360,
                        col, -1, cv2.LINE_AA, 4)
            pri.append(Prior2D(label, np.array(c) + 1.0, np.diag(np.square(ax) / 4.0), 0.7))
        img = cv2.add(img, rng.normal(0, 2, img.shape).astype(np.int16), dtype=cv2.CV_8U)
        images.append(img)
        priors.append(pri)
    return images, priors


def benchmark(width: int = 320, height: int = 240, frames: int = 60,
              work_scale: float = 1.0) -> dict[str, float]:
    """Print and return ms per frame of ``BlobTracker2D.step`` on a synthetic sequence:
    'seeding' (background seed frames), 'startup' (no priors) and 'tracking' (with priors)."""
    labels = ["torso", "head", "l_hand", "r_hand"]
    classes = {"torso": "shirt", "head": SKIN, "l_hand": SKIN, "r_hand": SKIN}
    cfg = BlobTrackerConfig(work_scale=work_scale)
    images, priors = _benchmark_scene(width, height, frames)
    n_seed = cfg.background_seed_frames * cfg.background_seed_stride
    tracker = BlobTracker2D("bench", labels, classes, cfg)
    out: dict[str, float] = {}
    t0 = time.perf_counter()
    for img in images[:n_seed]:
        tracker.step(img, None)
    out["seeding"] = (time.perf_counter() - t0) / n_seed * 1e3
    rest = images[n_seed:]
    t0 = time.perf_counter()
    for img in rest:
        tracker.step(img, None)
    out["startup"] = (time.perf_counter() - t0) / len(rest) * 1e3
    t0 = time.perf_counter()
    for img, pri in zip(rest, priors[n_seed:]):
        tracker.step(img, pri)
    out["tracking"] = (time.perf_counter() - t0) / len(rest) * 1e3
    print(f"BlobTracker2D {width}x{height} (work_scale {work_scale}): "
          + ", ".join(f"{k} {v:.2f} ms/frame" for k, v in out.items()))
    return out


if __name__ == "__main__":  # pragma: no cover
    benchmark(320, 240)
    benchmark(640, 480)
