"""Sensor error models made measurable: IMU Allan deviation with its noise terms, LiDAR range
bias and noise, encoder quantisation. Rates rad/s, accelerations m/s^2, ranges m, times s.

Allan deviation: overlapping estimator (IEEE Std 952) from the integrated signal, vectorised per
cluster time. Noise terms fitted to the Allan variance as N^2/tau + (0.664 B)^2 + K^2 tau/3
(non-negative least squares, each point weighted by its confidence): N, the white-noise density
(slope -1/2, read at tau = 1 s), B, the bias instability (flat floor / 0.664), K, the rate random
walk (slope +1/2, read at tau = 3 s).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.optimize import nnls

FLICKER_FACTOR = 0.664          # Allan deviation floor of bias instability B: 0.664 B


@dataclass(frozen=True)
class AllanDeviation:
    """Cluster times tau (s), Allan deviation (unit of the input), and the number of
    independent clusters behind each point (T / tau)."""

    tau: NDArray[np.float64]
    adev: NDArray[np.float64]
    clusters: NDArray[np.float64]


@dataclass(frozen=True)
class NoiseTerms:
    """N (unit/sqrt(Hz)), B (unit) and K (unit x sqrt(Hz)) with, for each, None when the data
    cannot show it and the reason in notes."""

    n: float | None
    b: float | None
    k: float | None
    notes: tuple[str, ...]


def allan_deviation(values: ArrayLike, rate_hz: float, points_per_decade: int = 10,
                    min_clusters: int = 3) -> AllanDeviation:
    """Overlapping Allan deviation of evenly sampled values (N,) at rate_hz, at log-spaced
    cluster sizes up to N / min_clusters samples (cluster starts every max(1, m // 16)
    samples)."""
    y = np.asarray(values, dtype=float).ravel()
    n = y.size
    if n < 3 * min_clusters:
        raise ValueError(f'{n} samples are too few for an Allan deviation')
    dt = 1.0 / rate_hz
    theta = np.concatenate(([0.0], np.cumsum(y - y.mean()))) * dt
    max_m = n // min_clusters
    m = np.unique(
        np.round(
            np.logspace(0, math.log10(max_m), int(math.log10(max_m) * points_per_decade) + 1)
        ).astype(int)
    )
    m = m[(m >= 1) & (2 * m < n)]
    adev = np.empty(m.size)
    for i, mi in enumerate(m):
        # Cluster starts every mi // 16 samples: overlapping clusters closer than that add
        # almost no information and only cost time at long tau.
        stride = max(1, mi // 16)
        d = theta[2 * mi::stride] - 2.0 * theta[mi:-mi:stride] + theta[:-2 * mi:stride]
        tau = mi * dt
        adev[i] = math.sqrt(float(d @ d) / (2.0 * tau * tau * d.size))
    tau = m * dt
    return AllanDeviation(tau, adev, n * dt / tau)


def fit_noise_terms(ad: AllanDeviation, min_share: float = 0.5,
                    min_clusters: float = 9.0) -> NoiseTerms:
    """N, B, K from an Allan deviation (see the module doc). A term is reported only where it
    makes up at least min_share of the fitted variance at some tau with at least min_clusters
    independent clusters (a trustworthy point); else it is None with the reason."""
    tau, avar = ad.tau, ad.adev ** 2
    trusted = ad.clusters >= min_clusters
    design = np.column_stack((1.0 / tau, np.full(tau.size, FLICKER_FACTOR ** 2), tau / 3.0))
    # Relative uncertainty of an Allan variance point ~ 1/sqrt(clusters): weight accordingly.
    weight = np.sqrt(np.maximum(ad.clusters - 1.0, 1.0)) / avar
    coef, _ = nnls(design[trusted] * weight[trusted, None], avar[trusted] * weight[trusted])
    parts = design * coef
    share = parts / np.maximum(parts.sum(axis=1, keepdims=True), 1e-300)
    names = ('white noise N (slope -1/2)', 'bias instability B (flat)',
             'rate random walk K (slope +1/2)')
    values: list[float | None] = []
    notes: list[str] = []
    longest = float(tau[trusted].max()) if trusted.any() else 0.0
    for i, name in enumerate(names):
        shown = trusted & (share[:, i] >= min_share)
        if coef[i] > 0.0 and shown.any():
            values.append(float(math.sqrt(coef[i])))
        else:
            values.append(None)
            notes.append(f'{name}: not visible up to tau = {longest:.3g} s (the longest cluster '
                         f'time with {min_clusters:g} independent clusters)')
    return NoiseTerms(values[0], values[1], values[2], tuple(notes))


@dataclass(frozen=True)
class RangeErrors:
    """Range residuals m - v (m): bias (mean), sigma (std), the lesson's accuracy
    1 - |m - v| / v (mean over beams) and precision (sensor span / sigma), from `beams` beams."""

    bias_m: float | None
    sigma_m: float
    accuracy: float | None
    precision: float
    beams: int


def range_errors(measured: ArrayLike, true: ArrayLike, span_m: float,
                 outlier_m: float = 0.2) -> RangeErrors:
    """Statistics of measured against true ranges (m), both finite where used; residuals beyond
    outlier_m (edges, occlusions) are left out."""
    m = np.asarray(measured, dtype=float).ravel()
    v = np.asarray(true, dtype=float).ravel()
    ok = np.isfinite(m) & np.isfinite(v) & (v > 0)
    res = m[ok] - v[ok]
    keep = np.abs(res) <= outlier_m
    if keep.sum() >= 10:
        # Edges and occlusions give a few huge residuals: keep those within 5 robust std.
        centre = np.median(res[keep])
        robust = 1.4826 * np.median(np.abs(res[keep] - centre))
        keep &= np.abs(res - centre) <= 5.0 * max(robust, 1e-6)
    res, v_ok = res[keep], v[ok][keep]
    if res.size < 10:
        raise ValueError(f'only {res.size} beams with a true range')
    sigma = float(res.std(ddof=1))
    return RangeErrors(float(res.mean()), sigma, float(np.mean(1.0 - np.abs(res) / v_ok)),
                       span_m / sigma, int(res.size))


@dataclass(frozen=True)
class EncoderQuantisation:
    """Smallest angle step seen (rad), the counts per revolution it means, and how many
    readings sit on that grid."""

    step_rad: float | None
    counts_per_rev: float | None
    on_grid_fraction: float
    note: str = ''


def encoder_quantisation(positions: ArrayLike, grid_tolerance: float = 0.01
                         ) -> EncoderQuantisation:
    """Quantisation of one wheel's joint positions (rad): the smallest non-zero step between
    readings, checked by how many readings are whole multiples of it."""
    p = np.asarray(positions, dtype=float).ravel()
    steps = np.abs(np.diff(p))
    steps = steps[steps > 1e-12]
    if steps.size < 10:
        return EncoderQuantisation(None, None, 0.0, 'the wheel hardly turns')
    smallest = float(steps.min())
    smallest = float(steps[steps < 1.5 * smallest].mean())
    # The smallest step seen may be several counts: take the largest divisor of it that puts
    # the readings on a grid (a greatest common divisor of the steps).
    on_grid = 0.0
    for divisor in range(1, 17):
        q = smallest / divisor
        units = (p - p[0]) / q
        on_grid = float(np.mean(np.abs(units - np.round(units)) < grid_tolerance))
        if on_grid >= 0.99:
            break
    if on_grid < 0.99:
        return EncoderQuantisation(None, None, on_grid,
                                   'positions are not on a grid: continuous (simulated or '
                                   'interpolated) readings, no quantisation seen')
    return EncoderQuantisation(q, 2.0 * math.pi / q, on_grid)
