"""SE(3) exp / log / adjoint (ALGORITHMS.md §2 "Representation"): property and finite-difference tests."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.linalg import expm
from scipy.spatial.transform import Rotation

from artrack.lie import GENERATORS, adjoint, cross, exp_se3, hat, inverse_se3, log_se3, make_se3, skew, vee


def random_poses(rng: np.random.Generator, n: int) -> np.ndarray:
    return make_se3(Rotation.random(n, random_state=rng).as_matrix(), rng.normal(size=(n, 3)))


def test_generators_and_hat_vee():
    rng = np.random.default_rng(0)
    xi = rng.normal(size=(5, 6))
    assert np.allclose(hat(xi), np.einsum("nj,jab->nab", xi, GENERATORS))
    assert np.allclose(vee(hat(xi)), xi)
    w, p = rng.normal(size=3), rng.normal(size=3)
    assert np.allclose(skew(w) @ p, np.cross(w, p))


def test_exp_matches_matrix_exponential_including_small_angles():
    rng = np.random.default_rng(1)
    xis = rng.normal(size=(20, 6))
    for scale in (1e-9, 1e-5, 9e-5, 1.1e-4, 1e-2, 1.0, 3.0):
        x = xis * scale / np.maximum(np.linalg.norm(xis[:, 3:], axis=1, keepdims=True), 1e-12)
        E = exp_se3(x)
        ref = np.stack([expm(h) for h in hat(x)])
        assert np.allclose(E, ref, atol=1e-12, rtol=1e-10), scale


def test_exp_log_round_trips_batched():
    rng = np.random.default_rng(2)
    E = random_poses(rng, 200).reshape(10, 20, 4, 4)
    assert np.allclose(exp_se3(log_se3(E)), E, atol=1e-10)
    xi = rng.normal(size=(4, 50, 6))
    xi[..., 3:] *= 3.0 / np.maximum(np.linalg.norm(xi[..., 3:], axis=-1, keepdims=True), 3.0)  # |w| < pi
    assert np.allclose(log_se3(exp_se3(xi)), xi, atol=1e-9)
    tiny = rng.normal(size=(5, 6)) * 1e-7
    assert np.allclose(log_se3(exp_se3(tiny)), tiny, atol=1e-15)
    near_pi = np.r_[0.3, -0.2, 0.5, 0.0, 0.0, np.pi - 1e-6]
    assert np.allclose(exp_se3(log_se3(exp_se3(near_pi))), exp_se3(near_pi), atol=1e-9)


def test_inverse():
    rng = np.random.default_rng(3)
    E = random_poses(rng, 30)
    assert np.allclose(inverse_se3(E) @ E, np.eye(4), atol=1e-12)


def test_adjoint_properties():
    rng = np.random.default_rng(4)
    A, B = random_poses(rng, 25), random_poses(rng, 25)
    assert np.allclose(adjoint(A @ B), adjoint(A) @ adjoint(B), atol=1e-12)
    assert np.allclose(adjoint(inverse_se3(A)), np.linalg.inv(adjoint(A)), atol=1e-10)
    xi = rng.normal(size=(25, 6)) * 0.5
    lhs = A @ exp_se3(xi) @ inverse_se3(A)
    rhs = exp_se3(np.einsum("nij,nj->ni", adjoint(A), xi))
    assert np.allclose(lhs, rhs, atol=1e-10)


def test_finite_differences_of_exp_and_point_velocity():
    rng = np.random.default_rng(5)
    h = 1e-6
    for j in range(6):
        e = np.zeros(6)
        e[j] = 1.0
        d = (exp_se3(h * e) - exp_se3(-h * e)) / (2 * h)
        assert np.allclose(d, GENERATORS[j], atol=1e-8)
    xi, p = rng.normal(size=6), rng.normal(size=3)
    ph = np.r_[p, 1.0]
    vel = ((exp_se3(h * xi) @ ph - exp_se3(-h * xi) @ ph) / (2 * h))[:3]
    assert np.allclose(vel, xi[:3] + np.cross(xi[3:], p), atol=1e-7)  # v + w x p
    # derivative of E exp(t xi) E^-1 at 0 is hat(Ad(E) xi)
    E = random_poses(rng, 1)[0]
    d = (E @ exp_se3(h * xi) @ inverse_se3(E) - E @ exp_se3(-h * xi) @ inverse_se3(E)) / (2 * h)
    assert np.allclose(vee(d), adjoint(E) @ xi, atol=1e-7)


def test_bad_shapes_raise():
    with pytest.raises(ValueError):
        exp_se3(np.zeros(5))
    with pytest.raises(ValueError):
        log_se3(np.eye(3))


def test_cross_equals_numpy_and_broadcasts():
    rng = np.random.default_rng(4)
    a, b = rng.normal(size=(5, 1, 3)), rng.normal(size=(1, 7, 3))
    np.testing.assert_allclose(cross(a, b), np.cross(a, b), atol=1e-15)
    np.testing.assert_allclose(skew(a[:, 0]) @ b[0, 0], np.cross(a[:, 0], b[0, 0]), atol=1e-15)
