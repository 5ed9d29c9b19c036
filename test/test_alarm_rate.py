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


def test_a_silence_is_judged_by_the_misses_calibration_allows():
    """No miss in N samples: the chance of one is at most 1 - 0.05^(1/N) (95 %); k misses in a
    row start at a sample with at most that to the k-th, on each of the wheels."""
    estimate = alarm_rate.silence_estimate(np.ones((3000, 4), dtype=bool), 0.01)
    chance = 1.0 - 0.05 ** (1.0 / 3000)
    assert estimate.miss_chance == pytest.approx(chance, rel=1e-9)
    assert estimate.longest == 0
    assert estimate.rate(3) == pytest.approx(4 * 360000.0 * chance ** 3)
    # 4 x 360000 x p^2 = 1.43 per hour, x p once more = 1.4e-3: three in a row meet 0.01 / 6
    assert estimate.threshold(0.01 / 6) == 3
    assert estimate.rate(estimate.threshold(1e-6)) <= 1e-6 < estimate.rate(estimate.threshold(1e-6) - 1)


def test_a_silence_as_long_as_one_calibration_saw_is_never_a_fault():
    """Wheel 1 missed 5 samples in a row, wheel 2 one: the longest run is 5, so a silence needs 6
    whatever the chance says; the chance is the Clopper-Pearson bound of the wheel missing most."""
    answered = np.ones((3000, 4), dtype=bool)
    answered[100:105, 1] = False
    answered[2000, 2] = False
    estimate = alarm_rate.silence_estimate(answered, 0.01)
    assert alarm_rate.longest_run(~answered) == estimate.longest == 5
    assert estimate.rate(5) == math.inf
    assert estimate.threshold(1e3) == 6  # a lax target: the run calibration saw decides
    # 5 misses of 3000: P(X <= 5) = 0.05 at the bound (binomial)
    p = estimate.miss_chance
    assert sum(math.comb(3000, k) * p ** k * (1 - p) ** (3000 - k) for k in range(6)) == \
        pytest.approx(0.05, rel=1e-6)


def test_silences_without_data_or_with_bad_shapes():
    with pytest.raises(ValueError, match='shape'):
        alarm_rate.silence_estimate(np.ones(10, dtype=bool), 0.01)
    with pytest.raises(ValueError, match='interval'):
        alarm_rate.silence_estimate(np.ones((10, 4), dtype=bool), 0.0)
    every = alarm_rate.silence_estimate(np.zeros((10, 4), dtype=bool), 0.01)  # never an answer
    assert every.miss_chance == 1.0 and every.threshold(0.01) == math.inf


def test_a_wheel_times_out_after_its_silent_samples_never_after_the_base():
    """A wheel's silence counts from its first sample without a reading, so k samples in a row
    span (k - 1) intervals; never longer than the base's data timeout, which stands in when
    identify measured nothing (no count, or no interval)."""
    from dataclasses import replace
    from youbot_fdi.fdi.settings import FdiSettings
    base = FdiSettings()
    assert replace(base, silent_samples=3, sample_interval=0.01).wheel_timeout == pytest.approx(0.02)
    assert replace(base, silent_samples=3).wheel_timeout == base.data_timeout  # no interval
    assert replace(base, sample_interval=0.01).wheel_timeout == base.data_timeout  # no count
    slow = replace(base, silent_samples=40, sample_interval=0.05)  # 1.95 s of samples
    assert slow.wheel_timeout == slow.data_timeout == pytest.approx(0.75)  # 15 intervals
