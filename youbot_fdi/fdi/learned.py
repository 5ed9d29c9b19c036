"""Learned corrections of the physics model (issue 12): where the physics runs out, learn from the
user's own nominal recordings what the model misses, and evaluate it with numpy on the robot.

What the physics misses most on real bases is friction that depends on the direction of travel
and on speed in ways the viscous + Coulomb model does not have: omni and mecanum rollers, a
gearbox run in more one way than the other. The torque correction is linear in features of each
wheel's own operating point over the interval::

    c_w = clip(W[w] . (s_w, |s_w|, v_w), -limit_w, limit_w)          [N·m]
    s_w = tanh(v_w / speed_scale)

with v_w the wheel's mean speed over the interval [rad/s] (kinematic convention): a change of the
Coulomb level (s), a direction-independent offset while moving (|s|; with s it makes friction
differ by direction) and of the viscous slope (v). It is added to the explained torque (and so
to what the observer and the command path take as friction); the load factor and the bounds keep
using the physics friction, and the bounds are fitted to the physics residuals. ``limit_w`` is the
largest correction seen in calibration: outside the operating range the data covered it does not
grow. A wheel keeps its correction only where it lowers the residual's mean square out of sample
by ``MIN_GAIN`` (fitted on part of the recording, tried on the rest); a recording with nothing
systematic to learn gives no correction at all.

What was tried on the Robotino recordings (calibrated on the green covering, judged on the
others): features of the other wheels (the direction of the whole base) explain a third of the
calibration residual but transfer badly (false alarms x5 with bounds fitted to the corrected
residuals; a fault hidden with the physics bounds); scaling the correction with the load factor
raised false alarms; the per-wheel correction here, fitted on the whole calibration, changed the
false alarms by -24 % or +14 % depending on one wheel's tiny correction: noise. Validated out of
sample, no wheel's correction holds on those recordings, so none is learned there.

:class:`TorqueCorrection` is the evaluation (one matrix product, for a sample or a block), shared by
the live nodes and ``replay``; :func:`fit_torque_correction` is the fit ``identify`` runs (ridge
least squares, numpy only: no training dependency).
"""
from dataclasses import dataclass

import numpy as np

from youbot_fdi.errors import ConfigError

#: Ridge regularisation, relative to the number of samples (features scaled to unit RMS first).
RIDGE = 1e-3
#: Rows used for the fit only where some wheel turns faster than this many ``speed_scale`` s.
MOVING_SCALES = 1.0
#: A wheel whose correction is this many times the median of the others' (RMS over the recording)
#: is suspected of a fault in the nominal recording: its correction is not learned.
GUARD_RATIO = 3.0
MIN_ROWS = 200  # fewer moving rows than this: nothing is learned
FOLDS = 2  # a wheel keeps its correction only if it lowers the residual of every held-out part ...
MIN_GAIN = 0.05  # ... by at least this share of its mean square (less is not worth the risk)
FEATURES = 3  # per wheel: smooth sign, its magnitude, speed


@dataclass(frozen=True)
class TorqueCorrection:
    """The learned torque correction (see the module doc)."""

    weights: np.ndarray  # (n, FEATURES) [N·m per feature]
    limit: np.ndarray  # (n,) largest |correction| seen in calibration [N·m]
    speed_scale: float  # [rad/s] of the smooth sign

    @classmethod
    def from_mapping(cls, data, n, source='<params>'):
        """From the ``learned.torque`` mapping of a parameter file; ConfigError if malformed."""
        try:
            weights = np.array(data['weights'], dtype=float)
            limit = np.array(data['limit'], dtype=float)
            speed_scale = float(data['speed_scale'])
        except (KeyError, TypeError, ValueError) as err:
            msg = (f'{source}: learned.torque needs weights ({n}x{FEATURES}), limit ({n}) and '
                   f'speed_scale: {err}')
            raise ConfigError(msg) from err
        if weights.shape != (n, FEATURES) or limit.shape != (n,) or not speed_scale > 0 \
                or not (np.all(np.isfinite(weights)) and np.all(np.isfinite(limit))) or np.any(limit < 0):
            msg = (f'{source}: learned.torque must have weights {n}x{FEATURES}, limit {n} (>= 0) and '
                   f'speed_scale > 0, finite; got {weights.shape}, {limit.shape}, {speed_scale}')
            raise ConfigError(msg)
        return cls(weights, limit, speed_scale)

    def to_mapping(self):
        """The ``learned.torque`` mapping written by ``identify``."""
        return {'weights': [[float(v) for v in row] for row in self.weights],
                'limit': [float(v) for v in self.limit], 'speed_scale': float(self.speed_scale)}

    def features(self, mean_speed):
        """(..., n, FEATURES) features of mean wheel speeds (..., n) [rad/s]."""
        sign = np.tanh(mean_speed / self.speed_scale)
        return np.stack([sign, np.abs(sign), mean_speed], axis=-1)

    def __call__(self, mean_speed):
        """The correction [N·m] (..., n) for mean wheel speeds (..., n) [rad/s]."""
        sign = np.tanh(mean_speed / self.speed_scale)
        w = self.weights
        return np.clip(w[:, 0] * sign + w[:, 1] * np.abs(sign) + w[:, 2] * mean_speed,
                       -self.limit, self.limit)


def _ridge(x, y):
    """Ridge least squares of y (N,) on x (N, k), columns scaled to unit RMS; the weights (k,).
    Solved as an augmented least-squares problem, so constant or empty columns are harmless."""
    scale = np.sqrt(np.mean(x ** 2, axis=0))
    scale = np.where(scale > 0.0, scale, 1.0)
    k = x.shape[1]
    augmented = np.vstack([x / scale, np.sqrt(RIDGE * len(x)) * np.eye(k)])
    target = np.concatenate([y, np.zeros(k)])
    return np.linalg.lstsq(augmented, target, rcond=None)[0] / scale


def fit_torque_correction(mean_speed, residual, speed_scale, torque_floor):
    """Fit the correction to physics torque residuals (measured - explained, N·m).

    ``mean_speed`` (N, n) [rad/s] and ``residual`` (N, n) of a nominal recording (rows with a
    NaN residual are left out); ``torque_floor`` [N·m] is the size below which a correction is
    noise. Ridge least squares per wheel on standardised features; a wheel keeps its correction
    only where it lowers the residual's mean square out of sample by ``MIN_GAIN`` (``FOLDS``
    consecutive parts, each held out in turn). Returns (TorqueCorrection, or None when nothing is learned; notes: why nothing was
    learned, or wheels whose correction was refused as a suspected fault).
    """
    n = mean_speed.shape[1]
    rows = (np.all(np.isfinite(residual), axis=1) & np.all(np.isfinite(mean_speed), axis=1)
            & (np.max(np.abs(mean_speed), axis=1) > MOVING_SCALES * speed_scale))
    if np.count_nonzero(rows) < MIN_ROWS:
        return None, [f'{np.count_nonzero(rows)} moving samples with effort; the correction needs '
                      f'{MIN_ROWS}: not learned']
    unfitted = TorqueCorrection(np.zeros((n, FEATURES)), np.full(n, np.inf), speed_scale)
    phi = unfitted.features(mean_speed[rows])  # (N, n, FEATURES)
    target = residual[rows]
    weights = np.stack([_ridge(phi[:, w], target[:, w]) for w in range(n)])
    # Validated out of sample: fitted on all but one consecutive part of the recording, each part
    # in turn, the correction must lower that part's residual on every fold by MIN_GAIN, or it is
    # noise fitted (or an effect too small to be worth carrying to another floor).
    parts = np.array_split(np.arange(len(target)), FOLDS)
    holds = np.ones(n, dtype=bool)
    for part in parts:
        rest = np.setdiff1d(np.arange(len(target)), part)
        for w in range(n):
            fold = _ridge(phi[rest, w], target[rest, w])
            left = target[part, w] - phi[part, w] @ fold
            holds[w] &= np.mean(left ** 2) < (1.0 - MIN_GAIN) * np.mean(target[part, w] ** 2)
    weights[~holds] = 0.0
    fitted = TorqueCorrection(weights, np.full(n, np.inf), speed_scale)(mean_speed[rows])
    rms = np.sqrt(np.mean(fitted ** 2, axis=0))
    notes = []
    for w in range(n):
        others = np.median(np.delete(rms, w)) if n > 1 else 0.0
        if rms[w] > torque_floor and rms[w] > GUARD_RATIO * others:
            notes.append(f'wheel {w}: its correction ({rms[w]:.3g} N·m RMS) is '
                         f'{rms[w] / max(others, 1e-12):.1f}x the other wheels\'; a fault in the '
                         'nominal recording? not learned for it')
            weights[w] = 0.0
            fitted[:, w] = 0.0
    if not np.any(weights):
        return None, notes + ['no wheel\'s residual has a part the features explain: physics only']
    return TorqueCorrection(weights, np.max(np.abs(fitted), axis=0), speed_scale), notes
