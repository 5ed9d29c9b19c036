"""``youbot_fdi/fdi/recursions.py``: each vectorised recursion over a block equals its
one-row loop (prefix scans, closed-form CUSUMs, running maxima), from any state."""
import warnings

from hypothesis import given, settings, strategies as st

import numpy as np

from youbot_fdi.fdi.recursions import (affine_recursion, bounded_cusum, clip_recursion, cusum,
                                      decaying_peak, last_true_value, nan_median, run_lengths,
                                      scalar_recursion)

FAST_EXCEPT = ()  # `make check`: every test here (the unit tests of the core, under a minute)


@settings(max_examples=60, deadline=None)
@given(rows=st.integers(0, 40), size=st.integers(1, 5), seed=st.integers(0, 2**32 - 1))
def test_affine_recursion_equals_its_loop(rows, size, seed):
    rng = np.random.default_rng(seed)
    a = rng.normal(scale=0.6, size=(rows, size, size))
    a[rng.random(rows) < 0.2] = 0.0  # restarts
    b = rng.normal(size=(rows, size))
    x = x0 = rng.normal(size=size)
    expected = []
    for k in range(rows):
        x = a[k] @ x + b[k]
        expected.append(x)
    got = affine_recursion(a, b, x0)
    assert got.shape == (rows, size)
    np.testing.assert_allclose(got, np.reshape(expected, (rows, size)), rtol=1e-9, atol=1e-9)


@settings(max_examples=60, deadline=None)
@given(rows=st.integers(1, 70), seed=st.integers(0, 2**32 - 1))
def test_smoothing_and_cusums_equal_their_loops(rows, seed):
    """Exponential smoothing with a factor per row or per element, the CUSUM and the CUSUM held
    below a ceiling, from any state, equal their one-row loops."""
    rng = np.random.default_rng(seed)
    shape = (rows, 2, 3)
    factor_rows, factors = rng.random(rows), rng.random(shape)
    steps = rng.normal(scale=2.0, size=shape)
    start = rng.random(shape[1:]) * 6.0
    ceiling = rng.uniform(1.0, 8.0)
    flat = steps.reshape(rows, -1)
    by_row = by_element = plain = held = start.reshape(-1)  # each name is rebound, never changed
    expected = {name: [] for name in ('by_row', 'by_element', 'plain', 'held')}
    for k in range(rows):
        by_row = factor_rows[k] * by_row + flat[k]
        by_element = factors[k].reshape(-1) * by_element + flat[k]
        plain = np.maximum(0.0, plain + flat[k])
        held = np.clip(held + flat[k], 0.0, ceiling)
        for name, value in zip(expected, (by_row, by_element, plain, held)):
            expected[name].append(value)
    got = {'by_row': scalar_recursion(factor_rows, flat, start.reshape(-1)),
           'by_element': scalar_recursion(factors.reshape(rows, -1), flat, start.reshape(-1)),
           'plain': cusum(steps, start).reshape(rows, -1),
           'held': bounded_cusum(steps, start, ceiling).reshape(rows, -1)}
    for name, rows_expected in expected.items():
        np.testing.assert_allclose(got[name], rows_expected, rtol=1e-9, atol=1e-9, err_msg=name)


@settings(max_examples=60, deadline=None)
@given(rows=st.integers(1, 70), seed=st.integers(0, 2**32 - 1))
def test_a_clip_recursion_equals_its_loop(rows, seed):
    """``x_k = min(max(x_{k-1}, low_k), high_k)`` with rows that hold (-inf, inf), set (low =
    high) or clip, by its loop: the same bits (a clip does no arithmetic)."""
    rng = np.random.default_rng(seed)
    ends = np.sort(rng.normal(size=(rows, 2)), axis=1)
    kind = rng.integers(0, 3, rows)
    low = np.where(kind == 0, -np.inf, ends[:, 0])
    high = np.where(kind == 0, np.inf, np.where(kind == 1, ends[:, 0], ends[:, 1]))
    x = start = float(rng.normal())
    expected = []
    for k in range(rows):
        x = min(max(x, low[k]), high[k])
        expected.append(x)
    assert clip_recursion(low, high, start).tolist() == expected


@settings(max_examples=60, deadline=None)
@given(rows=st.integers(1, 30), size=st.integers(1, 7), seed=st.integers(0, 2**32 - 1))
def test_a_decaying_peak_is_the_same_in_any_chunking(rows, size, seed):
    """``y_k = max(v_k, exp(-rate dt_k) y_{k-1})`` by its loop, and the same bits in chunks of any
    size (the state carried between them); NaN counts as nothing."""
    rng = np.random.default_rng(seed)
    values = np.where(rng.random((rows, 3)) < 0.4, 0.0, rng.exponential(size=(rows, 3)))
    values[rng.random((rows, 3)) < 0.1] = np.nan
    elapsed = np.cumsum(rng.uniform(0.001, 0.05, rows))[:, None]
    rate = np.array([0.0, 3.0, 40.0])  # [1/s]: never forgets, slowly, quickly
    peak, before, expected = np.zeros(3), 0.0, []
    for k in range(rows):
        peak = np.maximum(np.nan_to_num(values[k]), np.exp(-rate * (elapsed[k, 0] - before)) * peak)
        before = elapsed[k, 0]
        expected.append(peak)
    whole, _ = decaying_peak(values, elapsed, rate, np.full(3, -np.inf))
    np.testing.assert_allclose(whole, expected, rtol=1e-9, atol=1e-300)
    level, parts = np.full(3, -np.inf), []
    for start in range(0, rows, size):
        part, levels = decaying_peak(values[start:start + size], elapsed[start:start + size], rate, level)
        parts.append(part)
        level = levels[-1]
    np.testing.assert_array_equal(np.concatenate(parts), whole)


@settings(max_examples=80, deadline=None)
@given(rows=st.integers(0, 6), width=st.integers(1, 6), seed=st.integers(0, 2**32 - 1))
def test_nan_median_equals_numpys(rows, width, seed):
    """The rows' median without NaN, as numpy's nanmedian gives it (NaN for a row of NaN)."""
    rng = np.random.default_rng(seed)
    values = rng.normal(size=(rows, width))
    values[rng.random((rows, width)) < 0.3] = np.nan
    values[rng.random((rows, width)) < 0.2] = 1.0  # ties
    with np.errstate(all='ignore'), warnings.catch_warnings():
        warnings.simplefilter('ignore', RuntimeWarning)  # numpy warns of all-NaN rows
        expected = np.nanmedian(values, axis=-1)
    np.testing.assert_array_equal(nan_median(values), expected)
    np.testing.assert_array_equal(nan_median(values[0]) if rows else [], expected[0] if rows else [])


@settings(max_examples=80, deadline=None)
@given(flags=st.lists(st.lists(st.booleans(), min_size=3, max_size=3), max_size=30),
       carry=st.lists(st.integers(0, 9), min_size=3, max_size=3), seed=st.integers(0, 999))
def test_run_lengths_and_last_values_equal_their_loops(flags, carry, seed):
    rows = len(flags)
    flags = np.array(flags, dtype=bool).reshape(rows, 3)
    restart = np.random.default_rng(seed).random(rows) < 0.15
    count, expected = np.array(carry), []
    for k in range(rows):
        count = np.where(flags[k] & ~restart[k], count + 1, 0)
        expected.append(count)
    np.testing.assert_array_equal(run_lengths(flags, np.array(carry), restart),
                                  np.reshape(expected, (rows, 3)))
    values = np.arange(rows) * 10.0
    latest, expected = -1.0, []
    for k in range(rows):
        latest = values[k] if restart[k] else latest
        expected.append(latest)
    np.testing.assert_array_equal(last_true_value(restart, values, -1.0), expected)
    # values per column (N, 3) at each column's own latest flag, row by row the same
    table = np.random.default_rng(seed + 1).random((rows, 3))
    initial = np.array(carry, dtype=float)
    latest, expected = initial.copy(), []
    for k in range(rows):
        latest = np.where(flags[k], table[k], latest)
        expected.append(latest)
    block = last_true_value(flags, table, initial)
    np.testing.assert_array_equal(block, np.reshape(expected, (rows, 3)))
    carried, by_row = initial.copy(), []
    for k in range(rows):
        carried = last_true_value(flags[k:k + 1], table[k:k + 1], carried)[0]
        by_row.append(carried)
    np.testing.assert_array_equal(np.reshape(by_row, (rows, 3)), block)


