"""The body model as clipped quadrics and its visible outline (ALGORITHMS.md §2 "Model")."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from artrack.body_model import Shape, body_model_from_dict, load_body_model
from artrack.body_quadrics import body_quadrics, sample_body, shape_quadrics, visible_surface_gaussian
from artrack.motion import pose_at
from artrack.quadrics import quadric_value
from artrack.synth import Renderer, default_rig


@pytest.fixture(scope="module")
def scene():
    body = load_body_model()
    cams = default_rig(4, 320, 240)
    return body, cams, Renderer(body, cams, 3), body_quadrics(body)


def boundary_distance(label: np.ndarray) -> np.ndarray:
    """Distance (px) of every pixel to the nearest pixel on a label boundary (either side)."""
    b = np.zeros(label.shape, bool)
    dx = label[:, 1:] != label[:, :-1]
    dy = label[1:] != label[:-1]
    b[:, 1:] |= dx
    b[:, :-1] |= dx
    b[1:] |= dy
    b[:-1] |= dy
    return cv2.distanceTransform((~b).astype(np.uint8), cv2.DIST_L2, 5)


def sample_distances(cam, samples, dist_img: np.ndarray) -> np.ndarray:
    """Distances of the samples, mapped through the full (distorted) camera, to the label boundaries."""
    uv, _ = cam.project((samples.points_cam - cam.t) @ cam.R)
    ui = np.clip(np.round(uv).astype(int), 0, [cam.width - 1, cam.height - 1])
    return dist_img[ui[:, 1], ui[:, 0]]


def test_capsule_quadrics_are_the_capsule_surface():
    rng = np.random.default_rng(0)
    sh = Shape("capsule", "skin", p0=np.array([0.02, -0.1, 0.3]), p1=np.array([0.0, 0.15, 0.1]), radius=0.05)
    parts = shape_quadrics(sh)
    assert [p for p, _ in parts] == ["cylinder", "cap0", "cap1"]
    # random points: on the capsule surface iff (distance to the segment) == r
    X = rng.uniform(-0.3, 0.4, size=(4000, 3))
    a = sh.p1 - sh.p0
    s = np.clip((X - sh.p0) @ a / (a @ a), 0.0, 1.0)
    dseg = np.linalg.norm(X - (sh.p0 + s[:, None] * a), axis=1)
    Xs = sh.p0 + s[:, None] * a + (X - sh.p0 - s[:, None] * a) / dseg[:, None] * sh.radius  # surface points
    for pts, expect in ((Xs, True), (X[np.abs(dseg - sh.radius) > 0.01], False)):
        on = np.zeros(len(pts), bool)
        for _, q in parts:
            scale = np.abs(q.surface).max()
            on |= (np.abs(quadric_value(q.surface, pts)) < 1e-9 * scale) & (quadric_value(q.clip, pts) <= 1e-12)
        assert on.all() if expect else not on.any()
    # a zero-length capsule is a sphere, ellipsoids / spheres are single unclipped quadrics
    assert [p for p, _ in shape_quadrics(Shape("capsule", "skin", p0=np.zeros(3), p1=np.zeros(3), radius=0.1))] \
        == ["sphere"]
    ell = shape_quadrics(Shape("ellipsoid", "skin", centre=np.array([0, 0, 0.1]), radii=np.array([0.1, 0.2, 0.3])))
    assert len(ell) == 1 and ell[0][1].clip is None
    assert quadric_value(ell[0][1].surface, np.array([[0.0, 0.2, 0.1], [0.0, 0.0, 0.4]])) == pytest.approx([0, 0])


@pytest.mark.parametrize("t", [0.0, 1.3, 2.7])
def test_outline_samples_lie_on_rendered_silhouette_edges(scene, t):
    body, cams, renderer, quads = scene
    theta = pose_at("default", t, body)
    _, labels = renderer.render(theta, noise_sigma=0.0, labels=True)
    T = body.forward_kinematics(theta)
    for cam, lab in zip(cams, labels):
        shifted = T.copy()
        shifted[:, :3, 3] += 0.08 * cam.R[0]  # the whole body moved 8 cm (~5 px) along the image x axis
        dist_img = boundary_distance(lab)
        s = sample_body(quads, cam.cam_from_world @ T, cam.K, (cam.width, cam.height), 4.0)
        assert len(s) > 60
        assert set(np.unique(s.link)) >= {1, 3, 6, 9, 12}  # torso, arms and thighs are seen from every side
        d = sample_distances(cam, s, dist_img)
        assert np.median(d) < 1.0 and np.mean(d < 1.5) > 0.85, cam.name
        s_off = sample_body(quads, cam.cam_from_world @ shifted, cam.K, (cam.width, cam.height), 4.0)
        assert np.median(sample_distances(cam, s_off, dist_img)) > 1.5, cam.name  # the check can fail


def test_occlusion_drops_samples_off_the_silhouette(scene):
    body, cams, renderer, quads = scene
    theta = pose_at("default", 1.3, body)
    _, labels = renderer.render(theta, noise_sigma=0.0, labels=True)
    T = body.forward_kinematics(theta)
    for cam, lab in zip(cams, labels):
        dist_img = boundary_distance(lab)
        E = cam.cam_from_world @ T
        vis = sample_body(quads, E, cam.K, (cam.width, cam.height), 4.0)
        every = sample_body(quads, E, cam.K, (cam.width, cam.height), 4.0, occlusion=False)
        key = {tuple(np.round(u, 6)) for u in vis.uv}
        hidden = np.array([tuple(np.round(u, 6)) not in key for u in every.uv])
        assert hidden.sum() > 20  # torso / pelvis outline behind the limbs, limb ends inside the torso, ...
        d_hidden = sample_distances(cam, type(every)(*(a[hidden] for a in (
            every.uv, every.normals, every.points_cam, every.link, every.prim))), dist_img)
        d_vis = sample_distances(cam, vis, dist_img)
        assert np.mean(d_hidden < 1.5) < np.mean(d_vis < 1.5) - 0.15, cam.name
        only = sample_body(quads, E, cam.K, (cam.width, cam.height), 4.0, links=[3])
        assert len(only) and set(only.link) == {3}


def _per_quadric_reference(quads, E, K, size, spacing, margin=0.0):
    """The unbatched path: :func:`sample_contour` quadric by quadric, then the body occlusion test."""
    from artrack.body_quadrics import _occluded
    from artrack.lie import inverse_se3
    from artrack.quadrics import sample_contour

    Ti = inverse_se3(E)
    Q_cam = np.array([Ti[q.link].T @ q.quadric.surface @ Ti[q.link] for q in quads])
    clip_cam = np.array([np.zeros((4, 4)) if q.quadric.clip is None else Ti[q.link].T @ q.quadric.clip @ Ti[q.link]
                         for q in quads])
    parts = [(sample_contour(q.quadric, E[q.link], K, size, spacing, margin_px=margin), k) for k, q in enumerate(quads)]
    uv = np.vstack([s.uv for s, _ in parts])
    nrm = np.vstack([s.normals for s, _ in parts])
    P = np.vstack([s.points_cam for s, _ in parts])
    prim = np.concatenate([np.full(len(s), k) for s, k in parts]).astype(int)
    keep = ~_occluded(P, prim, Q_cam, clip_cam)
    return uv[keep], nrm[keep], P[keep], prim[keep]


@pytest.mark.parametrize("size", [(320, 240), (640, 480)])
def test_batched_sampling_equals_per_quadric_sampling(size):
    """sample_body / sample_body_views (all quadrics of all cameras in one pass) give the samples of
    sample_contour quadric by quadric, in the same order, to 1e-9 — random poses, including bodies
    straddling the camera plane (hyperbolae, per-conic fallback) and cropped outlines."""
    from artrack.body_quadrics import sample_body_views
    from artrack.lie import exp_se3

    body = load_body_model()
    quads = body_quadrics(body)
    cams = default_rig(4, *size)
    rng = np.random.default_rng(7)
    n_samples = 0
    for trial in range(8):
        T = body.forward_kinematics(pose_at("default", rng.uniform(0.0, 10.0), body))
        T = T @ exp_se3(rng.normal(0.0, [0.03] * 3 + [0.3] * 3, size=(len(T), 6)))
        Es = np.array([c.cam_from_world @ T for c in cams])
        if trial % 4 == 3:
            Es[:, :, 2, 3] -= rng.uniform(3.0, 3.6)  # the body around the camera centre
        spacing, margin = (4.0, 0.0) if trial % 2 == 0 else (2.5, 3.0)
        views = sample_body_views(quads, Es, np.array([c.K for c in cams]), [size] * 4, spacing, margin_px=margin)
        for cam, E, got in zip(cams, Es, views):
            uv, nrm, P, prim = _per_quadric_reference(quads, E, cam.K, size, spacing, margin)
            one = sample_body(quads, E, cam.K, size, spacing, margin_px=margin)
            for s in (got, one):
                assert np.array_equal(s.prim, prim)
                assert np.array_equal(s.link, np.array([quads[k].link for k in prim], dtype=int))
                np.testing.assert_allclose(s.uv, uv, rtol=0, atol=1e-9)
                np.testing.assert_allclose(s.normals, nrm, rtol=0, atol=1e-9)
                np.testing.assert_allclose(s.points_cam, P, rtol=0, atol=1e-9)
            n_samples += len(uv)
    assert n_samples > 1000


# ---------------------------------------------------------------------- blob features from the shapes
def _one_link_body(shapes: list[dict], blob: dict | None = None) -> dict:
    """A body of one free link (origin 1 m above the floor) with these shapes."""
    return {"links": [{"name": "ball", "parent": None, "joint": "free", "offset": [0.0, 0.0, 1.0],
                       "limits": [[-9, 9]] * 6, "end": [0.0, 0.0, 0.1], "colour": "skin", "shapes": shapes,
                       **({"blob": blob} if blob else {})}],
            "joints": [{"name": "ball", "link": "ball"}]}


def test_visible_surface_gaussian_of_a_lone_sphere_is_analytic():
    # a sphere of radius r seen from a level ring: each surface element counts with its projected
    # area averaged over the ring, |n_horizontal| / pi, so the mean is the centre and the
    # per-axis sigma is r sqrt(3/8) across and r / 2 up (integrals over z of (1 - z^2)^(3/2)
    # and z^2 (1 - z^2)^(1/2) against (1 - z^2)^(1/2)); the ring is 4 m away, not at infinity
    r = 0.1
    body = body_model_from_dict(_one_link_body([{"type": "sphere", "centre": [0.0, 0.0, 0.05], "radius": r}]))
    mean, cov = visible_surface_gaussian(body, 0, "skin")
    assert np.allclose(mean, [0.0, 0.0, 0.05], atol=1e-3)
    sigma = np.sqrt(np.diag(cov))
    assert np.allclose(sigma, r * np.array([np.sqrt(3 / 8), np.sqrt(3 / 8), 0.5]), rtol=0.02)


def test_visible_surface_gaussian_drops_what_another_shape_hides():
    # a skin sphere with a hair sphere over its top half (as hair over a face): only the uncovered
    # lower, front part counts, so the skin mean moves down and forward, away from the hair;
    # the same body with the hair removed keeps the centre
    skin = {"type": "sphere", "centre": [0.0, 0.0, 0.0], "radius": 0.1}
    hair = {"type": "sphere", "centre": [-0.03, 0.0, 0.06], "radius": 0.1, "colour": "hair"}
    body = body_model_from_dict(_one_link_body([skin, hair]))
    mean, _ = visible_surface_gaussian(body, 0, "skin")
    assert mean[2] < -0.01 and mean[0] > 0.01 and abs(mean[1]) < 1e-3
    hair_mean, _ = visible_surface_gaussian(body, 0, "hair")
    assert hair_mean[2] > 0.05 and hair_mean[0] < -0.01
    bare = body_model_from_dict(_one_link_body([skin]))
    assert np.allclose(visible_surface_gaussian(bare, 0, "skin")[0], 0.0, atol=1e-3)
    with pytest.raises(ValueError, match="no shape of colour 'shirt'"):
        visible_surface_gaussian(body, 0, "shirt")


def test_blob_auto_takes_the_visible_surface_gaussian():
    data = _one_link_body([{"type": "sphere", "centre": [0.0, 0.0, 0.0], "radius": 0.1},
                           {"type": "sphere", "centre": [-0.03, 0.0, 0.06], "radius": 0.1, "colour": "hair"}],
                          blob={"colour": "skin", "centre": "auto", "radii": "auto"})
    body = body_model_from_dict(data)
    mean, cov = visible_surface_gaussian(body, 0, "skin")
    blob = body.links[0].blob
    assert blob.derived == ("centre", "radii")
    assert np.allclose(blob.centre, mean) and np.allclose(blob.radii, np.sqrt(np.diag(cov)))
    data["links"][0]["blob"]["radii"] = [0.05, 0.05, 0.05]  # only the centre derived
    part = body_model_from_dict(data).links[0].blob
    assert part.derived == ("centre",) and np.allclose(part.centre, mean) and np.allclose(part.radii, 0.05)


def test_default_blobs_sit_where_the_rendered_pixels_are(scene):
    # the synthetic renderer's true label images: the pixels of each blob link, in its colour,
    # have their centroid's row near the projected 'auto' blob centre's (median over views and
    # poses). The hand-set centres at the middle of each shape were 3-4 px (4-6 cm)
    # above the thigh and shin pixels. The head is left out: the renderer paints whole ellipses
    # in depth order (the face over the hair from the front, the hair over the face from behind),
    # not the 3-D visible surface, so its head pixels sit ~3 px below any one 3-D centre.
    # (The default body's torso and head centres are measured where the tracker's blobs sit,
    # config/body_model.yaml; the 'auto' centres are computed here for every link.)
    body, cams, renderer, _ = scene
    off: dict[str, list[float]] = {lab: [] for lab in body.blob_labels}
    link = {name: body.link_names.index(name) for name in body.blob_labels}
    auto = {name: visible_surface_gaussian(body, i, body.links[i].blob.colour)[0] for name, i in link.items()}
    for t in (0.5, 2.0, 3.5, 5.0):
        theta = pose_at("default", t, body)
        T = body.forward_kinematics(theta)
        images, labels = renderer.render(theta, (), 0.0, frame_index=0, labels=True)
        for cam, img, lab in zip(cams, images, labels, strict=True):
            for name, (xs, ys) in renderer.blob_pixels(img, lab).items():
                if len(xs) < 20:
                    continue
                centre = T[link[name], :3, :3] @ auto[name] + T[link[name], :3, 3]
                uv = cam.project(centre[None])[0][0]
                off[name].append(float(ys.mean() - uv[1]))
    rows = {name: float(np.median(off[name])) for name in ("torso", "l_hand", "r_hand", "l_thigh", "r_thigh",
                                                            "l_shin", "r_shin")}
    assert all(abs(v) < 1.5 for v in rows.values()), rows
