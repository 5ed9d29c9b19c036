"""Linear recursions over a whole block of samples at once (the batched replay's building blocks).

Each function equals its one-sample-at-a-time loop up to floating-point rounding; for a block of
one sample it is that loop.
"""
from __future__ import annotations

import numpy as np

#: The stamp [s] of something that has not happened (finite: differences stay defined).
NEVER = -1e300


def clip(values, low, high):
    """``np.clip(values, low, high)`` (NaN stays NaN), without its dispatch, which costs a live
    row of four wheels twice the arithmetic (1.7 against 0.8 µs)."""
    return np.minimum(np.maximum(values, low), high)


def shifted(first, rows: np.ndarray) -> np.ndarray:
    """Each of ``rows`` (N, ...) replaced by the one before it, ``first`` (...) before the first:
    ``concatenate([first[None], rows[:-1]])``; for one row a view of ``first`` (the live path).
    Neither is written to."""
    first = np.asarray(first)
    if len(rows) == 1:
        return first[None]
    return np.concatenate([first[None], rows[:-1]])


def matvec(matrices: np.ndarray, vectors: np.ndarray) -> np.ndarray:
    """``matrices @ vectors`` row by row: (N, d, m) with (N, m) -> (N, d)."""
    return np.matmul(matrices, vectors[..., None])[..., 0]


def affine_recursion(a: np.ndarray, b: np.ndarray, x0: np.ndarray) -> np.ndarray:
    """States of ``x_k = a_k x_{k-1} + b_k`` for k = 0..N-1 from ``x_{-1} = x0``.

    a : (N, d, d); b : (N, d); x0 : (d,). Returns (N, d). A prefix scan (Hillis-Steele): log2(N)
    vectorised compositions instead of N small matrix products.
    """
    n = len(b)
    if n == 0:
        return np.empty((0, len(x0)))
    if n == 1:
        return (a[0] @ x0 + b[0])[None]
    a, b = a.copy(), b.copy()
    shift = 1
    while shift < n:
        b[shift:] += matvec(a[shift:], b[:-shift])
        a[shift:] = np.matmul(a[shift:], a[:-shift])
        shift *= 2
    return matvec(a, np.broadcast_to(x0, b.shape)) + b


def scalar_recursion(a: np.ndarray, b: np.ndarray, x0: np.ndarray) -> np.ndarray:
    """States of ``x_k = a_k x_{k-1} + b_k`` element by element: a (N,) (one factor per row) or
    (N, d), b (N, d), x0 (d,); returns (N, d). Exponential smoothing with a varying step, as a
    prefix scan."""
    n = len(b)
    if n == 0:
        return np.empty((0, len(x0)))
    if n == 1:  # one row (the live path): the same ``a x0 + b`` without the scan's copies
        a = np.asarray(a, dtype=float)
        return (a[:, None] if a.ndim == 1 else a) * x0 + np.asarray(b, dtype=float)
    a, b = np.array(a, dtype=float), np.array(b, dtype=float)
    if a.ndim == 1:
        a = a[:, None]
    a = np.array(np.broadcast_to(a, b.shape))
    shift = 1
    while shift < n:
        b[shift:] += a[shift:] * b[:-shift]
        a[shift:] *= a[:-shift]
        shift *= 2
    return a * x0 + b


def decaying_peak(values: np.ndarray, elapsed: np.ndarray, rate, level: np.ndarray):
    """Peaks ``y_k = max(values_k, exp(-rate dt_k) y_{k-1})`` of ``values`` (N, d) >= 0 (NaN
    counts as 0) at times ``elapsed`` (N, 1) [s] since a reference stamp, decaying at ``rate``
    (scalar or (d,)) [1/s], continuing ``level`` (d,): the state, the log of the peak carried to
    the reference (-inf: none). Returns (peaks (N, d), levels (N, d): the state after each row).

    Kept as ``max_j (log values_j + rate elapsed_j)``, a running maximum, so a block gives the same
    bits as its rows one by one (a product of decays would not)."""
    values = np.asarray(values, dtype=float)
    # log 0 (and of NaN) is -inf here: nothing to carry (no warning state to switch)
    own = np.log(values, out=np.full(values.shape, -np.inf), where=values > 0.0) + rate * elapsed
    if len(own) == 1:
        levels = np.maximum(own, level)
    else:
        levels = np.maximum.accumulate(np.concatenate([np.asarray(level)[None], own]), axis=0)[1:]
    return np.exp(levels - rate * elapsed), levels


def nan_median(values: np.ndarray) -> np.ndarray:
    """The median over the last axis with NaN left out (NaN where every value is), shape
    ``values.shape[:-1]``: ``np.nanmedian(values, axis=-1)`` without its masked-array machinery,
    which costs a live sample more than the rest of the observer."""
    values = np.asarray(values, dtype=float)
    width = values.shape[-1]
    if values.size == width:  # one row (the live path): the same median, in plain floats
        known = sorted(v for v in values.reshape(-1).tolist() if v == v)
        return np.array(sorted_median(known)).reshape(values.shape[:-1])
    ordered = np.sort(values, axis=-1).reshape(-1, width)  # NaN sort last
    count = (~np.isnan(values)).sum(axis=-1).reshape(-1)
    rows = np.arange(len(count))
    low, high = ordered[rows, np.maximum((count - 1) // 2, 0)], ordered[rows, count // 2]
    return np.where(count > 0, (low + high) / 2.0, np.nan).reshape(values.shape[:-1])


def sorted_median(known: list[float]) -> float:
    """The median of the sorted floats ``known``, as :func:`nan_median` takes it; NaN for none."""
    count = len(known)
    return (known[(count - 1) // 2] + known[count // 2]) / 2.0 if count else np.nan


def run_lengths(flags: np.ndarray, carry: np.ndarray, restart: np.ndarray | None = None) -> np.ndarray:
    """Consecutive True ``flags`` (N, n) ending at each row, continuing ``carry`` (n,) from before
    the block; a ``restart`` row (N,) bool starts over from zero."""
    flags = np.asarray(flags, dtype=bool)
    if restart is not None:
        flags = flags & ~restart[:, None]
    if len(flags) == 1:
        return np.where(flags, carry + 1, 0)
    count = np.cumsum(flags, axis=0)
    reset = np.maximum.accumulate(np.where(flags, 0, count), axis=0)
    since_block = ~np.cumsum(~flags, axis=0).astype(bool)  # no False yet in this column
    return count - reset + np.where(since_block, carry, 0)


def last_true_value(flags: np.ndarray, values: np.ndarray, initial: float | np.ndarray) -> np.ndarray:
    """For each row, ``values`` (N,) or (N, n) at the latest row at or before it where ``flags``
    (N,) or (N, n) holds (column by column), else ``initial`` (scalar, or (n,))."""
    flags = np.asarray(flags, dtype=bool)
    values = np.asarray(values)
    columns = values.ndim == 2
    if len(flags) == 1:
        return np.where(flags, values if columns else values.reshape((1,) + (1,) * (flags.ndim - 1)),
                        initial)
    rows = np.arange(len(flags)).reshape((-1,) + (1,) * (flags.ndim - 1))
    index = np.maximum.accumulate(np.where(flags, rows, -1), axis=0)
    picked = (np.take_along_axis(values, np.maximum(index, 0), axis=0) if columns
              else values[np.maximum(index, 0)])
    return np.where(index >= 0, picked, initial)


def cusum(steps: np.ndarray, g0: np.ndarray) -> np.ndarray:
    """States of the CUSUM ``g_k = max(0, g_{k-1} + x_k)`` over rows of ``steps`` x (N, ...)
    from ``g_{-1} = g0`` (...); returns (N, ...). In closed form, ``g_k = S_k - min(-g_{-1},
    min_{j<=k} S_j)`` with S the running sum of x."""
    if len(steps) == 1:
        return np.maximum(0.0, g0 + steps[0])[None]
    total = np.cumsum(steps, axis=0)
    return total - np.minimum(-g0, np.minimum.accumulate(total, axis=0))


def bounded_cusum(steps: np.ndarray, g0: np.ndarray, ceiling: float) -> np.ndarray:
    """States of the CUSUM held below a ceiling, ``g_k = min(ceiling, max(0, g_{k-1} + x_k))``,
    over rows of ``steps`` x (N, ...) from ``g_{-1} = g0`` (...); returns (N, ...).

    Each row is the map ``g -> clip(g + a, lo, hi)``; two such maps compose into one of the same
    form, so the states are a prefix scan of compositions (log2(N) vectorised steps)."""
    if len(steps) == 1:
        return clip(g0 + steps[0], 0.0, ceiling)[None]
    offset = np.array(steps, dtype=float)
    low, high = np.zeros_like(offset), np.full_like(offset, ceiling)
    _compose_clips(offset, low, high)
    return clip(g0 + offset, low, high)


def _compose_clips(offset: np.ndarray, low: np.ndarray, high: np.ndarray) -> None:
    """Rows (N, ...) of maps ``g -> clip(g + offset_k, low_k, high_k)`` replaced, in place, by
    their compositions from the first row to each (a prefix scan: log2(N) vectorised steps)."""
    shift = 1
    while shift < len(offset):  # row k after row k - shift: clip(clip(g + a1, l1, h1) + a2, l2, h2)
        later = slice(shift, None)
        earlier = slice(None, -shift)
        low[later], high[later], offset[later] = (
            clip(low[earlier] + offset[later], low[later], high[later]),
            clip(high[earlier] + offset[later], low[later], high[later]),
            offset[earlier] + offset[later])
        shift *= 2


def clip_recursion(low: np.ndarray, high: np.ndarray, x0: float) -> np.ndarray:
    """States of ``x_k = min(max(x_{k-1}, low_k), high_k)`` (``low_k <= high_k``; -inf and inf
    leave the state as it is, ``low_k == high_k`` sets it) over rows (N,) from ``x_{-1} = x0``;
    returns (N,). :func:`bounded_cusum`'s maps without the step, composed alike (a prefix scan);
    a clip does no arithmetic, so any chunking gives the same bits."""
    if len(low) == 1:
        return clip(x0, low, high)
    low, high = np.array(low, dtype=float), np.array(high, dtype=float)
    _compose_clips(np.zeros_like(low), low, high)  # no step: the offsets stay 0
    return clip(x0, low, high)


class ExponentialAverage:
    """Exponential averages of n signals whose memory fills as samples come: ``m_k = m_{k-1} +
    (g_k / w_k) (x_k - m_{k-1})`` with ``w_k = w_{k-1} + g_k (1 - w_{k-1})`` the share of the memory
    that holds samples, so it starts as the plain mean of the first samples (no bias towards 0). A
    gain g_k = 1 - exp(-dt / time constant) advances it by an interval; g_k = 0 leaves it as it is.
    """

    def __init__(self, size: int) -> None:
        self.value = np.zeros(size)
        self.weight = np.zeros(size)  # [-], 0: no sample yet
        self._after = None  # (average, weight) after each row of the last advance, for rewind

    def advance(self, gain: np.ndarray, values: np.ndarray,
                keep: float | np.ndarray = 1.0) -> tuple[np.ndarray, np.ndarray]:
        """Take rows of ``values`` (N, n) with their gains (N, n) in [0, 1]; ``keep`` (N, n) 0
        forgets the memory before a row. Returns the average and its weight before each row, both
        (N, n)."""
        weight = scalar_recursion(keep * (1.0 - gain), gain, self.weight)
        step = np.divide(gain, weight, out=np.zeros_like(weight), where=weight > 0)
        average = scalar_recursion(1.0 - step, step * values, self.value)
        if len(average) == 1:
            before = (self.value[None], self.weight[None])
        else:
            before = (np.concatenate([self.value[None], average[:-1]]),
                      np.concatenate([self.weight[None], weight[:-1]]))
        self._after = (average, weight)
        self.value, self.weight = average[-1], weight[-1]
        return before

    def after(self) -> np.ndarray:
        """The average after each row of the last :meth:`advance` (N, n)."""
        return self._after[0]

    def rewind(self, row: int) -> None:
        """Go back to the state after ``row`` of the last :meth:`advance`."""
        average, weight = self._after
        self.value, self.weight = average[row], weight[row]


def savgol_filter(values: np.ndarray, window: int, order: int, deriv: int = 0,
                  delta: float = 1.0) -> np.ndarray:
    """Savitzky-Golay smoothing (``deriv`` 0) or derivative along axis 0 of ``values`` (N, ...)
    sampled every ``delta``: the least-squares polynomial of ``order`` through each ``window``
    (odd) samples, evaluated at the middle one; the first and last ``window // 2`` samples from the
    polynomial of the first and last window (``scipy.signal.savgol_filter``'s ``mode='interp'``,
    which needs a 0.7 s import of scipy.signal, with scipy.stats, on the 2-core dev machine).
    """
    values = np.asarray(values, dtype=float)
    count = len(values)
    if window % 2 == 0 or not order < window <= count:
        msg = (f'savgol_filter: window must be odd, above order {order} and at most the '
               f'{count} samples; got {window}')
        raise ValueError(msg)
    half = window // 2
    positions = np.arange(-half, half + 1, dtype=float)
    powers = np.arange(order + 1)
    fit = np.linalg.pinv(positions[:, None] ** powers)  # window values -> polynomial coefficients
    falling = np.array([np.prod(np.arange(p - deriv + 1, p + 1)) for p in powers], dtype=float)
    basis = np.where(powers >= deriv, falling * positions[:, None] ** np.maximum(powers - deriv, 0), 0.0)
    at = basis @ fit / delta ** deriv  # (window, window): row i = the derivative at position i
    out = np.empty_like(values)
    windows = np.lib.stride_tricks.sliding_window_view(values, window, axis=0)  # (N-W+1, ..., W)
    out[half:count - half] = np.tensordot(windows, at[half], axes=([-1], [0]))
    out[:half] = np.tensordot(at[:half], values[:window], axes=([1], [0]))
    out[count - half:] = np.tensordot(at[half + 1:], values[count - window:], axes=([1], [0]))
    return out
