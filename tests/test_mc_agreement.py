"""The per-pixel z-test's bounds (tests/mc_agreement.py) on synthetic estimates whose truth
is known: agreeing estimates pass at the stated false-alarm rate, a biased estimate or one
whose variance is understated fails, and an estimate without its passes is refused."""

from __future__ import annotations

import numpy as np
import pytest

from mc_agreement import BIAS_BUDGET, FALSE_ALARM, agreement
from pbr_tactile.render import Estimate

#: An 8x6 film of 3 channels, as the volpath checks use, with the two estimators' pass
#: counts and per-pass relative noise (each mean then has about 4 % and 10 % error).
SHAPE, TEST_PASSES, REF_PASSES = (6, 8, 3), 6, 16
TEST_NOISE, REF_NOISE = 0.04 * np.sqrt(TEST_PASSES), 0.10 * np.sqrt(REF_PASSES)
#: A footprint much wider than the kernel: the pixels are independent here.
FOOTPRINT_M, KERNEL_M = 1.0, 1e-6
TRIALS = 20


def _estimate(truth, passes, noise, rng, scale=1.0, variance_scale=1.0):
    images = [truth * scale * (1 + noise * rng.standard_normal(truth.shape)) for _ in range(passes)]
    est = Estimate.from_passes(images, 1)
    return Estimate(est.mean, est.variance * variance_scale, est.spp, est.passes)


def _failures(scale=1.0, variance_scale=1.0, seed=0) -> int:
    rng = np.random.default_rng(seed)
    failed = 0
    for _ in range(TRIALS):
        truth = rng.uniform(0.2, 1.0, SHAPE)
        test = _estimate(truth, TEST_PASSES, TEST_NOISE, rng, scale, variance_scale)
        ref = _estimate(truth, REF_PASSES, REF_NOISE, rng, 1.0, variance_scale)
        try:
            agreement(test, ref, np.ones(SHAPE, bool), FOOTPRINT_M, KERNEL_M).check()
        except AssertionError:
            failed += 1
    return failed


def test_agreeing_estimates_pass_at_the_stated_rate():
    # 3 statistics at FALSE_ALARM each (the aggregate's budget is far from its noise here):
    # 0.06 false alarms expected in 20 trials; 2 or more has odds under 0.2 %.
    assert 3 * FALSE_ALARM * TRIALS < 0.1
    assert _failures() <= 1


@pytest.mark.parametrize("scale", [1 + 2 * BIAS_BUDGET, 1 - 2 * BIAS_BUDGET])
def test_an_estimate_off_by_twice_the_budget_fails(scale):
    assert _failures(scale=scale) >= TRIALS - 1


def test_understated_variances_fail():
    # both variances a quarter of the truth: every z twice what it should be
    assert _failures(variance_scale=0.25) >= TRIALS - 1


def test_an_estimate_without_its_passes_is_refused():
    truth = np.ones(SHAPE)
    est = Estimate(truth, truth * 0.01, 1)  # passes not recorded (0)
    with pytest.raises(ValueError, match="test must record its passes"):
        agreement(est, est, np.ones(SHAPE, bool), FOOTPRINT_M, KERNEL_M)
