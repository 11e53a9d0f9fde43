"""Speed and accuracy of the Allan deviation: 2 hours of a still 200 Hz IMU (6 axes) from the
simulator's error model, processed as sensing_characterize does (overlapping Allan deviation
and the N/B/K fit per axis): white noise N with bias random walk K (the timed case, 6 axes), and
white noise N with bias instability B. Times are
per CPU second of this process and on the wall clock; nothing is asserted.
"""

from __future__ import annotations

import math
import time

import numpy as np

from sensing_nodes.core.evaluation import characterization as ch
from sensing_nodes.core.sim.simulator import GyroBiasProcess

RATE_HZ = 200.0
N_TRUE = 7.1e-5         # rad/s/sqrt(Hz): sensor_sim's 0.001 rad/s per sample at 200 Hz
K_TRUE = 2.0e-5         # rad/s/sqrt(s)
B_TRUE = 5.0e-5         # rad/s


def _series(n: int, k: float, b: float, seed: int) -> np.ndarray:
    """(n, 3) still gyro samples (rad/s): white noise N_TRUE plus the simulator's bias process."""
    bias = GyroBiasProcess(k, b, 1.0 / RATE_HZ, np.random.default_rng(seed))
    white = np.random.default_rng(seed + 1).standard_normal((n, 3)) * (N_TRUE * math.sqrt(RATE_HZ))
    return white + bias.sample(n)


def _worst(terms, name: str, truth: float) -> float:
    """Largest relative error of a term over the axes (inf when an axis does not show it)."""
    return max(abs(getattr(t, name) / truth - 1.0) if getattr(t, name) else math.inf
               for t in terms)


def run(quick: bool = False) -> dict:
    hours = 0.25 if quick else 2.0
    n = int(hours * 3600 * RATE_HZ)
    gyro = _series(n, K_TRUE, 0.0, seed=3)
    accel = np.random.default_rng(9).standard_normal((n, 3)) * 0.02
    cpu, wall = time.process_time(), time.perf_counter()
    terms = [ch.fit_noise_terms(ch.allan_deviation(values[:, i], RATE_HZ))
             for values in (gyro, accel) for i in range(3)]
    cpu, wall = time.process_time() - cpu, time.perf_counter() - wall
    # Bias instability alone (no random walk), to see its floor.
    flicker = _series(n, 0.0, B_TRUE, seed=5)
    b_terms = [ch.fit_noise_terms(ch.allan_deviation(flicker[:, i], RATE_HZ)) for i in range(3)]
    return {
        'hours_of_200hz_imu': hours,
        'samples_per_axis': n,
        'six_axes_cpu_s': round(cpu, 3),
        'six_axes_wall_s': round(wall, 3),
        'n_k_case_gyro_n_worst_relative_error': _worst(terms[:3], 'n', N_TRUE),
        'n_k_case_gyro_k_worst_relative_error': _worst(terms[:3], 'k', K_TRUE),
        'n_b_case_gyro_n_worst_relative_error': _worst(b_terms, 'n', N_TRUE),
        'n_b_case_gyro_b_worst_relative_error': _worst(b_terms, 'b', B_TRUE),
    }


if __name__ == '__main__':
    import json

    print(json.dumps(run(), indent=2))
