"""Per-pixel background model of the 2-D blob tracker (ALGORITHMS.md §1, "2-D blobs": the
background learned while the person moves, adapting slowly).

Background (``BackgroundModel``). A per-pixel Gaussian in B, G, R (mean and a
diagonal variance, grey levels) at the working resolution. Start-up choice:
the first ``background_seed_frames`` samples (one every ``background_seed_stride``
frames) are kept per pixel in sorted order (an insertion sorting network of
element-wise min/max, cheap on uint8 images); the background is their temporal
median and its spread 1.4826 x the median absolute deviation (floored at
``background_min_sigma``), both of which ignore a person who covers a pixel in
fewer than half of the samples. While seeding, the foreground is the large
deviation from the running median of the samples so far (the current frame
included, so a person's old position leaves no ghost once three samples exist).
Frame 0 alone has no foreground: a person who never moves during the seed is
indistinguishable from the room and becomes background (see "weak points").
After seeding, a pixel is foreground when its Mahalanobis distance to the
background exceeds ``background_threshold``; the mask is cleaned by a small
median filter. The model adapts at ``background_learning_rate`` only where the
pixel is background; pixels in the support of a tracked blob never adapt; other
("unexplained") foreground adapts at the tiny ``background_ghost_rate`` and is
taken into the background once it has stayed unchanged for
``background_static_frames`` frames (an object that stopped for good). Ghosts
(where the seed absorbed a person who then left: the room reappears as
"foreground") are removed sooner: any foreground region unchanged for
``background_ghost_frames`` frames whose pixels on the silhouette have
``background_ghost_edge_ratio`` times stronger gradients in the background model
than in the image (the outline of something that has left, not of something
that is there) becomes background at once, unless it is in a tracked blob's support
(a person standing still in front of a textured floor fails the edge test too). With
``background_ghost_detached``, a support on a foreground region detached from the person
(not the component holding the most labelled pixels) is tested all the same: a hand's label
that settled on the ghost of the start position would otherwise keep it for good.
From the first tracked frame on, the per-channel sigma is capped at
``background_max_sigma``: where the person stood in about half of the seed samples,
the MAD is the spread between person and room (sigmas of 40-70 grey levels), and
uncapped it decays only at the learning rate, so when the person comes back to
where they started, a hand in front of the floor is within 5 of those sigmas and
is not foreground (the self-occlusion scene: a hanging hand lost in all views at
once). The cap waits for tracking because start-up has no priors to tell a ghost
of the start position (foreground under the cap) from the person.
"""

from __future__ import annotations

import cv2
import numpy as np

from .blob_config import BlobTrackerConfig

__all__ = ["BackgroundModel"]

_F32 = np.float32
_GHOST_EVERY = 8  # frames between background updates at the ghost rate (amortised)
_ONES13 = np.ones((1, 3), _F32)


def _insert_sorted(stack: list[np.ndarray], x: np.ndarray) -> None:
    """Insert image x into a per-pixel sorted list of images (in place), by min/max swaps."""
    carry = x
    stack.append(x)
    for i in range(len(stack) - 2, -1, -1):
        stack[i + 1] = cv2.max(stack[i], carry)
        carry = cv2.min(stack[i], carry)
    stack[0] = carry


def _median_of_sorted(stack: list[np.ndarray]) -> np.ndarray:
    """Per-pixel median (float32) of a per-pixel sorted image list."""
    n = len(stack)
    if n % 2:
        return stack[n // 2].astype(_F32)
    return cv2.addWeighted(stack[n // 2 - 1], 0.5, stack[n // 2], 0.5, 0.0, dtype=cv2.CV_32F)


class BackgroundModel:
    """Per-pixel Gaussian background in B, G, R (module docstring).

    ``mean``: (H, W, 3) float32 grey levels; ``var``: (H, W, 3) float32 grey levels²,
    kept floored at ``background_min_sigma``² (None until the seed is complete, see ``ready``);
    ``static``: (H, W) uint16 frames each unexplained foreground pixel has stayed unchanged.
    """

    def __init__(self, config: BlobTrackerConfig):
        self.config = config
        self.frames = 0
        self.frames_ready = 0  # frames processed since the seed was complete
        self.seed: list[np.ndarray] = []
        self.mean: np.ndarray | None = None
        self.var: np.ndarray | None = None
        self.static: np.ndarray | None = None
        self._floor: np.ndarray | None = None
        self._diff2: np.ndarray | None = None
        self._previous: np.ndarray | None = None
        self.capped = False  # whether background_max_sigma applies (from the first tracked frame)

    def cap_variance(self) -> None:
        """Cap the variance at ``background_max_sigma``² from now on (if configured)."""
        if self.capped or self.var is None or self.config.background_max_sigma <= 0:
            return
        np.minimum(self.var, self._max_var, out=self.var)
        self.capped = True

    @property
    def _max_var(self) -> np.float32:
        """background_max_sigma² (the variance cap)."""
        return _F32(self.config.background_max_sigma**2)

    @property
    def ready(self) -> bool:
        """True once the seed median has become the per-pixel Gaussian."""
        return self.var is not None

    def foreground(self, image: np.ndarray, image_f: np.ndarray) -> np.ndarray:
        """Foreground mask (H, W) bool of one frame (uint8 (H, W, 3) and its float32 copy).

        While seeding, the frame is added to the seed (every ``background_seed_stride``
        frames) and compared with the running median at the floor sigma.
        """
        cfg = self.config
        thr2 = cfg.background_threshold**2
        if not self.ready:
            if self.frames % cfg.background_seed_stride == 0:
                _insert_sorted(self.seed, image)
            self.frames += 1
            median = _median_of_sorted(self.seed)
            diff = cv2.subtract(image_f, median)
            d2 = cv2.transform(cv2.multiply(diff, diff), _ONES13)
            fg = d2 > thr2 * cfg.background_min_sigma**2
            if len(self.seed) >= cfg.background_seed_frames:
                self._finish_seed(median)
            return fg
        self.frames += 1
        self.frames_ready += 1
        diff = cv2.subtract(image_f, self.mean)
        self._diff2 = cv2.multiply(diff, diff)
        d2 = cv2.transform(cv2.divide(self._diff2, self.var), _ONES13)
        return d2 > thr2

    def _finish_seed(self, median: np.ndarray) -> None:
        """Seed -> Gaussian: mean = median, sigma = 1.4826 MAD (floored)."""
        med_u8 = np.clip(np.rint(median), 0, 255).astype(np.uint8)
        dev: list[np.ndarray] = []
        for s in self.seed:
            _insert_sorted(dev, cv2.absdiff(s, med_u8))
        mad = _median_of_sorted(dev)
        self.mean = median
        self._floor = np.full(median.shape, self.config.background_min_sigma**2, _F32)
        self.var = cv2.max(np.square(1.4826 * mad).astype(_F32), self._floor)
        self.static = np.zeros(median.shape[:2], np.uint16)
        self.seed = []

    def update(self, image: np.ndarray, image_f: np.ndarray, background: np.ndarray,
               unexplained: np.ndarray, ghost_tested: np.ndarray | None = None) -> None:
        """Adapt the model after ``foreground`` (module docstring).

        image: (H, W, 3) uint8 and image_f its float32 copy; background: (H, W) bool pixels
        classified background (rate ``background_learning_rate``); unexplained: (H, W) bool
        foreground pixels in no tracked blob's support (rate ``background_ghost_rate``; taken
        into the background at once after ``background_static_frames`` unchanged frames).
        Any unexplained foreground region unchanged for ``background_ghost_frames`` frames
        that is a ghost (``_ghosts``) is taken into the background at once; ``ghost_tested``:
        (H, W) bool supports tested all the same (``background_ghost_detached``), by that
        test alone (a still hand held away from the body is not "an object that stopped").
        """
        previous, self._previous = self._previous, image
        if not self.ready or self._diff2 is None:
            return
        cfg = self.config
        # the (tiny) ghost rate is applied every _GHOST_EVERY frames, scaled: its masks are scattered
        ghost_rate = 0.0
        if self.frames % _GHOST_EVERY == 0:
            ghost_rate = 1.0 - (1.0 - cfg.background_ghost_rate) ** _GHOST_EVERY
        for mask, rate in ((background, cfg.background_learning_rate), (unexplained, ghost_rate)):
            if rate <= 0:
                continue
            m = mask.view(np.uint8)
            x, y, w, h = cv2.boundingRect(m)
            if w == 0 or h == 0:
                continue
            box = (slice(y, y + h), slice(x, x + w))
            cv2.accumulateWeighted(self._diff2[box], self.var[box], rate, m[box])
            cv2.accumulateWeighted(image_f[box], self.mean[box], rate, m[box])
            cv2.max(self.var[box], self._floor[box], dst=self.var[box])
            if self.capped:
                np.minimum(self.var[box], self._max_var, out=self.var[box])
        self._diff2 = None
        if previous is None or previous.shape != image.shape:
            return
        # unchanged since the last frame: luma-weighted |change| within 2/3 x threshold x floor sigma
        change = cv2.cvtColor(cv2.absdiff(image, previous), cv2.COLOR_BGR2GRAY)
        still = ~background & (change <= (2.0 / 3.0) * cfg.background_threshold * cfg.background_min_sigma)
        self.static += still
        self.static *= still
        absorb = np.zeros(still.shape, bool)
        if cfg.background_static_frames > 0:
            absorb |= (self.static >= cfg.background_static_frames) & unexplained
        if cfg.background_ghost_frames > 0 and cfg.background_ghost_edge_ratio > 0:
            # a tracked blob's support is never a ghost: a person standing still in front of a
            # textured background (floor tiles) otherwise fails the edge-ratio test and is erased
            candidates = unexplained if ghost_tested is None else unexplained | ghost_tested
            candidates = (self.static >= cfg.background_ghost_frames) & candidates
            if candidates.any():
                absorb |= self._ghosts(candidates, ~background, image_f)
        if absorb.any():
            cv2.copyTo(image_f, absorb.view(np.uint8), self.mean)  # mean[absorb] = image_f[absorb], ~20x faster
            self.static[absorb] = 0

    def _ghosts(self, candidates: np.ndarray, fg: np.ndarray, image_f: np.ndarray) -> np.ndarray:
        """(H, W) bool: the 8-connected regions of ``candidates`` (static foreground) whose
        pixels on the foreground silhouette have a mean gradient magnitude (Sobel, grey) in the
        background model above ``background_ghost_edge_ratio`` x that in the image: the outline
        of something that has left (a ghost), not of something that is there."""
        out = np.zeros(candidates.shape, bool)
        H, W = candidates.shape
        x, y, w, h = cv2.boundingRect(candidates.view(np.uint8))
        x0, y0, x1, y1 = max(0, x - 2), max(0, y - 2), min(W, x + w + 2), min(H, y + h + 2)
        box = (slice(y0, y1), slice(x0, x1))
        n, comp = cv2.connectedComponents(candidates[box].view(np.uint8), connectivity=8)
        fgb = np.ascontiguousarray(fg[box]).view(np.uint8)
        rim = (fgb > cv2.erode(fgb, np.ones((3, 3), np.uint8), borderType=cv2.BORDER_REPLICATE)) & (comp > 0)
        if not rim.any():
            return out

        def gradient(bgr: np.ndarray) -> np.ndarray:
            grey = cv2.cvtColor(np.ascontiguousarray(bgr), cv2.COLOR_BGR2GRAY)
            return cv2.magnitude(cv2.Sobel(grey, cv2.CV_32F, 1, 0), cv2.Sobel(grey, cv2.CV_32F, 0, 1))

        ids = comp[rim]
        e_img = np.bincount(ids, gradient(image_f[box])[rim], minlength=n)
        e_bg = np.bincount(ids, gradient(self.mean[box])[rim], minlength=n)
        count = np.bincount(ids, minlength=n)
        ghost = (count >= 5) & (e_bg > self.config.background_ghost_edge_ratio * e_img + 1e-6)
        ghost[0] = False
        if ghost.any():
            out[box] = ghost[comp]
        return out
