"""Quadric models, image conics and visible contour samples (ALGORITHMS.md §2 "Model")."""

from __future__ import annotations

import numpy as np
import pytest

from artrack.lie import exp_se3, inverse_se3, make_se3
from artrack.quadrics import (
    ClippedQuadric,
    cone,
    cylinder,
    ellipsoid,
    image_conic,
    quadric_in_camera,
    quadric_value,
    sample_contour,
    slab,
    sphere,
    transform_quadric,
)

K = np.array([[500.0, 0.0, 320.0], [0.0, 480.0, 240.0], [0.0, 0.0, 1.0]])
SIZE = (640, 480)


def translation(t) -> np.ndarray:
    return make_se3(np.eye(3), np.asarray(t, dtype=float))


def look_pose(center, rng: np.random.Generator) -> np.ndarray:
    """A random orientation placed at ``center`` (camera frame)."""
    return make_se3(exp_se3(np.r_[0, 0, 0, rng.normal(size=3)])[:3, :3], center)


def rays_of(uv: np.ndarray) -> np.ndarray:
    d = np.c_[uv, np.ones(len(uv))] @ np.linalg.inv(K).T
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def test_constructors_inside_outside():
    assert quadric_value(sphere(0.5, (1, 0, 0)), np.array([[1.0, 0, 0]])) < 0
    assert np.isclose(quadric_value(sphere(0.5, (1, 0, 0)), np.array([[1.5, 0, 0]])), 0)
    assert np.isclose(quadric_value(ellipsoid((1, 2, 3)), np.array([[0, 2.0, 0]])), 0)
    assert np.isclose(quadric_value(cylinder(0.1), np.array([[0.06, 0.08, 7.0]])), 0)
    assert np.isclose(quadric_value(cone(0.5, apex_z=1.0), np.array([[0.5, 0.0, 2.0]])), 0)
    s = slab(-0.2, 0.3)
    assert quadric_value(s, np.array([[5, 5, 0.0]])) < 0 and quadric_value(s, np.array([[0, 0, 0.31]])) > 0
    T = exp_se3(np.r_[0.1, 0.2, 0.3, 0.4, -0.5, 0.6])
    X = np.array([[0.3, 0.1, -0.2], [1, 2, 3.0]])
    Xt = X @ T[:3, :3].T + T[:3, 3]
    assert np.allclose(
        quadric_value(transform_quadric(ellipsoid((1, 2, 3)), T), Xt), quadric_value(ellipsoid((1, 2, 3)), X)
    )
    with pytest.raises(ValueError):
        sphere(-1.0)


def test_image_conic_sign_invariant_and_pixel_transform():
    E = translation((0.1, -0.2, 3.0))
    Q = ellipsoid((0.2, 0.3, 0.4))
    Cn = image_conic(Q, E)
    assert np.allclose(image_conic(-Q, E), Cn)
    Ki = np.linalg.inv(K)
    assert np.allclose(image_conic(Q, E, K), Ki.T @ Cn @ Ki)
    # the image of the centre is inside the silhouette (negative)
    c = K @ (E[:3, 3] / E[2, 3])
    assert c @ image_conic(Q, E, K) @ c < 0


def test_sphere_on_axis_is_the_analytic_circle():
    r, d = 0.25, 2.0
    K_square = np.array([[500.0, 0.0, 320.0], [0.0, 500.0, 240.0], [0.0, 0.0, 1.0]])
    s = sample_contour(sphere(r), translation((0, 0, d)), K_square, SIZE, 4.0)
    radius = 500.0 * r / np.sqrt(d * d - r * r)
    rho = np.hypot(s.uv[:, 0] - 320, s.uv[:, 1] - 240)
    assert np.allclose(rho, radius, atol=1e-9)
    assert len(s) == pytest.approx(2 * np.pi * radius / 4.0, abs=1.5)
    # outward normals are radial
    radial = (s.uv - [320, 240]) / rho[:, None]
    assert np.allclose(s.normals, radial, atol=1e-9)
    spacing = np.linalg.norm(np.diff(s.uv, axis=0), axis=1)
    assert spacing.max() - spacing.min() < 0.05


def test_sphere_off_axis_contour_is_the_tangent_cone():
    rng = np.random.default_rng(0)
    for _ in range(5):
        X0 = np.r_[rng.uniform(-0.6, 0.6, 2), rng.uniform(1.5, 3.0)]
        r = rng.uniform(0.05, 0.3)
        s = sample_contour(sphere(r), translation(X0), K, SIZE, 3.0)
        assert len(s) > 10
        D = np.linalg.norm(X0)
        cos = rays_of(s.uv) @ X0 / D
        assert np.allclose(cos, np.sqrt(D * D - r * r) / D, atol=1e-10)
        assert np.allclose(np.linalg.norm(s.points_cam - X0, axis=1), r, atol=1e-9)
        # the sample's 3-D point projects to the sample
        proj = s.points_cam @ K.T
        assert np.allclose(proj[:, :2] / proj[:, 2:], s.uv, atol=1e-7)


def test_cylinder_contour_lines_are_tangent_and_clipped():
    rng = np.random.default_rng(1)
    r, half = 0.06, 0.25
    prim = ClippedQuadric(cylinder(r), slab(-half, half))
    for _ in range(5):
        E = look_pose(np.r_[rng.uniform(-0.2, 0.2, 2), rng.uniform(1.5, 2.5)], rng)
        s = sample_contour(prim, E, K, SIZE, 2.0)
        assert len(s) > 20
        P = (inverse_se3(E) @ np.c_[s.points_cam, np.ones(len(s))].T).T[:, :3]
        assert np.allclose(np.hypot(P[:, 0], P[:, 1]), r, atol=1e-9)  # on the cylinder
        assert np.all(np.abs(P[:, 2]) <= half + 1e-12)  # inside the clipping slab
        # tangency: the ray is at distance r from the axis line
        axis_p, axis_d = E[:3, 3], E[:3, 2]
        rays = rays_of(s.uv)
        cr = np.cross(rays, axis_d)
        dist = np.abs(axis_p @ cr.T) / np.linalg.norm(cr, axis=1)
        assert np.allclose(dist, r, atol=1e-9)
        # samples fall on two straight image lines; normals orthogonal to them, pointing outward
        C = image_conic(cylinder(r), E, K)
        for sign in (1, -1):
            uvh = np.c_[s.uv + sign * 0.5 * s.normals, np.ones(len(s))]
            vals = np.einsum("ni,ij,nj->n", uvh, C, uvh)
            assert np.all(np.sign(vals) == sign)
        for grp in (s.normals @ s.normals[0] > 0, s.normals @ s.normals[0] <= 0):
            pts = s.uv[grp]
            if len(pts) < 3:
                continue
            centred = pts - pts.mean(0)
            sv = np.linalg.svd(centred, compute_uv=False)
            assert sv[1] < 1e-6 * sv[0]
            direction = np.linalg.svd(centred)[2][0]
            assert np.allclose(s.normals[grp] @ direction, 0, atol=1e-9)


def test_truncated_cone_contour():
    rng = np.random.default_rng(2)
    prim = ClippedQuadric(cone(0.2, apex_z=-0.5), slab(-0.2, 0.2))
    E = look_pose(np.r_[0.05, -0.05, 2.0], rng)
    s = sample_contour(prim, E, K, SIZE, 2.0)
    assert len(s) > 20
    P = (inverse_se3(E) @ np.c_[s.points_cam, np.ones(len(s))].T).T[:, :3]
    assert np.allclose(quadric_value(cone(0.2, -0.5), P), 0, atol=1e-9)
    assert np.all(np.abs(P[:, 2]) <= 0.2 + 1e-12)


def check_samples(prim: ClippedQuadric, E: np.ndarray, s) -> None:
    """Samples lie on the quadric, rays tangent to it, in front, inside the clip, projecting onto uv."""
    Qc = quadric_in_camera(prim.surface, E)
    scale = np.abs(Qc).max()
    Xh = np.c_[s.points_cam, np.ones(len(s))]
    assert np.allclose(np.einsum("ni,ij,nj->n", Xh, Qc, Xh) / scale, 0, atol=1e-8)
    grad = (Xh @ Qc)[:, :3]
    cosang = np.einsum("ni,ni->n", grad, s.points_cam) / (
        np.linalg.norm(grad, axis=1) * np.linalg.norm(s.points_cam, axis=1)
    )
    assert np.allclose(cosang, 0, atol=1e-6)
    assert np.all(s.points_cam[:, 2] > 0)
    proj = s.points_cam @ K.T
    assert np.allclose(proj[:, :2] / proj[:, 2:], s.uv, atol=1e-6)
    assert np.all((s.uv >= -1e-9) & (s.uv <= np.array(SIZE) - 1 + 1e-9))
    assert np.allclose(np.linalg.norm(s.normals, axis=1), 1)
    if prim.clip is not None:
        Xh = np.c_[s.points_cam, np.ones(len(s))]
        assert np.all(np.einsum("ni,ij,nj->n", Xh, quadric_in_camera(prim.clip, E), Xh) <= 1e-9)


def test_generic_contour_properties_random_shapes():
    """Every sample: on the quadric, ray tangent to it, in front, projecting onto its pixel."""
    rng = np.random.default_rng(3)
    shapes = [
        ClippedQuadric(ellipsoid((0.1, 0.2, 0.3))),
        ClippedQuadric(ellipsoid((0.3, 0.1, 0.05)), slab(-0.05, 0.2)),
        ClippedQuadric(cylinder(0.08), slab(-0.3, 0.3)),
        ClippedQuadric(cone(0.3, 0.4), slab(-0.3, 0.3)),
    ]
    # includes poses close to the camera so that some images are hyperbolae / larger than the image
    for k in range(24):
        prim = shapes[k % len(shapes)]
        E = look_pose(np.r_[rng.uniform(-0.3, 0.3, 2), rng.uniform(0.15, 2.5)], rng)
        s = sample_contour(prim, E, K, SIZE, 3.0)
        if len(s) == 0:
            continue
        check_samples(prim, E, s)


def test_ellipse_hyperbola_when_quadric_straddles_the_camera_plane():
    # a long ellipsoid passing beside the camera: part of it is behind the image plane -> hyperbola
    E = make_se3(exp_se3(np.r_[0, 0, 0, 1.3, 0, 0])[:3, :3], [0.4, 0.0, 0.5])
    prim = ClippedQuadric(ellipsoid((0.1, 0.1, 2.0)))
    Cn = image_conic(prim.surface, E)
    assert np.linalg.det(Cn[:2, :2]) < 0  # hyperbola
    s = sample_contour(prim, E, K, SIZE, 3.0)
    assert len(s) > 20
    check_samples(prim, E, s)
    steps = np.linalg.norm(np.diff(s.uv, axis=0), axis=1)
    assert np.median(steps) == pytest.approx(3.0, abs=0.01)


def test_occlusion_and_behind_camera():
    back = sphere(0.3)
    E_back = translation((0.0, 0.0, 3.0))
    alone = sample_contour(back, E_back, K, SIZE, 2.0)
    front = ClippedQuadric(sphere(0.2))
    E_front = translation((0.1, 0.0, 1.5))
    hidden = sample_contour(back, E_back, K, SIZE, 2.0, occluders=[(front, E_front)])
    assert 0 < len(hidden) < len(alone)
    # the removed samples are those whose rays hit the front sphere
    rays = rays_of(alone.uv)
    c = E_front[:3, 3]
    proj = rays @ c
    miss = np.linalg.norm(c - proj[:, None] * rays, axis=1) > 0.2
    assert len(hidden) == int(miss.sum())
    # an occluder behind does not hide anything; the sampled quadric itself does not hide its own outline
    farther = ClippedQuadric(sphere(0.2))
    same = sample_contour(
        back,
        E_back,
        K,
        SIZE,
        2.0,
        occluders=[(farther, translation((0.1, 0, 6.0))), (ClippedQuadric(back), E_back)],
    )
    assert len(same) == len(alone)
    assert len(sample_contour(back, translation((0.0, 0.0, -3.0)), K, SIZE, 2.0)) == 0
