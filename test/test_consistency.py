"""core/evaluation/consistency.py: the three-cornered hat recovers known error sizes, the
relation covariance matches a Monte Carlo, and the 'good match' test of issue 32's target 3."""

import numpy as np
import pytest

from sensing_nodes.core.evaluation.consistency import (
    consecutive_relations,
    informative,
    relation_covariance,
    three_cornered_hat,
    within_reference_noise,
)
from sensing_nodes.core.geometry import se2


def test_relation_covariance_matches_a_monte_carlo():
    rng = np.random.default_rng(1)
    a, b = (1.0, 2.0, 0.7), (3.0, 1.5, -0.4)
    cov_a = np.diag([0.01, 0.02, 0.003])
    cov_b = np.diag([0.015, 0.005, 0.002])
    draws = np.array([se2.between(tuple(np.add(a, rng.multivariate_normal(np.zeros(3), cov_a))),
                                  tuple(np.add(b, rng.multivariate_normal(np.zeros(3), cov_b))))
                      for _ in range(40000)])
    sampled = np.cov(draws.T)
    # First order: within a few per cent of the sampled covariance at these small angles.
    np.testing.assert_allclose(relation_covariance(a, cov_a, b, cov_b), sampled,
                               atol=0.06 * np.max(np.abs(sampled)))


def _relations(n, rng):
    return np.column_stack([rng.uniform(0.2, 1.0, n), rng.uniform(-0.1, 0.1, n),
                            rng.uniform(-0.3, 0.3, n)])


def test_the_hat_recovers_each_estimate_s_own_error():
    rng = np.random.default_rng(2)
    n = 4000
    truth = _relations(n, rng)
    own = {'estimate': (0.01, 0.02, 0.002), 'other': (0.04, 0.03, 0.006),
           'reference': (0.02, 0.02, 0.005)}
    noisy = {k: truth + rng.normal(0.0, s, (n, 3)) for k, s in own.items()}
    claimed = np.tile(np.diag(np.square([0.02, 0.02, 0.004])), (n, 1, 1))
    hat = three_cornered_hat(noisy['estimate'], noisy['other'], noisy['reference'], claimed)
    assert hat.relations == n
    np.testing.assert_allclose(hat.own, own['estimate'], rtol=0.2)
    np.testing.assert_allclose(hat.reference_own, own['reference'], rtol=0.15)
    np.testing.assert_allclose(hat.claimed, [0.02, 0.02, 0.004])
    np.testing.assert_allclose(hat.ratio, [2.0, 1.0, 2.0], rtol=0.2)
    assert np.all(hat.own_low <= hat.own) and np.all(hat.own <= hat.own_high)


def test_an_error_below_what_the_others_resolve_is_zero_and_its_ratio_infinite():
    rng = np.random.default_rng(3)
    n = 500
    truth = _relations(n, rng)
    reference = truth + rng.normal(0.0, 0.05, (n, 3))
    hat = three_cornered_hat(truth.copy(), truth + rng.normal(0.0, 0.05, (n, 3)), reference,
                             np.tile(np.eye(3) * 1e-4, (n, 1, 1)))
    assert np.all(hat.own < 0.01)
    assert np.isinf(hat.ratio[hat.own == 0]).all()


def test_consecutive_relations_only_within_one_map():
    stamps = np.array([10, 20, 30, 40], dtype=np.int64)
    maps = np.array([1, 1, 2, 2])
    poses = np.array([[0.0, 0, 0], [1.0, 0, np.pi / 2], [0.0, 0, 0], [0.0, 2.0, 0]])
    covs = np.tile(np.eye(3) * 0.01, (4, 1, 1))
    pairs, rel, rel_cov = consecutive_relations(stamps, maps, poses, covs)
    assert pairs.tolist() == [[10, 20], [30, 40]]
    np.testing.assert_allclose(rel, [[1.0, 0, np.pi / 2], [0.0, 2.0, 0]], atol=1e-12)
    assert rel_cov.shape == (2, 3, 3)


def test_good_matches_are_within_three_reference_sigmas_on_resolved_axes():
    reference = np.zeros((3, 3)) + [1.0, 0.0, 0.0]
    estimate = reference + [[0.05, 0.0, 0.0], [0.0, 0.07, 0.0], [0.0, 0.0, 0.5]]
    good = within_reference_noise(estimate, reference, np.array([0.02, 0.02, 0.0]))
    # 0.05 < 3 x 0.02, 0.07 > 0.06; yaw unresolved (0) is not judged.
    assert good.tolist() == [True, False, True]


def test_uninformative_relations_are_those_far_above_the_median():
    covs = np.tile(np.eye(3) * 1e-4, (10, 1, 1))
    covs[3] *= 1e4
    assert informative(covs).tolist() == [i != 3 for i in range(10)]


@pytest.mark.parametrize('axis', [0, 1, 2])
def test_the_hat_is_per_axis(axis):
    rng = np.random.default_rng(4 + axis)
    n = 3000
    truth = _relations(n, rng)
    sigma = np.full(3, 0.01)
    sigma[axis] = 0.05
    hat = three_cornered_hat(truth + rng.normal(0.0, sigma, (n, 3)),
                             truth + rng.normal(0.0, 0.03, (n, 3)),
                             truth + rng.normal(0.0, 0.02, (n, 3)),
                             np.tile(np.eye(3) * 1e-4, (n, 1, 1)))
    assert np.argmax(hat.own) == axis
