"""Transforms: two publishers of one transform on /tf. A bag does not record who published a
message, but two publishers leave two interleaved tracks: consecutive samples of one pair jump
between them while every other sample continues smoothly (and stamps repeat or step back)."""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from sensing_nodes.core.diagnosis.check import OK, PROBLEM, Check, plural


def publishers_check(pair: str, stamps_ns: NDArray[np.int64], xyyaw: NDArray[np.float64],
                     min_jump_m: float = 0.01, min_jump_rad: float = math.radians(1.0)
                     ) -> Check:
    """One transform's samples (bag order): the share that jump from their predecessor but
    continue the one before it (two tracks), and stamps that go back or repeat."""
    p = np.asarray(xyyaw, dtype=float)
    if len(p) < 5:
        return Check('tf_publishers', pair, OK, 0.0, 'samples', f'{len(p)} samples only')

    def size(d: NDArray[np.float64]) -> NDArray[np.float64]:
        ang = np.abs(np.angle(np.exp(1j * d[:, 2])))
        return np.maximum(np.hypot(d[:, 0], d[:, 1]) / min_jump_m, ang / min_jump_rad)

    d1 = size(p[2:] - p[1:-1])
    d2 = size(p[2:] - p[:-2])
    switching = (d1 > 1.0) & (d2 < 0.5 * d1)
    share = float(switching.mean())
    t = np.asarray(stamps_ns)
    back = int((np.diff(t) < 0).sum())
    same = int((np.diff(t) == 0).sum())
    two = share > 0.05
    verdict = PROBLEM if two else OK
    advice = (f'{pair} alternates between two tracks ({100 * share:.0f} % of samples jump and '
              f'return; {back} stamps go back, {same} repeat): two nodes publish it (e.g. a '
              'base controller and an EKF, both with publish_tf): let one publish it'
              if two else f'{pair}: one consistent publisher')
    return Check('tf_publishers', pair, verdict, 100.0 * share, '% switching samples', advice,
                 '< 5 %', {'samples': int(len(p)), 'stamps_back': back, 'stamps_repeated': same})


def static_check(pair: str, translations: NDArray[np.float64],
                 rotations: NDArray[np.float64]) -> Check:
    """One /tf_static transform declared more than once (translations m, rotations x y z w):
    the declarations must agree (1 mm, 0.1 deg); two different mounts of one sensor mean two
    launch files disagree."""
    spread_m = float(np.ptp(translations, axis=0).max()) if len(translations) > 1 else 0.0
    q = np.asarray(rotations, dtype=float)
    q = q / np.linalg.norm(q, axis=1, keepdims=True)
    dots = np.clip(np.abs(q @ q[0]), 0.0, 1.0)
    spread_deg = math.degrees(float(2.0 * np.arccos(dots).max()))
    differ = spread_m > 1e-3 or spread_deg > 0.1
    return Check('tf_static', pair, PROBLEM if differ else OK, spread_m, 'm',
                 f'{pair} is declared {len(translations)} times, {spread_m:.3f} m and '
                 f'{spread_deg:.2f} deg apart: two publishers disagree on the mount; keep one'
                 if differ else f'{pair} declared {plural(len(translations), "time")}, '
                 'consistently',
                 '< 1 mm, < 0.1 deg', {'declarations': len(translations),
                                       'spread_deg': spread_deg})
