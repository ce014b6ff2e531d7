"""Tunables of the per-camera 2-D blob tracker (:class:`artrack.blobs.BlobTracker2D`;
ALGORITHMS.md §1, "2-D blobs"), mirrored with the same docs in ``config/blob_features.yaml``, and
the two start-up classes. Every field is checked on construction and a bad one named in one line.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from .errors import InputError

__all__ = ["FOREGROUND", "SKIN", "BlobTrackerConfig"]

#: Start-up class: the whole foreground silhouette.
FOREGROUND = "foreground"
#: Start-up class (and colour class): a connected region of skin-coloured foreground.
SKIN = "skin"


@dataclass
class BlobTrackerConfig:
    """Tunables of :class:`artrack.blobs.BlobTracker2D` (mirrored, with the same docs, in
    config/blob_features.yaml).

    Pixel quantities are in pixels of the full-resolution input image unless noted.
    """

    # ---- background model (per-pixel Gaussian in B, G, R)
    #: number of samples in the start-up temporal median that seeds the background
    background_seed_frames: int = 11
    #: one seed sample every this many frames (the seed spans frames*stride frames)
    background_seed_stride: int = 4
    #: adaptation rate of the background mean/variance where a pixel is background (per frame)
    background_learning_rate: float = 0.02
    #: adaptation rate where a pixel is foreground but in no tracked blob's support (0 = never)
    background_ghost_rate: float = 0.002
    #: a foreground pixel in no tracked blob's support, unchanged for this many frames, becomes
    #: background at once (heals ghosts; 0 = never)
    background_static_frames: int = 45
    #: a foreground region in no tracked blob's support, unchanged for this many frames, is tested for
    #: being a ghost (0 = never)
    background_ghost_frames: int = 8
    #: ... and is a ghost (becomes background at once) when its silhouette edges are this many
    #: times stronger in the background model than in the image (0 = never)
    background_ghost_edge_ratio: float = 1.5
    #: the labels whose support on a foreground region detached from the person (8-connected, gaps up
    #: to ``connected_gap_px`` closed; not the component holding the most labelled pixels) is still
    #: tested for being a ghost, like unexplained foreground (empty: every support is protected;
    #: config/blob_features.yaml has the measurements)
    background_ghost_detached: tuple[str, ...] = ("l_hand", "r_hand")
    #: Mahalanobis distance (sigmas, over B, G, R) to the background above which a pixel is foreground
    background_threshold: float = 5.0
    #: floor of the per-pixel, per-channel background sigma, grey levels
    background_min_sigma: float = 3.0
    #: cap of the per-pixel, per-channel background sigma, grey levels (0 = no cap)
    background_max_sigma: float = 8.0
    #: median-filter aperture applied to the foreground mask, px (odd; <= 1 disables)
    foreground_median: int = 3

    # ---- colour features and colour classes
    #: colour feature of the class likelihood: 'rgI' (chroma r, g and intensity) or 'rg' (chroma only)
    colour_features: str = "rgI"
    #: colour gate: Mahalanobis distance (sigmas) in colour beyond which a pixel cannot join a class
    colour_gate: float = 3.5
    #: rate at which a colour class model follows the statistics of its labelled pixels (per frame)
    colour_learning_rate: float = 0.2
    #: sigma floor added to the chroma (r, g) variances of every colour model
    colour_min_sigma_chroma: float = 0.01
    #: sigma floor added to the intensity variance of every colour model
    colour_min_sigma_intensity: float = 0.03
    #: default skin model: mean (r, g, I) of normalised chroma and intensity
    skin_mean: tuple[float, float, float] = (0.42, 0.31, 0.55)
    #: default skin model: sigmas of (r, g, I)
    skin_sigma: tuple[float, float, float] = (0.035, 0.025, 0.22)
    #: default skin model: correlation of chroma r and g
    skin_rg_correlation: float = 0.0
    #: pixels darker than this intensity (0..1) are never skin (hair, deep shadow)
    skin_min_intensity: float = 0.25
    #: pixels whose chroma r - g is below this are never skin (skin is red before green; neutral greys
    #: -- the floor, a wall, the ghost of the start position -- lie within the broad default model)
    skin_min_red_excess: float = 0.02
    #: colour class of a part's blob, overriding the body model's ({label: class}; e.g. a person with a
    #: bare torso and bare shins: {torso: skin, l_shin: skin, r_shin: skin}); empty = the body model's
    part_colours: dict[str, str] = field(default_factory=dict)
    #: configured start models of colour classes other than skin ({class: {mean: [r, g, I], sigma: [r, g, I]}};
    #: e.g. a cap of a colour the room lacks): such a class starts from its model, as skin does, instead of
    #: being bootstrapped from its labels' prior cores, which a start-up pose off the part puts on the
    #: wrong pixels; empty = every class but skin is bootstrapped
    colour_defaults: dict[str, dict] = field(default_factory=dict)
    #: sigmas of (r, g, I) of the broad start model of a colour class without a default (mean 1/3, 1/3, 0.5)
    unknown_colour_sigma: tuple[float, float, float] = (0.2, 0.2, 0.5)
    #: colour models are bootstrapped (robustly) and learned only from pixels within this many sigmas
    #: of their label's spatial prior (the part's core, least mixed with neighbours and ghosts)
    colour_core_sigma: float = 2.0
    #: ... and only from pixels within this colour Mahalanobis distance (sigmas) of the current model
    colour_learn_gate: float = 2.5
    #: a learned colour class (not skin) is bootstrapped again when, for this many frames in a row, the
    #: median colour of the foreground pixels in its labels' cores lay outside its ``colour_learn_gate``
    #: (a model learnt from a ghost or a wrong start-up pose does not describe the part, and, gated as
    #: learning is, would never recover); 0 = never
    colour_relearn_frames: int = 15
    #: a colour class is bootstrapped without the core pixels whose colour the room next to the person
    #: shows too: at least 0.2 % of the background pixels around the labels' ROIs within this distance,
    #: in units of (colour_min_sigma_chroma, colour_min_sigma_intensity) (the ghost of the start
    #: position shows the room); 0 = off
    colour_room_gate: float = 1.0

    # ---- class priors: feedback and temporal smoothness
    #: half-size of a label's region of interest, in sigmas of its spatial prior (also its spatial gate)
    roi_sigma: float = 3.5
    #: exponent w of the projected 3-D prior in the pixel class prior (confidence x Gaussian)^w
    prior_weight: float = 1.0
    #: confidences are floored at this value (a weak prior still counts, a little)
    prior_min_confidence: float = 0.05
    #: a prior's covariance is multiplied by 1 + this x (1 - confidence) (0: the projected extent as is)
    prior_confidence_inflation: float = 0.0
    #: sigma floor (isotropic, px) added to every spatial prior
    min_sigma_px: float = 1.5
    #: exponent w of the temporal (previous-blob) Gaussian when a label has no prior
    temporal_weight: float = 1.0
    #: previous blob covariance multiplier for the temporal prior
    temporal_inflation: float = 1.5
    #: expected per-frame motion, sigma in px, added to the temporal prior per missed frame
    temporal_motion_px: float = 6.0
    #: fraction of the last frame-to-frame displacement extrapolated (0 = static, 1 = constant velocity)
    temporal_velocity: float = 1.0
    #: frames a label may go unseen before its temporal prior is dropped
    temporal_max_missed: int = 5

    # ---- blobs and start-up
    #: blobs with fewer pixels are not reported (full-resolution px of an image min_blob_pixels_width wide)
    min_blob_pixels: int = 20
    #: image width (px) for which min_blob_pixels is given: a camera w px wide uses
    #: min_blob_pixels * (w / min_blob_pixels_width)² (a hand's area scales so); 0 = no scaling
    min_blob_pixels_width: float = 640.0
    #: while tracking, a skin label with more pixels than this many times the area of its projected
    #: 3-D prior's 2-sigma ellipse (4π√det S) is not reported (0 = never; BlobTracker2D._oversized)
    max_prior_area_ratio: float = 1.0
    #: while tracking, a skin label more than this share of whose pixels are better explained by the
    #: colour model of another colour class labelled in this view (Mahalanobis distance and log|Σ|)
    #: is not reported: its part has gone from view and the label sits on clothing of a skin-like
    #: colour, e.g. a hand behind the back leaving its label on khaki trousers (0 = never;
    #: BlobTracker2D._foreign_coloured). Nearly all: the shaded pixels of a hand half in view are
    #: often likelier khaki too (0.5 and 0.8 dropped such hands: docs/HISTORY.md, stop 51)
    foreign_colour_share: float = 0.9
    #: a label's 8-connected pieces smaller than this fraction of its largest piece are dropped (0 = keep all)
    min_component_fraction: float = 0.1
    #: while tracking, only foreground 8-connected to the pixels labelled with this label (e.g. 'torso':
    #: the person's trunk) is labelled: a part's label cannot sit on a detached region (a ghost of where
    #: the person stood while the background seeded, another person's hand); '' = no such test (default:
    #: it helped on some synthetic seeds and locked the loop onto a wrong start on others, docs/HISTORY.md)
    connected_to: str = ""
    #: gaps up to this many px (full resolution) in the foreground count as connected for ``connected_to``
    #: (thin limbs broken by the median filter or by clothing that matches the background)
    connected_gap_px: float = 2.0
    #: at start-up, report at most this many skin blobs (largest first)
    startup_max_skin_blobs: int = 3
    #: at start-up, skip skin components larger than this fraction of the foreground (clothing)
    startup_skin_max_fraction: float = 0.35
    #: while tracking, when a label of the skin colour class finds no pixels in this view, also report at
    #: most this many unlabelled skin-coloured foreground components (label 'skin', largest first, as at
    #: start-up): the 3-D stage re-acquires a lost hand from them; 0 = never
    lost_skin_blobs: int = 3
    #: report start-up blobs while the background is still seeding once the seed holds this many
    #: samples (0 = never: wait for the complete seed). A running median of a few samples cannot
    #: tell a person who hardly moved from the room: the foreground is then only the person's
    #: outline, and skin-coloured rims of the clothing pass for hands (wrong start-up poses)
    startup_min_seed_samples: int = 0
    #: after the seed is complete, report no start-up blobs for this many frames, so that ghosts
    #: (the person's place during the seed) are healed before the body is initialised from them
    startup_settle_frames: int = 10

    # ---- speed
    #: working resolution as a fraction of the input (1 = full; 0.5 halves width and height)
    work_scale: float = 1.0

    def __post_init__(self) -> None:
        where = "blob tracker config"

        def bad(name: str, what: str) -> InputError:
            return InputError(f"{where}: field '{name}' {what} (got {getattr(self, name)!r})")

        for name in ("skin_mean", "skin_sigma", "unknown_colour_sigma"):
            try:
                v = tuple(float(x) for x in getattr(self, name))
            except (TypeError, ValueError):
                raise bad(name, "must be three numbers") from None
            if len(v) != 3 or not all(math.isfinite(x) for x in v):
                raise bad(name, "must be three finite numbers")
            setattr(self, name, v)
        for name in ("skin_sigma", "unknown_colour_sigma"):
            if min(getattr(self, name)) <= 0:
                raise bad(name, "must be positive")
        positive = ("background_threshold", "background_min_sigma", "colour_gate", "colour_min_sigma_chroma",
                    "colour_core_sigma", "colour_learn_gate",
                    "colour_min_sigma_intensity", "roi_sigma", "prior_weight", "prior_min_confidence",
                    "min_sigma_px", "temporal_weight", "temporal_inflation", "work_scale")
        for name in positive:
            v = getattr(self, name)
            if not isinstance(v, (int, float)) or not math.isfinite(v) or v <= 0:
                raise bad(name, "must be a positive number")
        v = self.min_blob_pixels_width
        if not isinstance(v, (int, float)) or not math.isfinite(v) or v < 0:
            raise bad("min_blob_pixels_width", "must be a non-negative number")
        for name in ("background_learning_rate", "background_ghost_rate", "colour_learning_rate",
                     "foreign_colour_share"):
            v = getattr(self, name)
            if not isinstance(v, (int, float)) or not 0.0 <= v <= 1.0:
                raise bad(name, "must be in [0, 1]")
        for name in ("background_seed_frames", "background_seed_stride"):
            if not isinstance(getattr(self, name), int) or getattr(self, name) < 1:
                raise bad(name, "must be a positive integer")
        for name in ("min_blob_pixels", "startup_max_skin_blobs", "lost_skin_blobs", "temporal_max_missed",
                     "foreground_median",
                     "background_static_frames", "background_ghost_frames", "startup_min_seed_samples",
                     "startup_settle_frames", "colour_relearn_frames"):
            if not isinstance(getattr(self, name), int) or getattr(self, name) < 0:
                raise bad(name, "must be a non-negative integer")
        if self.colour_features not in ("rgI", "rg"):
            raise bad("colour_features", "must be 'rgI' or 'rg'")
        if not isinstance(self.part_colours, dict) or not all(
                isinstance(k, str) and isinstance(v, str) and v for k, v in self.part_colours.items()):
            raise bad("part_colours", "must map part labels to colour class names")
        if FOREGROUND in self.part_colours.values():
            raise bad("part_colours", f"cannot use the start-up class '{FOREGROUND}'")
        if not isinstance(self.colour_defaults, dict):
            raise bad("colour_defaults", "must map colour class names to {mean: [r, g, I], sigma: [r, g, I]}")
        defaults = {}
        for cls, model in self.colour_defaults.items():
            if not isinstance(cls, str) or cls in (FOREGROUND, SKIN, ""):
                raise bad("colour_defaults", f"cannot configure the class {cls!r} (skin has skin_mean / skin_sigma)")
            if not isinstance(model, dict) or set(model) != {"mean", "sigma"}:
                raise bad("colour_defaults", f"class '{cls}' needs exactly the keys mean and sigma")
            try:
                mean, sigma = (tuple(float(x) for x in model[k]) for k in ("mean", "sigma"))
            except (TypeError, ValueError):
                raise bad("colour_defaults", f"class '{cls}': mean and sigma must be three numbers each") from None
            if len(mean) != 3 or len(sigma) != 3 or not all(math.isfinite(x) for x in mean + sigma) \
                    or min(sigma) <= 0:
                raise bad("colour_defaults", f"class '{cls}': mean and sigma must be three finite numbers, "
                          "sigma positive")
            defaults[cls] = {"mean": mean, "sigma": sigma}
        self.colour_defaults = defaults
        if self.work_scale > 1.0:
            raise bad("work_scale", "must be in (0, 1]")
        if not -0.95 <= self.skin_rg_correlation <= 0.95:
            raise bad("skin_rg_correlation", "must be in [-0.95, 0.95]")
        if not isinstance(self.connected_to, str):
            raise bad("connected_to", "must be a label name or ''")
        if not isinstance(self.background_ghost_detached, (list, tuple)) or not all(
                isinstance(x, str) and x for x in self.background_ghost_detached):
            raise bad("background_ghost_detached", "must be a list of label names")
        self.background_ghost_detached = tuple(self.background_ghost_detached)
        non_negative = ("connected_gap_px", "skin_min_intensity", "skin_min_red_excess", "startup_skin_max_fraction",
                        "temporal_velocity", "temporal_motion_px", "min_component_fraction",
                        "background_ghost_edge_ratio", "prior_confidence_inflation", "background_max_sigma",
                        "max_prior_area_ratio", "colour_room_gate")
        for name in non_negative:
            v = getattr(self, name)
            if not isinstance(v, (int, float)) or not math.isfinite(v) or v < 0:
                raise bad(name, "must be a non-negative number")
        if 0 < self.background_max_sigma < self.background_min_sigma:
            raise bad("background_max_sigma", "must be 0 (no cap) or at least background_min_sigma")

    def has_start_model(self, colour_class: str) -> bool:
        """Whether a colour class starts from a configured model (skin, or one of ``colour_defaults``):
        such a class is never bootstrapped from its labels' cores nor relearned
        (:func:`artrack.colour_model.configured_model`)."""
        return colour_class == SKIN or colour_class in self.colour_defaults

    @property
    def colour_floor(self) -> np.ndarray:
        """(3,) the colour sigmas' floors in (r, g, I): ``colour_min_sigma_chroma`` twice, then
        ``colour_min_sigma_intensity``."""
        return np.array([self.colour_min_sigma_chroma] * 2 + [self.colour_min_sigma_intensity])
