"""Edge search, measurement Jacobian and robust motion statistics (ALGORITHMS.md §2 "Measurements",
"Robust statistics by re-weighting")."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from artrack.edges import jacobian_rows, motion_statistics, normal_search, robust_weights
from artrack.lie import GeometryError, exp_se3, make_se3
from artrack.quadrics import ClippedQuadric, cylinder, ellipsoid, sample_contour, slab

K = np.array([[400.0, 0.0, 160.0], [0.0, 400.0, 120.0], [0.0, 0.0, 1.0]])
SIZE = (320, 240)


def fill(img: np.ndarray, poly: np.ndarray, value: int, supersample: int = 8) -> np.ndarray:
    """Fill a sub-pixel polygon (N, 2) (pixel centres at integers) with area anti-aliasing.

    Rendered on a ``supersample`` times finer grid without anti-aliasing and averaged back
    (``cv2.INTER_AREA``): each pixel gets its covered fraction to ~1/supersample.
    (``cv2.fillPoly`` with LINE_AA grows polygons by about half a pixel, which biases edges.)
    """
    s = supersample
    h, w = img.shape
    big = cv2.resize(img, (w * s, h * s), interpolation=cv2.INTER_NEAREST)
    hi = (np.asarray(poly, float) + 0.5) * s - 0.5
    pts = np.round(hi * 16).astype(np.int32).reshape(-1, 1, 2)
    cv2.fillPoly(big, [pts], value, lineType=cv2.LINE_8, shift=4)
    img[:] = cv2.resize(big, (w, h), interpolation=cv2.INTER_AREA)
    return img


def render_cylinder(E: np.ndarray, radius: float, half: float) -> np.ndarray:
    """Grey image of a finite cylinder (axis z, |z| <= half) seen through E.

    Its silhouette is the convex hull of the images of its two end circles."""
    th = np.linspace(0, 2 * np.pi, 720, endpoint=False)
    circ = np.stack([radius * np.cos(th), radius * np.sin(th)], axis=1)
    pts = np.vstack([np.c_[circ, np.full(len(th), z)] for z in (-half, half)])
    X = pts @ E[:3, :3].T + E[:3, 3]
    uv = (X @ K.T)[:, :2] / X[:, 2:3]
    hull = cv2.convexHull(uv.astype(np.float32)).reshape(-1, 2).astype(float)
    img = np.full((SIZE[1], SIZE[0]), 40, np.uint8)
    fill(img, hull, 200)
    return cv2.GaussianBlur(img, (0, 0), 1.0)


def test_normal_search_step_edge_signed_subpixel():
    img = np.full((100, 120), 30, np.uint8)
    fill(img, np.array([[60.3, -5], [200, -5], [200, 200], [60.3, 200]]), 220)  # vertical edge at x = 60.3
    img = cv2.GaussianBlur(img, (0, 0), 0.8)
    pts = np.array([[55.0, 50.0], [65.0, 50.0], [55.0, 30.0], [20.0, 50.0]])
    normals = np.array([[1.0, 0.0], [1.0, 0.0], [-1.0, 0.0], [1.0, 0.0]])
    d, found = normal_search(img, pts, normals, 8.0)
    assert found.tolist() == [True, True, True, False]
    edge_x = 55.0 + d[0]
    assert edge_x == pytest.approx(60.3, abs=0.1)
    assert 65.0 + d[1] == pytest.approx(edge_x, abs=0.05)
    assert d[2] == pytest.approx(-d[0], abs=1e-6)
    assert np.isnan(d[3])  # not found is never a zero distance
    d, found = normal_search(np.full((50, 50), 100, np.uint8), pts[:1] * 0 + 25, normals[:1], 8.0)
    assert not found.any() and np.isnan(d).all()
    # search lines leaving the image do not invent edges at the border
    d, found = normal_search(img, np.array([[2.0, 50.0]]), np.array([[-1.0, 0.0]]), 10.0)
    assert not found[0]


def test_normal_search_picks_the_nearest_edge():
    img = np.zeros((40, 100), np.uint8)
    img[:, 30:] = 100
    img[:, 45:] = 250  # second, stronger edge farther away
    img = cv2.GaussianBlur(img, (0, 0), 0.7)
    d, found = normal_search(img, np.array([[36.0, 20.0]]), np.array([[1.0, 0.0]]), 15.0)
    assert found[0] and d[0] == pytest.approx(-6.5, abs=0.2)
    d, found = normal_search(img, np.array([[36.0, 20.0]]), np.array([[1.0, 0.0]]), 15.0, select="strongest")
    assert found[0] and d[0] == pytest.approx(8.5, abs=0.2)
    with pytest.raises(GeometryError):
        normal_search(img, np.array([[36.0, 20.0]]), np.array([[1.0, 0.0]]), 15.0, select="best")


def test_normal_search_colour_edge_without_grey_contrast():
    img = np.zeros((40, 100, 3), np.uint8)
    img[:, :50] = (200, 40, 113)  # BGR with nearly the grey level of the right half
    img[:, 50:] = (40, 92, 72)
    grey = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
    assert abs(int(grey[0, 10]) - int(grey[0, 90])) <= 2
    pts, nrm = np.array([[46.3, 20.0]]), np.array([[1.0, 0.0]])
    assert not normal_search(grey, pts, nrm, 8.0)[1][0]
    d, found = normal_search(img, pts, nrm, 8.0)
    assert found[0] and d[0] == pytest.approx(3.2, abs=0.3)


def test_jacobian_rows_match_finite_differences():
    rng = np.random.default_rng(0)
    E = make_se3(exp_se3(np.r_[0, 0, 0, rng.normal(size=3)])[:3, :3], [0.1, -0.05, 1.5])
    P = rng.normal(size=(30, 3)) * 0.1  # component frame
    X = P @ E[:3, :3].T + E[:3, 3]
    n = rng.normal(size=(30, 2))
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    J = jacobian_rows(X, n, K, E)
    h = 1e-6
    for j in range(6):
        e = np.zeros(6)
        e[j] = h

        def image(Ej: np.ndarray) -> np.ndarray:
            Y = P @ Ej[:3, :3].T + Ej[:3, 3]
            return (Y @ K.T)[:, :2] / (Y @ K.T)[:, 2:]

        duv = (image(E @ exp_se3(e)) - image(E @ exp_se3(-e))) / (2 * h)
        assert np.allclose(J[:, j], np.einsum("ni,ni->n", duv, n), rtol=1e-6, atol=1e-5)


def test_cylinder_render_measure_recovers_motion():
    radius, half = 0.05, 0.25
    prim = ClippedQuadric(cylinder(radius), slab(-half, half))
    E0 = make_se3(exp_se3(np.r_[0, 0, 0, 1.3, 0.3, 0.2])[:3, :3], [0.0, 0.0, 0.9])
    # small true motion (~3.6 px RMS in the image), in the four directions a cylinder's outline
    # observes (its axial slide and roll are invisible)
    xi_true = np.r_[0.008, -0.006, 0.0, 0.02, -0.015, 0.0]
    img = render_cylinder(E0 @ exp_se3(xi_true), radius, half)
    s = sample_contour(prim, E0, K, SIZE, 2.0)
    assert len(s) > 150
    d, found = normal_search(img, s.uv, s.normals, 10.0, threshold=10.0)
    assert found.mean() > 0.95
    J = jacobian_rows(s.points_cam, s.normals, K, E0)
    xi_hat, C = motion_statistics(J, d, c_robust=1.0, iterations=3)
    assert np.linalg.matrix_rank(C, tol=1e-6 * np.abs(C).max()) == 4
    assert xi_hat[2] == pytest.approx(0, abs=1e-9) and xi_hat[5] == pytest.approx(0, abs=1e-9)
    motion_px = np.sqrt(np.mean((J @ xi_true) ** 2))
    err_px = np.sqrt(np.mean((J @ (xi_hat - xi_true)) ** 2))
    assert motion_px > 3.0 and err_px < 0.1, (motion_px, err_px)
    err = np.abs(xi_hat - xi_true)
    # depth is only seen through the 36 px apparent width: millimetres, not better
    assert np.all(err[:3] < 0.0015) and np.all(err[3:] < 0.003), err


def _two_ellipsoid_component():
    """A rigid component of two quadrics (full-rank statistics), its pose and its samples."""
    E = make_se3(exp_se3(np.r_[0, 0, 0, 0.4, 0.3, 0.1])[:3, :3], [0.02, -0.01, 1.2])
    a = ClippedQuadric(ellipsoid((0.08, 0.05, 0.12)))
    b = ClippedQuadric(ellipsoid((0.04, 0.04, 0.04), center=(0.0, 0.0, 0.17)))
    pts, nrm = [], []
    for prim, other in ((a, b), (b, a)):
        s = sample_contour(prim, E, K, SIZE, 1.5, occluders=[(other, E)])
        pts.append(s.points_cam)
        nrm.append(s.normals)
    return E, np.vstack(pts), np.vstack(nrm)


def test_reweighting_is_robust_to_30_percent_outliers():
    E, X, n = _two_ellipsoid_component()
    J = jacobian_rows(X, n, K, E)
    assert np.linalg.matrix_rank(J) == 6 and len(J) > 100
    rng = np.random.default_rng(7)
    errs = []

    def err(xi_est: np.ndarray, xi_true: np.ndarray) -> float:  # RMS image error of the motion, px
        return float(np.sqrt(np.mean((J @ (xi_est - xi_true)) ** 2)))

    for _ in range(30):
        xi_true = rng.normal(size=6) * np.r_[0.005, 0.005, 0.005, 0.02, 0.02, 0.02]
        m = J @ xi_true + rng.normal(0.0, 0.3, len(J))
        clean = motion_statistics(J, m, iterations=0)[0]
        bad = m.copy()
        idx = rng.choice(len(m), int(round(0.3 * len(m))), replace=False)
        bad[idx] = rng.uniform(-10.0, 10.0, len(idx))
        plain = motion_statistics(J, bad, iterations=0)[0]
        robust = motion_statistics(J, bad, c_robust=0.5, iterations=10)[0]
        errs.append((err(clean, xi_true), err(plain, xi_true), err(robust, xi_true)))
    e_clean, e_plain, e_robust = np.mean(errs, axis=0)
    assert e_robust < 2.0 * e_clean, (e_clean, e_robust)
    assert e_plain > 2.0 * e_clean, (e_clean, e_plain)


def test_motion_statistics_plain_and_masking():
    rng = np.random.default_rng(3)
    J = rng.normal(size=(40, 6))
    m = J @ rng.normal(size=6) + 0.01 * rng.normal(size=40)
    xi, C = motion_statistics(J, m, iterations=0)
    assert np.allclose(C, J.T @ J)
    assert np.allclose(xi, np.linalg.solve(J.T @ J, J.T @ m))
    m2 = m.copy()
    m2[:5] = np.nan  # edges not found
    xi2, C2 = motion_statistics(J, m2, iterations=0)
    assert np.allclose(C2, J[5:].T @ J[5:])
    xi3, _ = motion_statistics(J, m, iterations=0, valid=np.arange(40) >= 5)
    assert np.allclose(xi2, xi3)
    assert robust_weights(np.array([0.0]), 2.0)[0] == 1.0
    with pytest.raises(ValueError):
        motion_statistics(J, m[:-1])


def test_normal_search_polarity_skips_shading_edges_inside_the_outline():
    """A shaded disc (darker rim, brighter core): searching outwards from inside the core, the nearest
    edge is the shading ring; with the disc's colour cone only the outline (disc inside, background
    outside) counts (ALGORITHMS.md §2 "Measurements", edge polarity)."""
    from artrack.edges import fit_colour_cone

    img = np.zeros((80, 80, 3), np.float32)
    img[:] = (40.0, 160.0, 60.0)  # green background
    yy, xx = np.mgrid[0:80, 0:80]
    r = np.hypot(xx - 40.0, yy - 40.0)
    colour = np.array([60.0, 80.0, 200.0])
    img[r <= 20.0] = 0.6 * colour  # rim
    img[r <= 15.0] = 1.0 * colour  # core: a shading edge at r = 15
    img[:, 70:] = (200.0, 200.0, 40.0)  # a background edge at x = 69.5
    img = cv2.GaussianBlur(img, (0, 0), 0.8)
    pts, nrm = np.array([[53.0, 40.0]]), np.array([[1.0, 0.0]])  # r = 13, searching outwards
    d, found = normal_search(None, pts, nrm, 10.0, colour_image=img, gradients=(
        cv2.Sobel(img, cv2.CV_32F, 1, 0, ksize=3, scale=1 / 8), cv2.Sobel(img, cv2.CV_32F, 0, 1, ksize=3, scale=1 / 8)))
    assert found[0] and abs(d[0] - 2.0) < 0.6  # the shading edge
    inside = img[r <= 19.0]
    cone = fit_colour_cone(inside, margin=10.0)
    model = (np.array([True]), cone.u[None], np.array([cone.s_lo]), np.array([cone.s_hi]), np.array([cone.perp_max]))
    d, found = normal_search(None, pts, nrm, 10.0, colour_image=img, colour_model=model, gradients=(
        cv2.Sobel(img, cv2.CV_32F, 1, 0, ksize=3, scale=1 / 8), cv2.Sobel(img, cv2.CV_32F, 0, 1, ksize=3, scale=1 / 8)))
    assert found[0] and abs(d[0] - 7.0) < 0.6  # the outline at r = 20
    # a background edge (both sides unlike the disc) is not an outline either
    grads = (cv2.Sobel(img, cv2.CV_32F, 1, 0, ksize=3, scale=1 / 8),
             cv2.Sobel(img, cv2.CV_32F, 0, 1, ksize=3, scale=1 / 8))
    assert normal_search(None, np.array([[67.0, 40.0]]), nrm, 5.0, gradients=grads)[1][0]
    assert not normal_search(None, np.array([[67.0, 40.0]]), nrm, 5.0, colour_image=img, colour_model=model,
                             gradients=grads)[1][0]
