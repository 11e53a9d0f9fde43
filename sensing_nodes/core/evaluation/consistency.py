"""Whether an estimator's claimed covariance covers its own error, where the reference has an
error of its own: the three-cornered hat over the relations between consecutive samples of
three estimates of the same motion (the estimator, another input, the reference).

With independent errors, the variances of the pairwise differences give each estimate's own
error variance: own(A) = (var(A - C) + var(A - B) - var(B - C)) / 2 per axis. The estimator's
claimed standard deviation is the RMS of the ones its covariances give the same relations;
claimed over own near 1 is honest (docs/real-data.md). Relation errors in the relation's start
frame (x, y in m, yaw in rad)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from sensing_nodes.core.geometry import se2

AXES = ('x', 'y', 'yaw')


def relation_covariance(a: se2.Pose2, cov_a: NDArray[np.float64], b: se2.Pose2,
                        cov_b: NDArray[np.float64]) -> NDArray[np.float64]:
    """Covariance (3x3) of between(a, b) for independent poses a and b with covariances over
    their coordinates (x, y, yaw)."""
    dx, dy = b[0] - a[0], b[1] - a[1]
    c, s = np.cos(a[2]), np.sin(a[2])
    # between(a, b) = (R(a)ᵀ (t_b - t_a), yaw_b - yaw_a): its Jacobians in a's and b's
    # coordinates.
    j_a = np.array([[-c, -s, -s * dx + c * dy], [s, -c, -c * dx - s * dy], [0.0, 0.0, -1.0]])
    j_b = np.array([[c, s, 0.0], [-s, c, 0.0], [0.0, 0.0, 1.0]])
    return j_a @ cov_a @ j_a.T + j_b @ cov_b @ j_b.T


def consecutive_relations(stamps: NDArray[np.int64], map_ids: NDArray[np.int64],
                          poses: NDArray[np.float64], covariances: NDArray[np.float64]
                          ) -> tuple[NDArray[np.int64], NDArray[np.float64], NDArray[np.float64]]:
    """The relations between consecutive matches in the same local map (poses (N, 3) in the map
    named by map_ids, covariances (N, 3, 3), at stamps ns): the pairs' stamps (M, 2), the
    relations (M, 3) in the first's frame and their covariances (M, 3, 3), the two poses'
    errors taken as independent."""
    same = np.flatnonzero(map_ids[1:] == map_ids[:-1])
    pairs = np.stack([stamps[same], stamps[same + 1]], axis=1)
    relations = np.array([se2.between(tuple(poses[i]), tuple(poses[i + 1])) for i in same]
                         ).reshape(-1, 3)
    covs = np.array([relation_covariance(tuple(poses[i]), covariances[i], tuple(poses[i + 1]),
                                         covariances[i + 1]) for i in same]).reshape(-1, 3, 3)
    return pairs.astype(np.int64), relations, covs


def informative(covariances: NDArray[np.float64], factor: float = 10.0) -> NDArray[np.bool_]:
    """Relations (covariances (N, 3, 3)) whose standard deviation on every axis is within
    `factor` times the median's: the others are the matcher saying it does not know (a
    fallback on the odometry, a degenerate match), weigh nothing in the fusion and would
    dominate a root-mean-square claimed sigma."""
    sigma = np.sqrt(covariances[:, [0, 1, 2], [0, 1, 2]])
    return np.all(sigma <= factor * np.median(sigma, axis=0), axis=1)


def relation_errors(motion: NDArray[np.float64], reference: NDArray[np.float64]
                    ) -> NDArray[np.float64]:
    """Each relation's error (N, 3) against the reference's, in the relation's end frame."""
    e = np.array([se2.between(tuple(r), tuple(m)) for r, m in zip(reference, motion)]
                 ).reshape(-1, 3)
    e[:, 2] = se2.wrap_angle(e[:, 2])
    return e


@dataclass(frozen=True)
class Hat:
    """Per axis (x, y, yaw): the estimator's own error's standard deviation by the
    three-cornered hat (0 where the difference of variances is negative: below what the
    others resolve) with a bootstrap 90 % interval, the standard deviation its covariances
    claim (RMS over the relations), the reference's own standard deviation (with any part
    common to both inputs), and the number of relations."""

    own: NDArray[np.float64]
    own_low: NDArray[np.float64]
    own_high: NDArray[np.float64]
    claimed: NDArray[np.float64]
    reference_own: NDArray[np.float64]
    relations: int

    @property
    def ratio(self) -> NDArray[np.float64]:
        """claimed / own per axis (inf where own is 0)."""
        with np.errstate(divide='ignore', invalid='ignore'):
            return np.where(self.own > 0, self.claimed / np.where(self.own > 0, self.own, 1.0),
                            np.inf)


def _own(e_a: NDArray, e_b: NDArray) -> NDArray[np.float64]:
    """Own error variance of A per axis from A's and B's errors against the reference."""
    return 0.5 * (e_a.var(axis=0) + (e_a - e_b).var(axis=0) - e_b.var(axis=0))


def three_cornered_hat(estimate: NDArray[np.float64], other: NDArray[np.float64],
                       reference: NDArray[np.float64], claimed: NDArray[np.float64],
                       bootstrap: int = 500, seed: int = 0) -> Hat:
    """The hat over N relations (each (N, 3): the estimator's, another input's and the
    reference's motion between the same two samples) and the estimator's claimed covariance
    of each (N, 3, 3)."""
    e_a, e_b = relation_errors(estimate, reference), relation_errors(other, reference)
    own = np.sqrt(np.maximum(_own(e_a, e_b), 0.0))
    # The reference's own part: var(R) = (var(A - R) + var(B - R) - var(A - B)) / 2.
    reference_own = np.sqrt(np.maximum(
        0.5 * (e_a.var(axis=0) + e_b.var(axis=0) - (e_a - e_b).var(axis=0)), 0.0))
    rng = np.random.default_rng(seed)
    draws = np.array([np.sqrt(np.maximum(_own(e_a[i], e_b[i]), 0.0)) for i in
                      rng.integers(0, len(e_a), size=(bootstrap, len(e_a)))])
    low, high = np.percentile(draws, [5.0, 95.0], axis=0)
    claimed_std = np.sqrt(np.mean(claimed[:, [0, 1, 2], [0, 1, 2]], axis=0))
    return Hat(own, low, high, claimed_std, reference_own, len(e_a))


def within_reference_noise(estimate: NDArray[np.float64], reference: NDArray[np.float64],
                           reference_own: NDArray[np.float64], factor: float = 3.0
                           ) -> NDArray[np.bool_]:
    """Relations (N, 3) whose error against the reference's is under `factor` times the
    reference's own standard deviation on every axis where that is resolved (above 0): the
    matches a gate must not refuse."""
    e = np.abs(relation_errors(estimate, reference))
    resolved = reference_own > 0
    return np.all(e[:, resolved] < factor * reference_own[resolved], axis=1)
