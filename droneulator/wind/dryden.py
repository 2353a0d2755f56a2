"""Dryden turbulence at low altitude, as MIL-F-8785C (3.7.2) and MIL-HDBK-1797 define it, and exact
discrete-time filters that give its spectra.

Below 1000 ft the standard defines, with the height ``h`` and the wind 20 ft up ``W20`` in feet and
ft/s (converted here to metres):

* scale lengths ``L_w = h``, ``L_u = L_v = h / (0.177 + 0.000823 h)^1.2``;
* intensities ``sigma_w = 0.1 W20``, ``sigma_u = sigma_v = sigma_w / (0.177 + 0.000823 h)^0.4``;
* spectra in the spatial frequency ``Omega`` (rad/m), met at airspeed ``V`` as ``omega = V Omega``:
  ``Phi_u = sigma_u^2 (2 L_u / pi) / (1 + (L_u Omega)^2)`` and
  ``Phi_v,w = sigma^2 (L / pi) (1 + 3 (L Omega)^2) / (1 + (L Omega)^2)^2``.

The standard's model holds from 10 ft up: lower heights use 10 ft's lengths and intensities.

Filters. In time, with ``T = L / V``, ``u`` is a first-order Gauss-Markov process (autocorrelation
``exp(-|tau| / T)``), sampled exactly by ``x <- a x + sqrt(1 - a^2) n`` with ``a = exp(-dt / T)``.
``v`` and ``w`` have the shape ``(1 + sqrt(3) T s) / (1 + T s)^2``: two equal first-order lags in a
chain, ``x1`` driven by white noise and ``x2`` by ``x1``, read out as ``sqrt(3) x1 + (1 - sqrt(3)) x2``.
That chain is integrated exactly over a step (its transition ``exp(-h) [[1, 0], [h, 1]]`` and the noise
covariance integral in closed form, ``h = dt / T``), so the spectra hold at any step and any ``T``.
All processes here have unit variance; the field scales them by the intensities, so a change of height
or airspeed changes the turbulence without a transient.
"""

from __future__ import annotations

import numpy as np

FT = 0.3048
#: the low-altitude model's range (MIL-F-8785C: 10 ft to 1000 ft)
H_MIN_M = 10.0 * FT
H_MAX_M = 1000.0 * FT
#: the readout of the two-lag chain that gives the lateral and vertical spectra's shape
C1 = np.sqrt(3.0)
C2 = 1.0 - np.sqrt(3.0)
#: the two-lag chain's stationary state covariance at unit output variance
STATIONARY = np.array([[0.5, 0.25], [0.25, 0.25]])


def scale_lengths(h_m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(L_u = L_v, L_w) in metres at heights ``h_m`` (clipped to the model's 10-1000 ft)."""
    h_ft = np.clip(h_m, H_MIN_M, H_MAX_M) / FT
    k = 0.177 + 0.000823 * h_ft
    return h_ft / k**1.2 * FT, h_ft * FT


def intensities(h_m: np.ndarray, w20: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(sigma_u = sigma_v, sigma_w) in m/s at heights ``h_m`` under a wind of ``w20`` m/s 20 ft up."""
    h_ft = np.clip(h_m, H_MIN_M, H_MAX_M) / FT
    sigma_w = 0.1 * np.asarray(w20, dtype=float)
    return sigma_w / (0.177 + 0.000823 * h_ft) ** 0.4, sigma_w


def first_order_step(x: np.ndarray, dt: float, T: np.ndarray, noise: np.ndarray) -> None:
    """Advance unit-variance Gauss-Markov processes ``x`` (in place) by ``dt`` with time constants ``T``;
    ``noise`` is standard normal, shaped like ``x``."""
    a = np.exp(-dt / T)
    x *= a
    x += np.sqrt(-np.expm1(-2.0 * dt / T)) * noise


def second_order_step(x: np.ndarray, dt: float, T: np.ndarray, noise: np.ndarray) -> None:
    """Advance two-lag chains ``x`` (..., 2) (in place) by ``dt`` with time constants ``T`` (...);
    ``noise`` is standard normal, shaped like ``x``. Read out with :func:`second_order_output`."""
    h = dt / T
    e = np.exp(-h)
    e2 = e * e
    x1, x2 = x[..., 0].copy(), x[..., 1]
    x[..., 0] = e * x1
    x[..., 1] = e * (h * x1 + x2)
    # the exact noise covariance over the step, [[I0, I1], [I1, I2]] (unit output variance)
    i0 = -0.5 * np.expm1(-2.0 * h)
    i1 = 0.25 * (1.0 - e2 * (1.0 + 2.0 * h))
    i2 = 0.25 * (1.0 - e2 * (1.0 + 2.0 * h + 2.0 * h * h))
    l11 = np.sqrt(i0)
    l21 = i1 / l11
    l22 = np.sqrt(np.maximum(i2 - l21 * l21, 0.0))
    x[..., 0] += l11 * noise[..., 0]
    x[..., 1] += l21 * noise[..., 0] + l22 * noise[..., 1]


def second_order_output(x: np.ndarray) -> np.ndarray:
    return C1 * x[..., 0] + C2 * x[..., 1]


def stationary_start(rng: np.random.Generator, n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Initial states for ``n`` vehicles drawn from the stationary distribution (no warm-up transient):
    ``u`` (n,), ``v`` and ``w`` (n, 2)."""
    chol = np.linalg.cholesky(STATIONARY)
    u = rng.standard_normal(n)
    v = rng.standard_normal((n, 2)) @ chol.T
    w = rng.standard_normal((n, 2)) @ chol.T
    return u, v, w
