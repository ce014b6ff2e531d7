"""Synthetic multi-camera scenes: a coloured articulated person (plus optional
distractors) in a textured room, rendered by N calibrated cameras, with ground truth.

Rendering is a painter's-algorithm raster with OpenCV primitives: each body
shape (capsule, ellipsoid, sphere; see config/body_model.yaml) is projected
through the full camera model (lens distortion included) to a 2-D outline
(capsule: two end discs plus the tangent quad, radii from depth; ellipsoid:
the projected outline of its three semi-axes), primitives are sorted far to
near and filled with three concentric shrunk layers of increasing brightness
(cheap Lambertian look: darker towards the silhouette). The static room
(tiled floor, walls with coloured rectangles, ceiling) is ray-cast once per
camera and cached. Gaussian pixel noise is seeded per frame and camera (drawn
as a random crop of a per-seed noise pool, so a frame costs one add).

World frame: z up, floor z = 0, metres. Images are BGR uint8 (H, W, 3).
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field

import cv2
import numpy as np

from .body_model import BodyModel, load_body_model
from .cameras import Camera
from .motion import pose_at
from .types import Blob3D

#: room: walls at x, y = ±ROOM_HALF_SIZE, ceiling at ROOM_HEIGHT (m)
ROOM_HALF_SIZE = 5.5
ROOM_HEIGHT = 3.0
#: label value of other persons in label images (the target's links are 1..L, background 0)
OTHER_PERSON_LABEL = 255
#: stamp of frame 0, ns (a fixed, realistic wall-clock epoch so stamps are deterministic)
START_STAMP_NS = 1_700_000_000 * 1_000_000_000

_SHIFT = 4  # sub-pixel bits for cv2 drawing
_ONE = 1 << _SHIFT
_LAYERS = ((1.0, 0.6), (0.8, 0.74), (0.58, 0.87), (0.32, 1.0))  # (size scale, brightness) outer -> inner
_NOISE_MARGIN = 64


# ---------------------------------------------------------------------- cameras
def look_at_rotation(eye: np.ndarray, target: np.ndarray, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """(3, 3) cam_from_world rotation of an OpenCV camera at eye looking at target (x right, y down)."""
    z = np.asarray(target, float) - np.asarray(eye, float)
    z /= np.linalg.norm(z)
    x = np.cross(z, np.asarray(up, float))
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    return np.vstack([x, y, z])


def default_rig(n_cameras: int = 4, width: int = 640, height: int = 480, radius: float = 4.0,
                target=(0.0, 0.3, 0.9)) -> list[Camera]:
    """A ring of ``n_cameras`` cameras (cam01..camNN) ``radius`` m from the z axis, looking at ``target``.

    Azimuths 45° + k·360°/max(n, 4) (for n = 4: the room's diagonals, cam01 front-left of
    a body facing +x, cam02 back-left, cam03 back-right, cam04 front-right; fewer cameras take
    the first corners of that ring, so two cameras stand 90° apart rather than facing each
    other along one line, where their rays meet at grazing angles);
    heights alternate 1.9 / 1.6 m; focal 500 px at 640 px width (scaled with
    width), principal point near the centre, distortion k1 ≈ -0.05, k2 ≈ 0.01.
    Deterministic.
    """
    cams = []
    f = 500.0 * width / 640.0
    for k in range(n_cameras):
        az = np.deg2rad(45.0 + 360.0 * k / max(n_cameras, 4))
        eye = np.array([radius * np.cos(az), radius * np.sin(az), 1.9 if k % 2 == 0 else 1.6])
        K = np.array([[f * (1.0 + 0.004 * ((k % 3) - 1)), 0.0, (width - 1) / 2.0 + 2.0 * ((k % 2) * 2 - 1)],
                      [0.0, f * (1.0 + 0.004 * ((k % 3) - 1)), (height - 1) / 2.0 - 1.5 * ((k % 2) * 2 - 1)],
                      [0.0, 0.0, 1.0]])
        dist = np.array([-0.05 + 0.004 * ((k % 3) - 1), 0.01, 0.0, 0.0, 0.0])
        R = look_at_rotation(eye, target)
        cams.append(Camera(name=f"cam{k + 1:02d}", width=width, height=height, K=K, dist=dist, R=R,
                           t=-R @ eye))
    return cams


def _project(camera: Camera, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(N, 3) world -> (uv (N, 2) px with distortion, depth (N,) optical z, m)."""
    points = np.asarray(points, float).reshape(-1, 3)
    if hasattr(camera, "project"):
        return camera.project(points)
    depth = points @ camera.R[2] + camera.t[2]
    rvec, _ = cv2.Rodrigues(camera.R)
    uv, _ = cv2.projectPoints(points.reshape(-1, 1, 3), rvec, camera.t, camera.K, camera.dist)
    return uv.reshape(-1, 2), depth


def _pixel_rays(camera: Camera) -> np.ndarray:
    """(H*W, 3) unit world directions of the viewing rays of all pixels (row-major)."""
    v, u = np.mgrid[0:camera.height, 0:camera.width]
    uv = np.stack([u.ravel(), v.ravel()], axis=1).astype(float)
    if hasattr(camera, "rays"):
        return camera.rays(uv)[1]
    xy = cv2.undistortPoints(uv.reshape(-1, 1, 2), camera.K, camera.dist).reshape(-1, 2)
    d = np.hstack([xy, np.ones((len(xy), 1))])
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return d @ camera.R


# ---------------------------------------------------------------------- colours
SKIN_BGR = (150.0, 180.0, 220.0)
_SHIRTS = [(165, 80, 35), (45, 45, 175), (60, 140, 55), (45, 165, 205), (140, 60, 135), (35, 110, 215),
           (120, 120, 40)]
_TROUSERS = [(95, 55, 30), (65, 65, 65), (110, 150, 165), (42, 40, 40), (70, 90, 55)]
_SHOES = [(30, 30, 30), (215, 215, 215), (40, 60, 90)]
_HAIR = [(20, 25, 35), (30, 50, 80), (45, 55, 70), (35, 35, 45)]


def person_palette(seed: int, variant: int = 0) -> dict[str, np.ndarray]:
    """BGR colour (3,) float per colour class for a person.

    variant 0 is the target; variant k > 0 is a similarly dressed other person
    (same garment classes, colours perturbed by ~10-15 grey levels).
    """
    rng = np.random.default_rng([seed, 7919])
    skin = np.array(SKIN_BGR) * rng.uniform(0.85, 1.08) + rng.normal(0.0, 6.0, 3)
    pal = {
        "skin": skin,
        "shirt": np.array(_SHIRTS[rng.integers(len(_SHIRTS))], float),
        "trousers": np.array(_TROUSERS[rng.integers(len(_TROUSERS))], float),
        "shoes": np.array(_SHOES[rng.integers(len(_SHOES))], float),
        "hair": np.array(_HAIR[rng.integers(len(_HAIR))], float),
    }
    if variant:
        vr = np.random.default_rng([seed, 104729, variant])
        pal = {k: c + vr.normal(0.0, 10.0, 3) for k, c in pal.items()}
    return {k: np.clip(c, 0.0, 255.0) for k, c in pal.items()}


# ---------------------------------------------------------------------- background
_DECOR = [(60, 60, 160), (160, 90, 40), (70, 150, 90), (200, 200, 200), (80, 180, 220), (120, 60, 110),
          (40, 40, 40), (170, 170, 90)]


def render_background(camera: Camera, seed: int = 0) -> np.ndarray:
    """(H, W, 3) BGR uint8 view of the static textured room for ``seed`` (ray-cast; ~0.3 s at 640x480)."""
    rng = np.random.default_rng([seed, 31337])
    d = _pixel_rays(camera)
    o = camera.center if hasattr(camera, "center") else -camera.R.T @ camera.t
    big = 1e9
    with np.errstate(divide="ignore", invalid="ignore"):
        t_floor = np.where(d[:, 2] < -1e-9, -o[2] / d[:, 2], big)
        t_ceil = np.where(d[:, 2] > 1e-9, (ROOM_HEIGHT - o[2]) / d[:, 2], big)
        t_wx = np.where(np.abs(d[:, 0]) > 1e-9, (np.sign(d[:, 0]) * ROOM_HALF_SIZE - o[0]) / d[:, 0], big)
        t_wy = np.where(np.abs(d[:, 1]) > 1e-9, (np.sign(d[:, 1]) * ROOM_HALF_SIZE - o[1]) / d[:, 1], big)
    ts = np.stack([t_floor, t_ceil, t_wx, t_wy], axis=1)
    ts[ts <= 0] = big
    which = np.argmin(ts, axis=1)
    tmin = ts[np.arange(len(ts)), which]
    P = o + d * tmin[:, None]
    col = np.zeros((len(d), 3))

    # floor: 0.6 m tiles, per-tile shade, dark grout
    m = which == 0
    floors = [(170, 175, 180), (120, 140, 160), (150, 150, 140), (95, 110, 125)]
    base_floor = np.array(floors[rng.integers(len(floors))], float)
    tile_shade = rng.normal(0.0, 6.0, (40, 40, 1)) + rng.normal(0.0, 1.5, (40, 40, 3))
    tile = 0.6
    ix = np.floor(P[m, 0] / tile).astype(int)
    iy = np.floor(P[m, 1] / tile).astype(int)
    c = base_floor + tile_shade[ix % 40, iy % 40] + 8.0 * ((ix + iy) % 2)[:, None]
    fx = np.abs(P[m, 0] / tile - np.round(P[m, 0] / tile)) * tile
    fy = np.abs(P[m, 1] / tile - np.round(P[m, 1] / tile)) * tile
    grout = (np.minimum(fx, fy) < 0.008)[:, None]
    col[m] = np.where(grout, c * 0.55, c)

    # ceiling: light grey with light panels
    m = which == 1
    ceil = np.full((m.sum(), 3), 205.0)
    panel = (np.abs(np.mod(P[m, 0], 2.0) - 1.0) < 0.3) & (np.abs(np.mod(P[m, 1], 2.0) - 1.0) < 0.3)
    ceil[panel] = 245.0
    col[m] = ceil

    # walls: a muted colour each, skirting board, coloured rectangles (posters, doors, shelves)
    for wall_axis, w_id in ((0, 2), (1, 3)):
        for sgn in (-1.0, 1.0):
            m = (which == w_id) & (np.sign(d[:, wall_axis]) == sgn)
            if not m.any():
                continue
            along = P[m, 1 - wall_axis]
            z = P[m, 2]
            wall = np.array(rng.uniform(150, 215, 3))
            wall = wall * 0.5 + wall.mean() * 0.5
            cw = np.tile(wall, (m.sum(), 1))
            cw *= (0.88 + 0.12 * z / ROOM_HEIGHT)[:, None]  # brighter towards the ceiling lights
            for _ in range(int(rng.integers(3, 6))):
                u0 = rng.uniform(-ROOM_HALF_SIZE + 0.3, ROOM_HALF_SIZE - 1.5)
                w = rng.uniform(0.4, 1.4)
                z0 = rng.uniform(0.1, 1.6)
                h = rng.uniform(0.3, min(1.3, ROOM_HEIGHT - 0.2 - z0))
                rc = np.array(_DECOR[rng.integers(len(_DECOR))], float)
                r = (along >= u0) & (along <= u0 + w) & (z >= z0) & (z <= z0 + h)
                cw[r] = rc + rng.normal(0.0, 5.0, 3)
                frame_px = r & ((along - u0 < 0.03) | (u0 + w - along < 0.03) | (z - z0 < 0.03)
                                | (z0 + h - z < 0.03))
                cw[frame_px] = rc * 0.5
            cw[z < 0.1] = wall * 0.45  # skirting board
            col[m] = cw
    # distance falloff, fixed fine texture, mild blur (anti-aliasing of the procedural edges)
    col *= (1.0 / (1.0 + 0.025 * tmin))[:, None]
    col += rng.normal(0.0, 3.0, col.shape)
    img = np.clip(col, 0, 255).reshape(camera.height, camera.width, 3).astype(np.uint8)
    return cv2.GaussianBlur(img, (3, 3), 0.8)


# ---------------------------------------------------------------------- renderer
@dataclass
class _Geometry:
    """Link-frame shape tables of a body model, grouped by kind, for vectorised transforms."""

    cap_link: np.ndarray
    cap_p0: np.ndarray
    cap_p1: np.ndarray
    cap_r: np.ndarray
    cap_colour: list[str]
    ell_link: np.ndarray
    ell_centre: np.ndarray
    ell_axes: np.ndarray   # (E, 3, 3) columns = semi-axes in the link frame
    ell_colour: list[str]


def _geometry(body: BodyModel) -> _Geometry:
    cl, c0, c1, cr, cc, el, ec, ea, eco = [], [], [], [], [], [], [], [], []
    for i, lk in enumerate(body.links):
        for sh in lk.shapes:
            if sh.kind == "capsule":
                cl.append(i)
                c0.append(sh.p0)
                c1.append(sh.p1)
                cr.append(sh.radius)
                cc.append(sh.colour)
            else:
                radii = sh.radii if sh.kind == "ellipsoid" else np.full(3, sh.radius)
                el.append(i)
                ec.append(sh.centre)
                ea.append(np.diag(radii))
                eco.append(sh.colour)
    return _Geometry(
        np.array(cl, int), np.array(c0, float).reshape(-1, 3), np.array(c1, float).reshape(-1, 3),
        np.array(cr, float), cc, np.array(el, int), np.array(ec, float).reshape(-1, 3),
        np.array(ea, float).reshape(-1, 3, 3), eco,
    )


class Renderer:
    """Renders a body model seen by a fixed camera set (backgrounds and noise pools cached).

    Usage: ``Renderer(body, cameras, seed).render(theta, extra_thetas, noise_sigma, frame_index)``.
    """

    def __init__(self, body: BodyModel, cameras: Sequence[Camera], seed: int = 0):
        self.body = body
        self.cameras = list(cameras)
        self.seed = int(seed)
        self.geometry = _geometry(body)
        self._backgrounds: dict[str, np.ndarray] = {}
        self._noise: dict[tuple, np.ndarray] = {}
        self._palettes: dict[int, dict[str, np.ndarray]] = {}

    def background(self, camera: Camera) -> np.ndarray:
        """The cached clean room image of ``camera`` (do not modify)."""
        bg = self._backgrounds.get(camera.name)
        if bg is None or bg.shape[:2] != (camera.height, camera.width):
            bg = render_background(camera, self.seed)
            self._backgrounds[camera.name] = bg
        return bg

    def palette(self, person: int) -> dict[str, np.ndarray]:
        """Colours of person ``person`` (0 = target)."""
        if person not in self._palettes:
            self._palettes[person] = person_palette(self.seed, person)
        return self._palettes[person]

    def blob_pixels(self, image: np.ndarray, label_image: np.ndarray) -> dict[str, tuple[np.ndarray, np.ndarray]]:
        """The true pixels of each blob of the target in one rendered view: blob label ->
        (xs, ys) of its link's pixels in ``label_image`` (from ``render(..., labels=True)``)
        whose colour in ``image`` is nearest the blob's colour class in the target's palette
        (so the head's skin without its hair)."""
        palette = self.palette(0)
        colours = list(palette)
        pixels = image.astype(float)
        nearest = np.argmin([np.linalg.norm(pixels - palette[c], axis=2) for c in colours], axis=0)
        out = {}
        for k, label in zip(self.body.blob_links, self.body.blob_labels, strict=True):
            ys, xs = np.nonzero((label_image == k + 1) & (nearest == colours.index(self.body.links[k].blob.colour)))
            out[label] = (xs, ys)
        return out

    def _noise_pool(self, height: int, width: int, sigma: float) -> np.ndarray:
        key = (height, width, round(float(sigma), 6))
        pool = self._noise.get(key)
        if pool is None:
            rng = np.random.default_rng([self.seed, 271828])
            shape = (4, height + _NOISE_MARGIN, width + _NOISE_MARGIN, 3)
            pool = np.round(rng.standard_normal(shape, dtype=np.float32) * sigma).astype(np.int16)
            self._noise = {key: pool}  # keep one pool only
        return pool

    def _world_shapes(self, theta: np.ndarray) -> tuple:
        """World shapes of a pose: theta (n_dof,), or the link poses world_from_link (L, 4, 4)."""
        g = self.geometry
        T = theta if theta.ndim == 3 else self.body.forward_kinematics(theta)
        tp = self.body.transform_points
        p0 = tp(T, g.cap_link, g.cap_p0)
        p1 = tp(T, g.cap_link, g.cap_p1)
        ec = tp(T, g.ell_link, g.ell_centre)
        ea = T[g.ell_link, :3, :3] @ g.ell_axes  # (E, 3, 3) world semi-axes as columns
        return p0, p1, ec, ea

    def _primitives(self, camera: Camera, persons: list[tuple[int, np.ndarray]]) -> list[tuple]:
        """Projected 2-D primitives of all persons, sorted far to near.

        Each: (distance, kind, params, bgr (3,), label).
        """
        g = self.geometry
        fpx = float(camera.K[0, 0])
        centre = camera.center
        prims = []
        for person, theta in persons:
            pal = self.palette(person)
            p0, p1, ec, ea = self._world_shapes(theta)
            nc, ne = len(p0), len(ec)
            pts = np.concatenate([p0, p1, ec, (ec[:, None, :] + np.swapaxes(ea, 1, 2)).reshape(-1, 3),
                                  (ec[:, None, :] - np.swapaxes(ea, 1, 2)).reshape(-1, 3)])
            uv, depth = _project(camera, pts)
            uv0, uv1 = uv[:nc], uv[nc:2 * nc]
            d0, d1 = depth[:nc], depth[nc:2 * nc]
            uvc = uv[2 * nc:2 * nc + ne]
            dc = depth[2 * nc:2 * nc + ne]
            uvp = uv[2 * nc + ne:2 * nc + 4 * ne].reshape(ne, 3, 2)
            uvm = uv[2 * nc + 4 * ne:].reshape(ne, 3, 2)
            dpm = np.minimum(depth[2 * nc + ne:2 * nc + 4 * ne], depth[2 * nc + 4 * ne:]).reshape(ne, 3)
            for k in range(nc):
                if min(d0[k], d1[k]) < 0.1:
                    continue
                link = g.cap_link[k]
                dist = float(np.linalg.norm(0.5 * (p0[k] + p1[k]) - centre))
                params = (uv0[k], uv1[k], fpx * g.cap_r[k] / d0[k], fpx * g.cap_r[k] / d1[k])
                label = link + 1 if person == 0 else OTHER_PERSON_LABEL
                prims.append((dist, 0, params, pal[g.cap_colour[k]], label))
            for k in range(ne):
                if dc[k] < 0.1 or dpm[k].min() < 0.05:
                    continue
                v = 0.5 * (uvp[k] - uvm[k])  # (3, 2) projected semi-axes
                S = v.T @ v
                evals, evecs = np.linalg.eigh(S)
                axes = np.sqrt(np.maximum(evals[::-1], 0.0))
                angle = float(np.degrees(np.arctan2(evecs[1, 1], evecs[0, 1])))
                link = g.ell_link[k]
                dist = float(np.linalg.norm(ec[k] - centre))
                label = link + 1 if person == 0 else OTHER_PERSON_LABEL
                prims.append((dist, 1, (uvc[k], axes, angle), pal[g.ell_colour[k]], label))
        prims.sort(key=lambda p: -p[0])
        return prims

    @staticmethod
    def _draw(img: np.ndarray, kind: int, params: tuple, colour, scale: float, line_type: int) -> None:
        lim = 1e5
        if kind == 0:
            a, b, ra, rb = params
            ra, rb = ra * scale, rb * scale
            if max(ra, rb) < 0.25 or np.abs(a).max() > lim or np.abs(b).max() > lim:
                return
            ai = (int(round(a[0] * _ONE)), int(round(a[1] * _ONE)))
            bi = (int(round(b[0] * _ONE)), int(round(b[1] * _ONE)))
            cv2.circle(img, ai, int(round(ra * _ONE)), colour, -1, line_type, _SHIFT)
            cv2.circle(img, bi, int(round(rb * _ONE)), colour, -1, line_type, _SHIFT)
            dvec = b - a
            n = np.linalg.norm(dvec)
            if n > 1e-6:
                nrm = np.array([-dvec[1], dvec[0]]) / n
                quad = np.array([a + ra * nrm, b + rb * nrm, b - rb * nrm, a - ra * nrm])
                cv2.fillConvexPoly(img, np.round(quad * _ONE).astype(np.int32), colour, line_type, _SHIFT)
        else:
            c, axes, angle = params
            ax = axes * scale
            if ax[0] < 0.25 or np.abs(c).max() > lim:
                return
            cv2.ellipse(img, (int(round(c[0] * _ONE)), int(round(c[1] * _ONE))),
                        (int(round(ax[0] * _ONE)), int(round(max(ax[1], 0.3) * _ONE))),
                        angle, 0.0, 360.0, colour, -1, line_type, _SHIFT)

    def render(self, theta: np.ndarray | None, extra_thetas: Sequence[np.ndarray] = (), noise_sigma: float = 2.0,
               frame_index: int = 0, labels: bool = False):
        """Render the target pose theta (n_dof,; None: no target, the empty room) and other
        persons in every camera.

        Returns a list of BGR uint8 images (H, W, 3), one per camera; with
        labels=True also a list of uint8 label images (H, W): 0 background,
        link index + 1 for the target's links, OTHER_PERSON_LABEL for others
        (noise-free, painter's order, no anti-aliasing).
        """
        persons = [(0, np.asarray(theta, float))] if theta is not None else []
        persons += [(k + 1, np.asarray(x, float)) for k, x in enumerate(extra_thetas)]
        images, label_images = [], []
        for ci, cam in enumerate(self.cameras):
            img = self.background(cam).copy()
            lab = np.zeros((cam.height, cam.width), np.uint8) if labels else None
            for _, kind, params, colour, label in self._primitives(cam, persons):
                for scale, bright in _LAYERS:
                    col = tuple(float(x) for x in np.minimum(colour * bright, 255.0))
                    self._draw(img, kind, params, col, scale, cv2.LINE_AA)
                if lab is not None:
                    self._draw(lab, kind, params, int(label), 1.0, cv2.LINE_8)
            if noise_sigma > 0:
                pool = self._noise_pool(cam.height, cam.width, noise_sigma)
                rng = np.random.default_rng([self.seed, int(frame_index), ci])
                k, dy, dx = rng.integers(len(pool)), rng.integers(_NOISE_MARGIN), rng.integers(_NOISE_MARGIN)
                noise = pool[k, dy:dy + cam.height, dx:dx + cam.width]
                img = cv2.add(img, noise, dtype=cv2.CV_8U)
            images.append(img)
            label_images.append(lab)
        return (images, label_images) if labels else images


    def silhouettes(self, world_from_link: np.ndarray) -> list[np.ndarray]:
        """(H, W) bool mask per camera: where the body model's shapes, placed at the link poses
        ``world_from_link`` (L, 4, 4) (e.g. a tracked estimate), project (no background, no noise)."""
        T = np.asarray(world_from_link, dtype=float)
        out = []
        for cam in self.cameras:
            lab = np.zeros((cam.height, cam.width), np.uint8)
            for _, kind, params, _, _ in self._primitives(cam, [(0, T)]):
                self._draw(lab, kind, params, 1, 1.0, cv2.LINE_8)
            out.append(lab.astype(bool))
        return out


_RENDERERS: dict[tuple, Renderer] = {}


def render(body: BodyModel, theta: np.ndarray, cameras: Sequence[Camera], seed: int = 0,
           extra_thetas: Sequence[np.ndarray] = (), noise_sigma: float = 2.0, frame_index: int = 0,
           labels: bool = False):
    """Render theta (n_dof,) (and ``extra_thetas``, other persons) in every camera.

    The room background depends on ``seed``; pixel noise (Gaussian, sigma in
    grey levels) on (seed, frame_index, camera). Returns list[(H, W, 3) BGR
    uint8] (and label images if labels=True, see Renderer.render). A Renderer
    is cached per (body, cameras, seed); keep your own Renderer for control.
    """
    key = (id(body), tuple(id(c) for c in cameras), int(seed))
    r = _RENDERERS.get(key)
    if r is None:
        if len(_RENDERERS) > 8:
            _RENDERERS.clear()
        r = _RENDERERS[key] = Renderer(body, cameras, seed)
    return r.render(theta, extra_thetas, noise_sigma, frame_index, labels)


# ---------------------------------------------------------------------- scenes
@dataclass
class SceneConfig:
    """A synthetic scene. motion: a motion.motion_names() entry; occlusion=True turns
    'default' into 'self_occlusion'; distractor=True adds a second walking person."""

    n_cameras: int = 4
    width: int = 640
    height: int = 480
    fps: float = 30.0
    duration_s: float = 10.0
    seed: int = 0
    noise_sigma: float = 2.0
    motion: str = "default"
    occlusion: bool = False
    distractor: bool = False
    empty_s: float = 0.0  # the room is empty this long before the person appears (motion clock starts then)
    #: (start_s, seconds): every camera sees only the empty room in that span (the person goes on
    #: moving; ground truth is kept) — an "occlude everything" event for recovery tests
    blackout: tuple[float, float] | None = None

    @property
    def n_frames(self) -> int:
        """Number of frames, round(duration_s * fps)."""
        return int(round(self.duration_s * self.fps))

    @property
    def motion_name(self) -> str:
        """The motion actually played."""
        return "self_occlusion" if self.occlusion and self.motion == "default" else self.motion

    def blacked_out(self, index: int) -> bool:
        """Frame ``index`` falls in the blackout span (start <= t < start + seconds, t = index / fps)."""
        if self.blackout is None:
            return False
        t = index / self.fps
        start, seconds = self.blackout
        return start <= t < start + seconds


@dataclass
class SynthFrame:
    """One rendered frame with ground truth.

    images: camera name -> (H, W, 3) BGR uint8; theta: (n_dof,) target pose;
    joints: (15, 3) world positions of body.joint_names (m) (theta and joints are None
    while the room is still empty, see SceneConfig.empty_s); blobs3d: the
    ground-truth blob features (centre and covariance from the body model);
    extra_thetas: poses of other persons (distractors).
    """

    index: int
    stamp_ns: int
    images: dict[str, np.ndarray]
    theta: np.ndarray | None  # None while the room is empty (SceneConfig.empty_s)
    joints: np.ndarray | None
    blobs3d: list[Blob3D]
    extra_thetas: list[np.ndarray] = field(default_factory=list)


def scene_cameras(config: SceneConfig) -> list[Camera]:
    """The cameras of a scene (default_rig of the configured count and size)."""
    return default_rig(config.n_cameras, config.width, config.height)


def frame_stamp_ns(index: int, fps: float) -> int:
    """Stamp of frame ``index``, ns."""
    return START_STAMP_NS + int(round(index * 1e9 / fps))


def generate_scene(config: SceneConfig, body: BodyModel | None = None,
                   cameras: Sequence[Camera] | None = None) -> Iterator[SynthFrame]:
    """Yield the frames of a scene (deterministic for a given config)."""
    body = load_body_model() if body is None else body
    cameras = scene_cameras(config) if cameras is None else list(cameras)
    renderer = Renderer(body, cameras, config.seed)
    motion = config.motion_name
    for i in range(config.n_frames):
        t = i / config.fps - config.empty_s  # the motion's clock
        present = t >= 0.0
        theta = pose_at(motion, t, body) if present else None
        extra = [pose_at("distractor", t, body)] if config.distractor and present else []
        if config.blacked_out(i):  # the cameras see the empty room; the truth goes on
            imgs = renderer.render(None, (), config.noise_sigma, frame_index=i)
        else:
            imgs = renderer.render(theta, extra, config.noise_sigma, frame_index=i)
        yield SynthFrame(
            index=i,
            stamp_ns=frame_stamp_ns(i, config.fps),
            images={c.name: im for c, im in zip(cameras, imgs, strict=True)},
            theta=theta,
            joints=body.joint_positions(theta) if present else None,
            blobs3d=body.blobs3d(theta) if present else [],
            extra_thetas=extra,
        )


def montage(images: Sequence[np.ndarray], cols: int = 2) -> np.ndarray:
    """Tile equally sized BGR images into one (rows*H, cols*W, 3) image."""
    h, w = images[0].shape[:2]
    rows = (len(images) + cols - 1) // cols
    out = np.zeros((rows * h, cols * w, 3), np.uint8)
    for k, im in enumerate(images):
        r, c = divmod(k, cols)
        out[r * h:(r + 1) * h, c * w:(c + 1) * w] = im
    return out
