"""Constant-acceleration Kalman filter (ALGORITHMS.md §1, kinematic variant)."""

import numpy as np
import pytest

from artrack.errors import ArtrackError
from artrack.kalman import (
    ConstantAccelerationKF,
    KalmanFilter,
    constant_acceleration_F,
    constant_acceleration_Q,
)


def _trajectory(t: np.ndarray, p0: np.ndarray, v0: np.ndarray, a0: np.ndarray) -> np.ndarray:
    """(T, N, 3) constant-acceleration positions."""
    return p0[None] + v0[None] * t[:, None, None] + 0.5 * a0[None] * t[:, None, None] ** 2


def test_exact_without_noise():
    rng = np.random.default_rng(0)
    n, dt = 4, 1.0 / 30.0
    p0, v0, a0 = rng.normal(size=(n, 3)), rng.normal(size=(n, 3)), rng.normal(size=(n, 3))
    t = np.arange(60) * dt
    truth = _trajectory(t, p0, v0, a0)
    kf = ConstantAccelerationKF(truth[0], position_var=1.0, velocity_var=10.0, acceleration_var=10.0, q=0.0)
    kf.update(truth[0], np.eye(3) * 1e-12)
    for k in range(1, len(t)):
        kf.predict(dt)
        kf.update(truth[k], np.eye(3) * 1e-12)
    np.testing.assert_allclose(kf.position, truth[-1], atol=1e-6)
    v_true = v0 + a0 * t[-1]
    np.testing.assert_allclose(kf.velocity, v_true, atol=1e-4)
    np.testing.assert_allclose(kf.acceleration, a0, atol=1e-2)
    # Zero process noise: the prediction is exact too.
    x_pred, _ = kf.predicted(dt)
    np.testing.assert_allclose(x_pred[:, :3], _trajectory(np.array([t[-1] + dt]), p0, v0, a0)[0], atol=1e-6)


def test_tracks_constant_acceleration_without_lag():
    rng = np.random.default_rng(1)
    n, dt, sigma = 50, 1.0 / 30.0, 0.01
    p0 = rng.normal(size=(n, 3))
    v0 = rng.normal(scale=0.5, size=(n, 3))
    a0 = rng.normal(scale=2.0, size=(n, 3))
    t = np.arange(150) * dt
    truth = _trajectory(t, p0, v0, a0)
    z = truth + rng.normal(scale=sigma, size=truth.shape)
    kf = ConstantAccelerationKF(z[0], position_var=sigma**2, velocity_var=4.0, acceleration_var=25.0, q=1.0)
    errors = []
    for k in range(1, len(t)):
        kf.predict(dt)
        kf.update(z[k], np.eye(3) * sigma**2)
        if k >= 60:
            errors.append(kf.position - truth[k])
    e = np.asarray(errors)  # (T', N, 3)
    bias = e.mean(axis=(0, 1))
    rms = np.sqrt(np.mean(e**2))
    # A lagging (e.g. constant-velocity) filter has a bias along the acceleration.
    assert np.all(np.abs(bias) < 3 * sigma / np.sqrt(e.shape[0] * e.shape[1]) + 1e-3)
    assert rms < sigma  # filtering reduces the noise, no lag
    lag = np.mean(np.sum(e * a0[None], axis=-1)) / np.mean(np.linalg.norm(a0, axis=-1))
    assert abs(lag) < 1e-3
    # Posterior covariance is consistent with the actual error (within a factor ~2).
    pred_var = np.mean(np.trace(kf.position_cov(), axis1=1, axis2=2)) / 3
    assert 0.25 < np.mean(e**2) / pred_var < 4.0


def test_mask_keeps_prediction_and_grows_covariance():
    kf = ConstantAccelerationKF(np.zeros((2, 3)), q=1.0)
    kf.predict(0.1)
    P_prior = kf.P_prior.copy()
    kf.update(np.array([[1.0, 1.0, 1.0], [np.nan, np.nan, np.nan]]), np.eye(3) * 1e-4, mask=[True, False])
    np.testing.assert_allclose(kf.x_post[1], kf.x_prior[1])
    np.testing.assert_allclose(kf.P_post[1], P_prior[1])
    assert np.trace(kf.P_post[0]) < np.trace(P_prior[0])
    kf.predict(0.1)
    assert np.trace(kf.position_cov(prior=True)[1]) > np.trace(P_prior[1][:3, :3])


def test_matrices():
    F = constant_acceleration_F(0.5, dim=1)
    np.testing.assert_allclose(F, [[1, 0.5, 0.125], [0, 1, 0.5], [0, 0, 1]])
    Q = constant_acceleration_Q(0.5, np.array([1.0, 2.0]), dim=3)
    assert Q.shape == (2, 9, 9)
    np.testing.assert_allclose(Q[1], 2 * Q[0])
    assert np.all(np.linalg.eigvalsh(Q[0]) > -1e-12)


def test_dimension_errors():
    kf = ConstantAccelerationKF(np.zeros((3, 3)))
    with pytest.raises(ValueError, match="z has shape"):
        kf.update(np.zeros((2, 3)), np.eye(3))
    with pytest.raises(ValueError, match="R has shape"):
        kf.update(np.zeros((3, 3)), np.eye(2))
    with pytest.raises(ValueError, match="mask"):
        kf.update(np.zeros((3, 3)), np.eye(3), mask=[True])
    with pytest.raises(ValueError, match="dt"):
        kf.predict(-1.0)
    with pytest.raises(ArtrackError):
        kf.predict_with(np.eye(8), np.eye(9))
    with pytest.raises(ValueError, match="H has shape"):
        KalmanFilter(np.zeros((1, 2)), np.eye(2)).update_with(np.zeros((1, 1)), np.eye(1), np.eye(3))
    with pytest.raises(ValueError, match="x0"):
        KalmanFilter(np.zeros(3), np.eye(3))


def test_generic_filter_matches_scalar_textbook():
    # One scalar random-walk filter: closed-form gain K = P/(P+R).
    kf = KalmanFilter(np.array([[0.0]]), np.array([[[4.0]]]))
    kf.predict_with(np.eye(1), np.eye(1))
    kf.update_with(np.array([[10.0]]), np.array([[1.0]]), np.eye(1))
    assert kf.K[0, 0, 0] == pytest.approx(5.0 / 6.0)
    assert kf.x_post[0, 0] == pytest.approx(50.0 / 6.0)
    assert kf.P_post[0, 0, 0] == pytest.approx(5.0 / 6.0)


def test_projection_moves_velocity_with_position():
    """Write-back of the constraint solver's result (ALGORITHMS.md §1) by estimate projection:
    the position is set exactly and the velocity moves through its covariance with the
    position, x ← x + P Hᵀ (H P Hᵀ)⁻¹ (d − H x); P is kept. A position-only overwrite would
    leave the velocity to integrate every correction as motion."""
    kf = ConstantAccelerationKF(np.zeros((2, 3)), 0.01, 1.0, 10.0, q=10.0)
    for k in range(5):
        kf.predict(0.1)
        kf.update(np.full((2, 3), 0.05 * (k + 1)), np.eye(3) * 1e-3)
    x, P = kf.x.copy(), kf.P.copy()
    target = x[:, :3] + np.array([0.02, -0.01, 0.03])
    kf.project_position(target, mask=np.array([True, False]))
    np.testing.assert_allclose(kf.position[0], target[0], atol=1e-12)
    np.testing.assert_array_equal(kf.x[1], x[1])
    expected_v = x[0, 3:6] + P[0, 3:6, :3] @ np.linalg.solve(P[0, :3, :3], target[0] - x[0, :3])
    np.testing.assert_allclose(kf.velocity[0], expected_v, atol=1e-12)
    assert np.linalg.norm(kf.velocity[0] - x[0, 3:6]) > 1e-3  # the velocity did move
    np.testing.assert_array_equal(kf.P, P)
