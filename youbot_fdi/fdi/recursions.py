"""Linear recursions over a whole block of samples at once (the batched replay's building blocks).

Each function equals its one-sample-at-a-time loop up to floating-point rounding; for a block of
one sample it is that loop.
"""
import numpy as np


def matvec(matrices, vectors):
    """``matrices @ vectors`` row by row: (N, d, m) with (N, m) -> (N, d)."""
    return np.matmul(matrices, vectors[..., None])[..., 0]


def affine_recursion(a, b, x0):
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


def scalar_recursion(a, b, x0):
    """States of ``x_k = a_k x_{k-1} + b_k`` with a scalar ``a_k`` per row: a (N,), b (N, d),
    x0 (d,); returns (N, d). Exponential smoothing with a varying step, as a prefix scan."""
    n = len(b)
    if n == 0:
        return np.empty((0, len(x0)))
    a, b = np.array(a, dtype=float), np.array(b, dtype=float)
    shift = 1
    while shift < n:
        b[shift:] += a[shift:, None] * b[:-shift]
        a[shift:] *= a[:-shift]
        shift *= 2
    return a[:, None] * x0 + b


def run_lengths(flags, carry, restart=None):
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


def last_true_value(flags, values, initial):
    """For each row, ``values`` at the latest row at or before it where ``flags`` (N,) holds, else
    ``initial``."""
    if len(flags) == 1:
        return np.where(flags, values, initial)
    index = np.maximum.accumulate(np.where(flags, np.arange(len(flags)), -1))
    return np.where(index >= 0, np.asarray(values)[np.maximum(index, 0)], initial)
