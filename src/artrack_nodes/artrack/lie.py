"""SE(3) as 4x4 matrices, its Lie algebra se(3) and the adjoint — ALGORITHMS.md §2 "Representation".

Each model component i has a pose ``E_i`` (component -> camera, a 4x4 matrix
``[[R, t], [0, 0, 0, 1]]``). A per-frame motion is ``M = exp(sum_j xi_j G_j)``
with the six generators below and ``E_t = E_{t-1} M_t``; the motion is
expressed in the component's own frame.

Convention (used by every module of §2):

* ``xi = (v, w)``: translation part ``v`` first (3), rotation part ``w`` (3) second;
* generators ``G_1..G_3`` translate along x, y, z; ``G_4..G_6`` rotate about
  x, y, z with the right-hand rule, ``G_{3+k} = [[skew(e_k), 0], [0, 0]]``;
  so a point ``p`` moved by ``exp(t * xi)`` has velocity ``v + w x p`` at t = 0;
* ``adjoint(E)`` is the 6x6 matrix with ``E exp(xi) E^-1 = exp(adjoint(E) xi)``,
  i.e. ``[[R, skew(t) R], [0, R]]``: it re-expresses a motion given in the
  frame E maps *from* in the frame E maps *to*.

All functions are batched over leading dimensions (``(..., 6)``, ``(..., 4, 4)``).
Rotations go through :class:`scipy.spatial.transform.Rotation`.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from artrack.errors import InputError

__all__ = [
    "GENERATORS",
    "GeometryError",
    "adjoint",
    "cross",
    "exp_se3",
    "hat",
    "inverse_se3",
    "log_se3",
    "left_jacobian_so3",
    "make_se3",
    "skew",
    "vee",
]


class GeometryError(InputError, ValueError):
    """Bad input to the §2 geometry / estimation core (lie, quadrics, edges, propagation).

    The message names the function and the argument."""


def skew(w: np.ndarray) -> np.ndarray:
    """Cross-product matrix: ``skew(w) @ p == np.cross(w, p)``. ``w (..., 3)`` -> ``(..., 3, 3)``."""
    w = np.asarray(w, dtype=float)
    out = np.zeros(w.shape[:-1] + (3, 3))
    out[..., 0, 1] = -w[..., 2]
    out[..., 0, 2] = w[..., 1]
    out[..., 1, 0] = w[..., 2]
    out[..., 1, 2] = -w[..., 0]
    out[..., 2, 0] = -w[..., 1]
    out[..., 2, 1] = w[..., 0]
    return out


def cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``a × b`` over the last axis of (..., 3) arrays (broadcast), without ``np.cross``'s per-call
    overhead on small arrays."""
    a = np.asarray(a, dtype=float)
    b = np.asarray(b, dtype=float)
    a0, a1, a2 = a[..., 0], a[..., 1], a[..., 2]
    b0, b1, b2 = b[..., 0], b[..., 1], b[..., 2]
    return np.stack([a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0], axis=-1)


def left_jacobian_so3(r: np.ndarray) -> np.ndarray:
    """Left Jacobian J_l(r) (..., 3, 3) of SO(3) at rotation vectors r (..., 3):
    exp(r + δ) ≈ exp(J_l(r) δ) exp(r); the right Jacobian is ``J_l(-r)``: exp(r + δ) ≈ exp(r) exp(J_l(-r) δ)."""
    r = np.asarray(r, float)
    th2 = np.sum(r * r, axis=-1)
    th = np.sqrt(th2)
    small = th < 1e-6
    ths = np.where(small, 1.0, th)
    a = np.where(small, 0.5 - th2 / 24.0, (1.0 - np.cos(ths)) / ths**2)
    b = np.where(small, 1.0 / 6.0 - th2 / 120.0, (ths - np.sin(ths)) / ths**3)
    K = skew(r)
    return np.eye(3) + a[..., None, None] * K + b[..., None, None] * (K @ K)


def _generators() -> np.ndarray:
    g = np.zeros((6, 4, 4))
    for k in range(3):
        g[k, k, 3] = 1.0
        e = np.zeros(3)
        e[k] = 1.0
        g[3 + k, :3, :3] = skew(e)
    g.setflags(write=False)
    return g


#: The six generators ``G_1..G_6`` of se(3), shape (6, 4, 4): translations x, y, z, then rotations x, y, z.
GENERATORS: np.ndarray = _generators()


def hat(xi: np.ndarray) -> np.ndarray:
    """``sum_j xi_j G_j``: ``xi (..., 6)`` -> ``(..., 4, 4)`` element of se(3)."""
    xi = np.asarray(xi, dtype=float)
    out = np.zeros(xi.shape[:-1] + (4, 4))
    out[..., :3, :3] = skew(xi[..., 3:])
    out[..., :3, 3] = xi[..., :3]
    return out


def vee(X: np.ndarray) -> np.ndarray:
    """Inverse of :func:`hat`: ``(..., 4, 4)`` -> ``(..., 6)`` (the skew part is read, not checked)."""
    X = np.asarray(X, dtype=float)
    return np.concatenate(
        [X[..., :3, 3], np.stack([X[..., 2, 1], X[..., 0, 2], X[..., 1, 0]], axis=-1)], axis=-1
    )


def make_se3(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Assemble ``[[R, t], [0, 1]]`` from ``R (..., 3, 3)`` and ``t (..., 3)`` -> ``(..., 4, 4)``."""
    R = np.asarray(R, dtype=float)
    t = np.asarray(t, dtype=float)
    shape = np.broadcast_shapes(R.shape[:-2], t.shape[:-1])
    out = np.zeros(shape + (4, 4))
    out[..., :3, :3] = R
    out[..., :3, 3] = t
    out[..., 3, 3] = 1.0
    return out


def inverse_se3(E: np.ndarray) -> np.ndarray:
    """Inverse of rigid transforms ``E (..., 4, 4)``: ``[[R^T, -R^T t], [0, 1]]``."""
    E = np.asarray(E, dtype=float)
    Rt = np.swapaxes(E[..., :3, :3], -1, -2)
    return make_se3(Rt, -np.einsum("...ij,...j->...i", Rt, E[..., :3, 3]))


def _rotvec_to_matrix(w: np.ndarray) -> np.ndarray:
    flat = w.reshape(-1, 3)
    return Rotation.from_rotvec(flat).as_matrix().reshape(w.shape[:-1] + (3, 3))


def _matrix_to_rotvec(R: np.ndarray) -> np.ndarray:
    flat = R.reshape(-1, 3, 3)
    return Rotation.from_matrix(flat).as_rotvec().reshape(R.shape[:-2] + (3,))


def _v_coefficients(theta: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``a = (1 - cos t) / t^2`` and ``b = (t - sin t) / t^3`` with Taylor series near 0."""
    small = theta < 1e-4
    t = np.where(small, 1.0, theta)
    t2 = theta * theta
    a = np.where(small, 0.5 - t2 / 24.0 + t2 * t2 / 720.0, (1.0 - np.cos(t)) / (t * t))
    b = np.where(small, 1.0 / 6.0 - t2 / 120.0 + t2 * t2 / 5040.0, (t - np.sin(t)) / (t * t * t))
    return a, b


def exp_se3(xi: np.ndarray) -> np.ndarray:
    """Exponential map ``exp(sum_j xi_j G_j)``: ``xi (..., 6)`` -> ``(..., 4, 4)``.

    Closed form: ``R = exp(skew(w))`` (via scipy), ``t = V v`` with
    ``V = I + a skew(w) + b skew(w)^2``, ``a = (1 - cos t)/t^2``, ``b = (t - sin t)/t^3``, ``t = |w|``.
    """
    xi = np.asarray(xi, dtype=float)
    if xi.shape[-1] != 6:
        raise GeometryError(f"exp_se3: xi must have a last dimension of 6, got shape {xi.shape}")
    v, w = xi[..., :3], xi[..., 3:]
    theta = np.linalg.norm(w, axis=-1)
    a, b = _v_coefficients(theta)
    W = skew(w)
    V = np.eye(3) + a[..., None, None] * W + b[..., None, None] * (W @ W)
    return make_se3(_rotvec_to_matrix(w), np.einsum("...ij,...j->...i", V, v))


def log_se3(E: np.ndarray) -> np.ndarray:
    """Logarithm of rigid transforms: ``E (..., 4, 4)`` -> ``xi (..., 6)`` with ``exp_se3(xi) == E``.

    The rotation angle is in [0, pi]; ``v = V^-1 t`` with
    ``V^-1 = I - skew(w)/2 + (1/t^2) (1 - t sin t / (2 (1 - cos t))) skew(w)^2``.
    """
    E = np.asarray(E, dtype=float)
    if E.shape[-2:] != (4, 4):
        raise GeometryError(f"log_se3: E must have trailing shape (4, 4), got {E.shape}")
    w = _matrix_to_rotvec(E[..., :3, :3])
    theta = np.linalg.norm(w, axis=-1)
    small = theta < 1e-4
    t = np.where(small, 1.0, theta)
    t2 = theta * theta
    c = np.where(
        small,
        1.0 / 12.0 + t2 / 720.0 + t2 * t2 / 30240.0,
        (1.0 - t * np.sin(t) / (2.0 * (1.0 - np.cos(t)))) / (t * t),
    )
    W = skew(w)
    Vinv = np.eye(3) - 0.5 * W + c[..., None, None] * (W @ W)
    return np.concatenate([np.einsum("...ij,...j->...i", Vinv, E[..., :3, 3]), w], axis=-1)


def adjoint(E: np.ndarray) -> np.ndarray:
    """Adjoint representation ``(..., 4, 4)`` -> ``(..., 6, 6)``: ``[[R, skew(t) R], [0, R]]``.

    ``E exp(xi) E^-1 == exp(adjoint(E) @ xi)``; ``adjoint(A @ B) == adjoint(A) @ adjoint(B)``.
    """
    E = np.asarray(E, dtype=float)
    R = E[..., :3, :3]
    out = np.zeros(E.shape[:-2] + (6, 6))
    out[..., :3, :3] = R
    out[..., 3:, 3:] = R
    out[..., :3, 3:] = skew(E[..., :3, 3]) @ R
    return out
