"""Linear Kalman filters, batched: one independent filter per tracked point.

ALGORITHMS.md §1, "The cheaper variant the paper settled on": one linear
Kalman filter per link with a constant-acceleration model (the paper's
Equation 7, ``x_t = Φ x_{t-1} + w``), standard predict / update:

    predict   x_prior = F x_post            P_prior = F P_post Fᵀ + Q
    update    K = P_prior Hᵀ (H P_prior Hᵀ + R)⁻¹
              x_post = x_prior + K (z − H x_prior)
              P_post = (I − K H) P_prior (I − K H)ᵀ + K R Kᵀ     (Joseph form)

Textbook names are kept (x, P, F, H, Q, R, K; ``x_prior``/``P_prior`` after
predict and ``x_post``/``P_post`` after update). Note: the paper (and Gelb)
call the process-noise covariance R; here Q is the process noise and R the
measurement noise, as in most modern texts.

Everything is vectorised over a batch of N independent filters (N links or
blobs), so x has shape (N, n) and P (N, n, n). ``ConstantAccelerationKF``
builds F and Q for a state ``[p (d), v (d), a (d)]`` per filter (d = 3 for
3-D points), with the white-jerk ("continuous Wiener-process acceleration")
process noise of spectral density ``q`` (m²/s⁵) per filter.

The norm of the position block of ``P_prior`` is the confidence the paper
feeds to the inverse observation model (ALGORITHMS.md §1, feedback
projection); ``position_cov(prior=True)`` exposes it.
"""

from __future__ import annotations

import numpy as np

from .errors import InputError


class KalmanDimensionError(InputError, ValueError):
    """An array handed to a filter has the wrong shape (names the argument)."""


def _check_shape(name: str, array: np.ndarray, shape: tuple[int, ...]) -> np.ndarray:
    a = np.asarray(array, dtype=float)
    if a.shape != shape:
        raise KalmanDimensionError(f"kalman: {name} has shape {a.shape}, expected {shape}")
    if not np.all(np.isfinite(a)):
        raise KalmanDimensionError(f"kalman: {name} contains non-finite values")
    return a


def _broadcast_batch(name: str, array: np.ndarray, n_batch: int, shape: tuple[int, ...]) -> np.ndarray:
    """Accept ``shape`` (shared by the batch) or ``(n_batch, *shape)``; return the latter."""
    a = np.asarray(array, dtype=float)
    if a.shape == shape:
        a = np.broadcast_to(a, (n_batch, *shape))
    return _check_shape(name, a, (n_batch, *shape)).copy()


class KalmanFilter:
    """A batch of N independent linear Kalman filters with state size n.

    x: (N, n) state mean; P: (N, n, n) state covariance. After ``predict``
    the attributes ``x_prior``, ``P_prior`` (and ``F``, ``Q``) hold the
    prediction; after ``update`` ``x_post``, ``P_post``, ``K``, ``H``, ``R``,
    ``innovation`` and ``S`` (innovation covariance) hold the correction.
    ``x`` / ``P`` always refer to the latest of the two.
    """

    def __init__(self, x0: np.ndarray, P0: np.ndarray):
        x0 = np.asarray(x0, dtype=float)
        if x0.ndim != 2:
            raise KalmanDimensionError(f"kalman: x0 has shape {x0.shape}, expected (N, n)")
        self.n_batch, self.n_state = x0.shape
        self.x_post = _check_shape("x0", x0, x0.shape).copy()
        self.P_post = _broadcast_batch("P0", P0, self.n_batch, (self.n_state, self.n_state))
        self.x_prior = self.x_post.copy()
        self.P_prior = self.P_post.copy()
        self.x = self.x_post
        self.P = self.P_post
        self.F: np.ndarray | None = None
        self.Q: np.ndarray | None = None
        self.H: np.ndarray | None = None
        self.R: np.ndarray | None = None
        self.K: np.ndarray | None = None
        self.S: np.ndarray | None = None
        self.innovation: np.ndarray | None = None

    # ------------------------------------------------------------------ predict
    def propagate(self, F: np.ndarray, Q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Prediction without changing the filter: returns (x (N, n), P (N, n, n)).

        F: (n, n) or (N, n, n) state transition; Q: (n, n) or (N, n, n)
        process-noise covariance.
        """
        F = _broadcast_batch("F", F, self.n_batch, (self.n_state, self.n_state))
        Q = _broadcast_batch("Q", Q, self.n_batch, (self.n_state, self.n_state))
        x = np.einsum("nij,nj->ni", F, self.x)
        P = F @ self.P @ np.swapaxes(F, 1, 2) + Q
        return x, 0.5 * (P + np.swapaxes(P, 1, 2))

    def predict_with(self, F: np.ndarray, Q: np.ndarray) -> None:
        """Time update ``x_prior = F x``, ``P_prior = F P Fᵀ + Q`` (shapes as in ``propagate``)."""
        self.x_prior, self.P_prior = self.propagate(F, Q)
        self.F = _broadcast_batch("F", F, self.n_batch, (self.n_state, self.n_state))
        self.Q = _broadcast_batch("Q", Q, self.n_batch, (self.n_state, self.n_state))
        self.x, self.P = self.x_prior, self.P_prior

    def inflate_prior(self, i: int, scale: float) -> None:
        """Count the last step's process noise ``scale`` times in filter ``i``'s prior (adaptive
        process noise, Bar-Shalom, Li and Kirubarajan 2001, §11.2): ``P_prior[i] += (scale − 1) Q[i]``.
        Between a predict and the update that follows it."""
        self.P_prior[i] = self.P_prior[i] + (scale - 1.0) * self.Q[i]
        self.P = self.P_prior

    # ------------------------------------------------------------------- update
    def update_with(
        self,
        z: np.ndarray,
        R: np.ndarray,
        H: np.ndarray,
        mask: np.ndarray | None = None,
    ) -> None:
        """Measurement update of the filters selected by ``mask``.

        z: (N, m) measurements; R: (m, m) or (N, m, m) measurement-noise
        covariance; H: (m, n) or (N, m, n) measurement matrix; mask: (N,)
        bool, True where a measurement is available (the paper's
        time-varying H: unobserved filters keep their prediction).
        Rows of z/R for masked-out filters are ignored (may be NaN).
        """
        H = np.asarray(H, dtype=float)
        m = H.shape[-2] if H.ndim >= 2 else -1
        if H.ndim not in (2, 3) or H.shape[-1] != self.n_state:
            raise KalmanDimensionError(
                f"kalman: H has shape {H.shape}, expected (m, {self.n_state}) or (N, m, {self.n_state})"
            )
        H = _broadcast_batch("H", H, self.n_batch, (m, self.n_state))
        if mask is None:
            mask = np.ones(self.n_batch, dtype=bool)
        mask = np.asarray(mask, dtype=bool)
        if mask.shape != (self.n_batch,):
            raise KalmanDimensionError(f"kalman: mask has shape {mask.shape}, expected ({self.n_batch},)")
        z = np.asarray(z, dtype=float)
        if z.shape != (self.n_batch, m):
            raise KalmanDimensionError(f"kalman: z has shape {z.shape}, expected ({self.n_batch}, {m})")
        R = np.asarray(R, dtype=float)
        if R.shape == (m, m):
            R = np.broadcast_to(R, (self.n_batch, m, m))
        if R.shape != (self.n_batch, m, m):
            raise KalmanDimensionError(
                f"kalman: R has shape {R.shape}, expected ({m}, {m}) or ({self.n_batch}, {m}, {m})"
            )
        R = R.copy()
        if not (np.all(np.isfinite(z[mask])) and np.all(np.isfinite(R[mask]))):
            raise KalmanDimensionError("kalman: z or R contains non-finite values for an observed filter")

        x_prior, P_prior = self.x, self.P
        x_post, P_post = x_prior.copy(), P_prior.copy()
        K = np.zeros((self.n_batch, self.n_state, m))
        S = np.zeros((self.n_batch, m, m))
        innovation = np.zeros((self.n_batch, m))
        idx = np.flatnonzero(mask)
        if idx.size:
            Hs, Ps, Rs = H[idx], P_prior[idx], R[idx]
            Ht = np.swapaxes(Hs, 1, 2)
            Ss = Hs @ Ps @ Ht + Rs
            Ss = 0.5 * (Ss + np.swapaxes(Ss, 1, 2))
            # K = P Hᵀ S⁻¹  computed as (S⁻¹ H P)ᵀ (S, P symmetric).
            Ks = np.swapaxes(np.linalg.solve(Ss, Hs @ Ps), 1, 2)
            y = z[idx] - np.einsum("nij,nj->ni", Hs, x_prior[idx])
            x_post[idx] = x_prior[idx] + np.einsum("nij,nj->ni", Ks, y)
            IKH = np.eye(self.n_state) - Ks @ Hs
            Pn = IKH @ Ps @ np.swapaxes(IKH, 1, 2) + Ks @ Rs @ np.swapaxes(Ks, 1, 2)
            P_post[idx] = 0.5 * (Pn + np.swapaxes(Pn, 1, 2))
            K[idx], S[idx], innovation[idx] = Ks, Ss, y
        self.H, self.R, self.K, self.S, self.innovation = H, R, K, S, innovation
        self.x_post, self.P_post = x_post, P_post
        self.x, self.P = x_post, P_post

    def set_state(self, x: np.ndarray, P: np.ndarray | None = None, mask: np.ndarray | None = None) -> None:
        """Overwrite the current (posterior) state of the filters in ``mask``.

        Used to write the constraint solver's globally consistent answer back
        into the filters (ALGORITHMS.md §1: "the result is written back as the
        filters' new state"). x: (N, n); P: (N, n, n) or None (keep P).
        """
        x = _check_shape("x", np.asarray(x, dtype=float), (self.n_batch, self.n_state))
        if mask is None:
            mask = np.ones(self.n_batch, dtype=bool)
        mask = np.asarray(mask, dtype=bool)
        self.x_post = self.x.copy()
        self.x_post[mask] = x[mask]
        self.P_post = self.P.copy()
        if P is not None:
            P = _check_shape("P", np.asarray(P, dtype=float), (self.n_batch, self.n_state, self.n_state))
            self.P_post[mask] = P[mask]
        self.x, self.P = self.x_post, self.P_post


    def project(self, d: np.ndarray, H: np.ndarray, mask: np.ndarray | None = None) -> None:
        """Constrain the current state to ``H x = d`` by estimate projection (ALGORITHMS.md §1,
        "the result is written back as the filters' new state").

        ``x ← x + P Hᵀ (H P Hᵀ)⁻¹ (d − H x)``: the P⁻¹-weighted least change of the whole
        state that satisfies the constraint (Simon & Chia's estimate projection), so that
        writing back a position also moves the velocity and acceleration through their
        cross-covariance with it, exactly as a noise-free measurement would. Overwriting
        the position alone (``set_state``) instead leaves the velocity to integrate every
        position correction as if it were motion. P is kept (the constraint is derived from
        the filters' own estimates, not new information). d: (N, m); H: (m, n) or (N, m, n);
        mask: (N,) bool, filters to constrain (default all).
        """
        H = np.asarray(H, dtype=float)
        if H.ndim not in (2, 3) or H.shape[-1] != self.n_state:
            raise KalmanDimensionError(
                f"kalman: H has shape {H.shape}, expected (m, {self.n_state}) or (N, m, {self.n_state})"
            )
        m = H.shape[-2]
        H = _broadcast_batch("H", H, self.n_batch, (m, self.n_state))
        d = _check_shape("d", np.asarray(d, dtype=float), (self.n_batch, m))
        if mask is None:
            mask = np.ones(self.n_batch, dtype=bool)
        mask = np.asarray(mask, dtype=bool)
        if mask.shape != (self.n_batch,):
            raise KalmanDimensionError(f"kalman: mask has shape {mask.shape}, expected ({self.n_batch},)")
        x = self.x.copy()
        idx = np.flatnonzero(mask)
        if idx.size:
            Hs, Ps = H[idx], self.P[idx]
            PHt = Ps @ np.swapaxes(Hs, 1, 2)
            r = d[idx] - np.einsum("nij,nj->ni", Hs, x[idx])
            x[idx] += np.einsum("nij,nj->ni", PHt, np.linalg.solve(Hs @ PHt, r[..., None])[..., 0])
        self.x_post, self.P_post = x, self.P.copy()
        self.x, self.P = self.x_post, self.P_post


def constant_acceleration_F(dt: float, dim: int = 3) -> np.ndarray:
    """(3 dim, 3 dim) transition of the state [p (dim), v (dim), a (dim)] over dt seconds."""
    f = np.array([[1.0, dt, 0.5 * dt * dt], [0.0, 1.0, dt], [0.0, 0.0, 1.0]])
    return np.kron(f, np.eye(dim))


def constant_acceleration_Q(dt: float, q: float | np.ndarray, dim: int = 3) -> np.ndarray:
    """White-jerk process noise for [p, v, a] over dt seconds.

    q: scalar or (N,) jerk spectral density, m²/s⁵. Returns (3 dim, 3 dim)
    for scalar q, else (N, 3 dim, 3 dim).
    """
    dt = float(dt)
    base = np.array(
        [
            [dt**5 / 20.0, dt**4 / 8.0, dt**3 / 6.0],
            [dt**4 / 8.0, dt**3 / 3.0, dt**2 / 2.0],
            [dt**3 / 6.0, dt**2 / 2.0, dt],
        ]
    )
    Q1 = np.kron(base, np.eye(dim))
    q = np.asarray(q, dtype=float)
    if q.ndim == 0:
        return float(q) * Q1
    return q[:, None, None] * Q1[None]


class ConstantAccelerationKF(KalmanFilter):
    """N independent constant-acceleration filters on d-dimensional points.

    State per filter: ``[p (d), v (d), a (d)]`` (m, m/s, m/s²); measurement
    the position p (``H = [I 0 0]``). ``q``: scalar or (N,) jerk spectral
    density (m²/s⁵) of the process noise.
    """

    def __init__(
        self,
        positions: np.ndarray,
        position_var: float | np.ndarray = 1e-2,
        velocity_var: float = 1.0,
        acceleration_var: float = 10.0,
        q: float | np.ndarray = 10.0,
    ):
        positions = np.asarray(positions, dtype=float)
        if positions.ndim != 2:
            raise KalmanDimensionError(f"kalman: positions has shape {positions.shape}, expected (N, d)")
        n, d = positions.shape
        self.dim = d
        x0 = np.zeros((n, 3 * d))
        x0[:, :d] = positions
        pv = np.broadcast_to(np.asarray(position_var, dtype=float), (n,))
        P0 = np.zeros((n, 3 * d, 3 * d))
        idx = np.arange(d)
        P0[:, idx, idx] = pv[:, None]
        P0[:, d + idx, d + idx] = velocity_var
        P0[:, 2 * d + idx, 2 * d + idx] = acceleration_var
        super().__init__(x0, P0)
        q = np.asarray(q, dtype=float)
        if q.ndim not in (0, 1) or (q.ndim == 1 and q.shape != (n,)):
            raise KalmanDimensionError(f"kalman: q has shape {q.shape}, expected () or ({n},)")
        self.q = q
        self.H = np.kron(np.array([[1.0, 0.0, 0.0]]), np.eye(d))

    def transition(self, dt: float) -> tuple[np.ndarray, np.ndarray]:
        """(F (n, n), Q (n, n) or (N, n, n)) for a step of dt seconds (dt ≥ 0)."""
        if not np.isfinite(dt) or dt < 0.0:
            raise KalmanDimensionError(f"kalman: dt must be finite and >= 0, got {dt}")
        return constant_acceleration_F(dt, self.dim), constant_acceleration_Q(dt, self.q, self.dim)

    def predict(self, dt: float) -> None:
        """Time update by dt seconds (sets x_prior, P_prior)."""
        F, Q = self.transition(dt)
        self.predict_with(F, Q)

    def predicted(self, dt: float) -> tuple[np.ndarray, np.ndarray]:
        """Prediction dt seconds ahead without changing the filter: (x (N, n), P (N, n, n))."""
        F, Q = self.transition(dt)
        return self.propagate(F, Q)

    def update(self, z: np.ndarray, R: np.ndarray, mask: np.ndarray | None = None) -> None:
        """Measurement update with positions z: (N, d); R: (d, d) or (N, d, d) m²; mask: (N,) bool."""
        H = np.kron(np.array([[1.0, 0.0, 0.0]]), np.eye(self.dim))
        self.update_with(z, R, H, mask)

    def project_position(self, positions: np.ndarray, mask: np.ndarray | None = None) -> None:
        """Constrain the positions to ``positions`` (N, d) by estimate projection (``project``):
        velocity and acceleration move with them through the covariance."""
        self.project(positions, np.kron(np.array([[1.0, 0.0, 0.0]]), np.eye(self.dim)), mask)

    # ---------------------------------------------------------------- accessors
    @property
    def position(self) -> np.ndarray:
        """(N, d) current position estimate, m."""
        return self.x[:, : self.dim]

    @property
    def velocity(self) -> np.ndarray:
        """(N, d) current velocity estimate, m/s."""
        return self.x[:, self.dim : 2 * self.dim]

    @property
    def acceleration(self) -> np.ndarray:
        """(N, d) current acceleration estimate, m/s²."""
        return self.x[:, 2 * self.dim :]

    def position_cov(self, prior: bool = False) -> np.ndarray:
        """(N, d, d) position covariance of the posterior (or of the prior), m²."""
        P = self.P_prior if prior else self.P
        return P[:, : self.dim, : self.dim]
