"""The stated false-alarm rate (``fdi/alarm_rate.py``): Lundberg's exponent and the rate bound,
against hand-derived closed forms."""
import math

import numpy as np
import pytest

from youbot_fdi.fdi import alarm_rate

pytestmark = pytest.mark.fast  # `make check`: the unit tests of the core, under a minute


def test_the_exponent_of_a_two_point_walk_is_log_two():
    """Steps +1 with probability 1/3 and -1 with 2/3: (1/3) e^t + (2/3) e^-t = 1 has the positive
    root e^t = 2, t = ln 2 (then an excursion rises by h with probability 2^-h)."""
    steps = np.array([1.0, -1.0, -1.0] * 1000)
    assert alarm_rate.lundberg_exponent(steps) == pytest.approx(math.log(2.0), rel=1e-9)


def test_walks_that_never_rise_or_that_drift_up():
    assert alarm_rate.lundberg_exponent(np.full(50, -0.5)) == math.inf  # never rises: never alarms
    assert alarm_rate.lundberg_exponent(np.array([1.0, -0.5])) == 0.0  # drifts up: always alarms


def test_the_rate_and_the_threshold_are_inverse():
    """rate(h) = streams x blocks per hour x exp(-theta h); threshold(rate) inverts it."""
    estimate = alarm_rate.RateEstimate(exponent=math.log(2.0), blocks_per_hour=3600.0, streams=4)
    assert estimate.rate(10.0) == pytest.approx(4 * 3600.0 / 2 ** 10)
    assert estimate.rate(estimate.threshold(0.01)) == pytest.approx(0.01)
    assert alarm_rate.RateEstimate(math.inf, 3600.0, 4).threshold(0.01) == 0.0
    assert alarm_rate.RateEstimate(0.0, 3600.0, 4).threshold(0.01) == math.inf


def test_blocks_span_the_scores_correlation():
    """Independent scores: one-sample blocks; a moving sum over 8 samples: its autocorrelation at
    lag L is (8 - L) / 8, below 1/e from lag 6 on."""
    rng = np.random.default_rng(0)
    white = rng.normal(size=(20000, 2))
    assert alarm_rate.correlation_length(white) == 1
    smooth = np.stack([np.convolve(white[:, k], np.ones(8), mode='valid') for k in range(2)], axis=1)
    assert alarm_rate.correlation_length(smooth) == 6


def test_identify_raises_a_threshold_only_where_its_rate_would_miss_the_target():
    from youbot_fdi.fdi.identify import RATE_TESTS, rate_thresholds
    from youbot_fdi.fdi.settings import FdiSettings
    settings = FdiSettings()
    quiet = alarm_rate.RateEstimate(math.inf, 3600.0, 4)
    noisy = alarm_rate.RateEstimate(0.5, 36000.0, 4)
    estimates = {test: quiet for test in RATE_TESTS}
    estimates['command'] = noisy
    chosen, stated = rate_thresholds(estimates, settings)
    share = settings.false_alarm_target / len(RATE_TESTS)
    assert chosen['family_thresholds'][0] == settings.family_thresholds[0]  # never lowered
    assert chosen['family_thresholds'][2] == pytest.approx(noisy.threshold(share))
    assert stated['command'][1] == pytest.approx(share)
    assert sum(rate for _, rate in stated.values()) <= settings.false_alarm_target + 1e-12
