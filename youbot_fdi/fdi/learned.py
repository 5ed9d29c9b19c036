"""Learned corrections of the physics model (issue 12): where the physics runs out, learn from the
user's own nominal recordings what the model misses, and evaluate it with numpy on the robot.

Two gaps, each learned per wheel from that wheel's own operating point over the interval:

- **Friction** the viscous + Coulomb model does not have: omni and mecanum rollers, a gearbox run
  in more one way than the other, friction that depends on the direction of travel::

      f_w = clip(W[w, :3] . (s_w, |s_w|, v_w), -limit_w, limit_w)             [N·m]
      s_w = tanh(v_w / speed_scale)

  with v_w the wheel's mean speed over the interval [rad/s] (kinematic convention): a change of
  the Coulomb level (s), a direction-independent offset while moving (|s|; with s it makes
  friction differ by direction) and of the viscous slope (v). Added to the explained torque and
  to the friction the observer and the command path work against.
- **Inertia as the samples see it**: the torque residual compares the mean of two current samples
  with the torque the speed change needs, but the current within the interval follows the
  firmware's loop, not a straight line between them, so the inertia that fits the samples is not
  the body's (docs/fdi.md, "Known limit"), and on a real base the rollers and the drive train add
  their own. A per-wheel share of the acceleration::

      i_w = clip(W[w, 3] . a_w, -inertia_limit_w, inertia_limit_w)            [N·m]

  with a_w the wheel's speed change over the interval divided by its length [rad/s²], 0 where
  the current reaches the firmware's limit (:data:`SATURATION_SHARE`),
  added to the explained torque only (the friction the predictions work against is unchanged).

``limit_w`` and ``inertia_limit_w`` are the largest corrections seen in calibration, and the
correction holds only at operating points the calibration covered: each wheel's mean speed (where
it keeps a friction part) and acceleration (where it keeps an inertia part) within the range
``identify`` saw, widened by ``calibration_range_margin`` of its span on each side. Outside it
that wheel falls back to the physics (no correction) and the decision says so (a ``WARN``
``unseen_operating_point``): what was learned there is a guess. Each wheel keeps a group of features (friction,
inertia, or both) only where it lowers what is left of its residual's mean square out of sample by
at least ``MIN_GAIN`` (fitted on part of the recording, tried on the rest); a recording with
nothing systematic to learn gives no correction at all. The bounds stay fitted to the physics
residuals: the correction takes the nominal residual further inside them. Bounds fitted to the
corrected residuals were tried (with the inertia part not yet kept from the current limit): on the
independent simulator (16 s calibration) a friction x1.8 surface change on every wheel then raised
a torque_loss alarm in 4 of 4 seeds (physics only: 2; the correction with the physics bounds: 0).

What was tried on the Robotino recordings (calibrated on the green covering, judged on the
others): features of the other wheels (the direction of the whole base) explain a third of the
calibration residual but transfer badly (false alarms x5 with bounds fitted to the corrected
residuals; a fault hidden with the physics bounds); scaling the correction with the load factor
raised false alarms. The current's change over the interval explains much of one simulator's
residual and makes another's worse out of sample: not a feature.

:class:`TorqueCorrection` is the evaluation (a few vector operations, for a sample or a block),
shared by the live nodes and ``replay``; :func:`fit_torque_correction` is the fit ``identify``
runs (ridge least squares, numpy only: no training dependency).
"""
from dataclasses import dataclass
from functools import cache, cached_property

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
#: The inertial part applies only where the current is below this share of the firmware's limit at
#: both ends of the interval. At the limit at both ends the current is flat and the two samples are
#: the mean torque; entering or leaving the limit within the interval, they miss it by an amount
#: that depends on when the limit was reached, not linearly on the acceleration: a correction
#: fitted there held out of sample in calibration and raised false alarms on a saturating drive.
SATURATION_SHARE = 0.95
FEATURES = 4  # per wheel: smooth sign, its magnitude, speed (friction); acceleration (inertia)
#: The feature groups a wheel may keep (columns of the weights), each validated out of sample.
FRICTION, INERTIA = (0, 1, 2), (3,)
GROUPS = (FRICTION, INERTIA)


@dataclass(frozen=True)
class TorqueCorrection:
    """The learned torque correction (see the module doc)."""

    weights: np.ndarray  # (n, FEATURES) [N·m per feature]
    limit: np.ndarray  # (n,) largest |friction correction| seen in calibration [N·m]
    speed_scale: float  # [rad/s] of the smooth sign
    inertia_limit: np.ndarray  # (n,) largest |inertial correction| seen in calibration [N·m]
    #: (n, 2) lowest and highest mean wheel speed [rad/s] and inertial feature [rad/s²] seen in
    #: calibration; None: not recorded (a file written before the ranges), every point is seen
    speed_range: np.ndarray = None
    acceleration_range: np.ndarray = None
    range_margin: float = 0.0  # the ranges are widened by this share of their span each side [-]

    @classmethod
    def from_mapping(cls, data, n, source='<params>'):
        """From the ``learned.torque`` mapping of a parameter file; ConfigError if malformed. A
        file written before the inertial part (weights n x 3) reads as friction only."""
        try:
            weights = np.array(data['weights'], dtype=float)
            limit = np.array(data['limit'], dtype=float)
            speed_scale = float(data['speed_scale'])
            inertia_limit = np.array(data.get('inertia_limit', np.zeros(n)), dtype=float)
            ranges = [None if data.get(key) is None else np.array(data[key], dtype=float)
                      for key in ('speed_range', 'acceleration_range')]
        except (KeyError, TypeError, ValueError, AttributeError) as err:
            msg = (f'{source}: learned.torque needs weights ({n}x{FEATURES}), limit ({n}), '
                   f'inertia_limit ({n}) and speed_scale: {err}')
            raise ConfigError(msg) from err
        if weights.ndim == 2 and weights.shape[1] == len(FRICTION):
            weights = np.hstack([weights, np.zeros((len(weights), len(INERTIA)))])
        arrays = (weights, limit, inertia_limit)
        if weights.shape != (n, FEATURES) or limit.shape != (n,) or inertia_limit.shape != (n,) \
                or not speed_scale > 0 or not all(np.all(np.isfinite(a)) for a in arrays) \
                or np.any(limit < 0) or np.any(inertia_limit < 0):
            msg = (f'{source}: learned.torque must have weights {n}x{FEATURES}, limit and '
                   f'inertia_limit {n} (>= 0) and speed_scale > 0, finite; got {weights.shape}, '
                   f'{limit.shape}, {inertia_limit.shape}, {speed_scale}')
            raise ConfigError(msg)
        for key, found in zip(('speed_range', 'acceleration_range'), ranges):
            if found is not None and (found.shape != (n, 2) or not np.all(np.isfinite(found))
                                      or np.any(found[:, 0] > found[:, 1])):
                msg = f'{source}: learned.torque.{key} must be {n} finite [low, high] pairs'
                raise ConfigError(msg)
        return cls(weights, limit, speed_scale, inertia_limit, *ranges)

    def to_mapping(self):
        """The ``learned.torque`` mapping written by ``identify``."""
        mapping = {'weights': [[float(v) for v in row] for row in self.weights],
                   'limit': [float(v) for v in self.limit],
                   'inertia_limit': [float(v) for v in self.inertia_limit],
                   'speed_scale': float(self.speed_scale)}
        for key in ('speed_range', 'acceleration_range'):
            found = getattr(self, key)
            if found is not None:
                mapping[key] = [[float(low), float(high)] for low, high in found]
        return mapping

    def seen(self, mean_speed, acceleration):
        """(..., n) bool: the operating point (mean wheel speeds [rad/s], inertial features
        [rad/s²], (..., n)) is one the calibration covered, for what the wheel keeps: its speed
        where it has a friction part, its acceleration where it has an inertia part."""
        slow, fast, least, most = self._prepared[3]
        return ((mean_speed >= slow) & (mean_speed <= fast) & (acceleration >= least)
                & (acceleration <= most))

    def features(self, mean_speed, acceleration):
        """(..., n, FEATURES) features of mean wheel speeds [rad/s] and accelerations [rad/s²]
        (..., n)."""
        sign = np.tanh(mean_speed / self.speed_scale)
        return np.stack([sign, np.abs(sign), mean_speed, acceleration], axis=-1)

    @cached_property
    def _prepared(self):
        """The weights' columns, the negated limits and the widened ranges (-inf, inf where a
        wheel does not check that feature), laid out once: a live sample is a few small numpy
        operations (``youbot-fdi bench``)."""
        columns = tuple(np.ascontiguousarray(self.weights[:, k]) for k in range(FEATURES))
        bounds = []
        for found, used in ((self.speed_range, FRICTION), (self.acceleration_range, INERTIA)):
            if found is None:  # a file from before the ranges: every point counts as seen
                found = np.zeros((len(self.weights), 2))
                checked = np.zeros(len(self.weights), dtype=bool)
            else:  # only a wheel that keeps a part of this feature checks its range
                checked = np.any(self.weights[:, list(used)] != 0.0, axis=1)
            widen = self.range_margin * (found[:, 1] - found[:, 0])
            bounds += [np.where(checked, found[:, 0] - widen, -np.inf),
                       np.where(checked, found[:, 1] + widen, np.inf)]
        return columns, -self.limit, -self.inertia_limit, bounds

    def friction(self, mean_speed):
        """The friction part [N·m] (..., n) at mean wheel speeds (..., n) [rad/s]."""
        (w0, w1, w2, _), low, _, _ = self._prepared
        sign = np.tanh(mean_speed / self.speed_scale)
        return np.minimum(np.maximum(w0 * sign + w1 * np.abs(sign) + w2 * mean_speed, low),
                          self.limit)

    def inertial(self, acceleration):
        """The inertial part [N·m] (..., n) at wheel accelerations (..., n) [rad/s²], as
        :func:`inertial_feature` gives them (0 where the current is at its limit)."""
        (_, _, _, w3), _, low, _ = self._prepared
        return np.minimum(np.maximum(w3 * acceleration, low), self.inertia_limit)

    def __call__(self, mean_speed, acceleration):
        """The whole correction [N·m] (..., n)."""
        return self.friction(mean_speed) + self.inertial(acceleration)

    def applied(self, mean_speed, acceleration):
        """(friction part, inertial part, seen) (..., n) as the observer applies them: both parts
        0 where the operating point was not seen in calibration (:meth:`seen` false)."""
        seen = self.seen(mean_speed, acceleration)
        return (np.where(seen, self.friction(mean_speed), 0.0),
                np.where(seen, self.inertial(acceleration), 0.0), seen)


def wheel_mask(seen):
    """(...,) float: the wheels whose operating point was not seen (``seen`` (..., n) false) as
    a bit mask, bit w for wheel w (exact in a float for any wheel count a base has)."""
    return np.logical_not(seen) @ _bits(np.shape(seen)[-1])


@cache
def _bits(n):
    """The value of each wheel's bit, 2^w (n,) (made once per wheel count)."""
    return 2.0 ** np.arange(n)


def mask_wheels(mask, n):
    """The wheels (..., n) bool of :func:`wheel_mask` values ``mask`` (...,)."""
    bits = np.asarray(mask, dtype=np.int64)[..., None]
    return (bits >> np.arange(n)) & 1 == 1


def masked_wheels(mask, n):
    """The wheel indices of a :func:`wheel_mask` value."""
    return np.flatnonzero(mask_wheels(mask, n)).tolist()


def inertial_feature(acceleration, torque, prev_torque, max_torque):
    """The inertial feature (..., n): the wheel's acceleration [rad/s²] where its torque [N·m]
    (``torque`` and ``prev_torque``, the interval's ends, any sign) is below ``SATURATION_SHARE``
    of ``max_torque`` at both ends, else 0 (an unknown torque counts as at the limit)."""
    level = SATURATION_SHARE * max_torque
    inside = (np.abs(torque) < level) & (np.abs(prev_torque) < level)
    return np.where(inside, acceleration, 0.0)


def _ridge(x, y):
    """Ridge least squares of y (N,) on x (N, k), columns scaled to unit RMS; the weights (k,).
    Solved as an augmented least-squares problem, so constant or empty columns are harmless."""
    scale = np.sqrt(np.mean(x ** 2, axis=0))
    scale = np.where(scale > 0.0, scale, 1.0)
    k = x.shape[1]
    augmented = np.vstack([x / scale, np.sqrt(RIDGE * len(x)) * np.eye(k)])
    target = np.concatenate([y, np.zeros(k)])
    return np.linalg.lstsq(augmented, target, rcond=None)[0] / scale


def out_of_sample_gain(x, y, folds=FOLDS):
    """The smallest share of the mean square of y (N,) that a ridge fit on x (N, k) removes from a
    held-out part (``folds`` consecutive parts, each held out in turn): below 0, it adds."""
    gains = []
    for part in np.array_split(np.arange(len(y)), folds):
        rest = np.setdiff1d(np.arange(len(y)), part)
        left = y[part] - x[part] @ _ridge(x[rest], y[rest])
        gains.append(1.0 - np.mean(left ** 2) / max(np.mean(y[part] ** 2), 1e-300))
    return min(gains)


def _select(x, y):
    """The feature columns one wheel keeps (forward selection over :data:`GROUPS`): a group joins
    only where it lowers the held-out mean square left by ``MIN_GAIN`` of it; [] for none."""
    kept, left = [], 1.0  # the share of the mean square still unexplained out of sample
    for _ in range(len(GROUPS)):
        trials = {group: out_of_sample_gain(x[:, kept + list(group)], y)
                  for group in GROUPS if not set(group) & set(kept)}
        if not trials:
            break
        group, gain = max(trials.items(), key=lambda item: item[1])
        if 1.0 - gain > (1.0 - MIN_GAIN) * left:
            break
        kept, left = kept + list(group), 1.0 - gain
    return sorted(kept)


def fit_torque_correction(mean_speed, acceleration, residual, speed_scale, torque_floor):
    """Fit the correction to physics torque residuals (measured - explained, N·m).

    ``mean_speed`` [rad/s], ``acceleration`` [rad/s²] and ``residual`` (N, n) of a nominal
    recording (rows with a NaN are left out); ``torque_floor`` [N·m] is the size below which a
    correction is noise. Ridge least squares per wheel on standardised features; each wheel keeps
    the feature groups (:data:`GROUPS`) that each lower what is left of its residual's mean square
    out of sample by ``MIN_GAIN`` (``FOLDS`` consecutive parts, each held out in turn). Returns
    (TorqueCorrection, or None when nothing is learned; notes: why nothing was learned, or wheels
    whose correction was refused as a suspected fault).
    """
    n = mean_speed.shape[1]
    rows = (np.all(np.isfinite(residual), axis=1) & np.all(np.isfinite(mean_speed), axis=1)
            & np.all(np.isfinite(acceleration), axis=1)
            & (np.max(np.abs(mean_speed), axis=1) > MOVING_SCALES * speed_scale))
    if np.count_nonzero(rows) < MIN_ROWS:
        return None, [f'{np.count_nonzero(rows)} moving samples with effort; the correction needs '
                      f'{MIN_ROWS}: not learned']
    unfitted = TorqueCorrection(np.zeros((n, FEATURES)), np.full(n, np.inf), speed_scale,
                                np.full(n, np.inf))
    phi = unfitted.features(mean_speed[rows], acceleration[rows])  # (N, n, FEATURES)
    target = residual[rows]
    weights = np.zeros((n, FEATURES))
    for w in range(n):
        # Validated out of sample: fitted on all but one consecutive part of the recording, each
        # part in turn, the correction must lower that part's residual by MIN_GAIN on every fold,
        # or it is noise fitted (or an effect too small to be worth carrying to another floor).
        group = _select(phi[:, w], target[:, w])
        if group:
            weights[w, group] = _ridge(phi[:, w, group], target[:, w])
    fitted = TorqueCorrection(weights, np.full(n, np.inf), speed_scale, np.full(n, np.inf))
    friction = fitted.friction(mean_speed[rows])
    inertial = fitted.inertial(acceleration[rows])
    rms = np.sqrt(np.mean((friction + inertial) ** 2, axis=0))
    notes = []
    for w in range(n):
        others = np.median(np.delete(rms, w)) if n > 1 else 0.0
        if rms[w] > torque_floor and rms[w] > GUARD_RATIO * others:
            notes.append(f'wheel {w}: its correction ({rms[w]:.3g} N·m RMS) is '
                         f'{rms[w] / max(others, 1e-12):.1f}x the other wheels\'; a fault in the '
                         'nominal recording? not learned for it')
            weights[w] = 0.0
            friction[:, w] = inertial[:, w] = 0.0
    if not np.any(weights):
        return None, notes + ['no wheel\'s residual has a part the features explain: physics only']
    covered = np.all(np.isfinite(mean_speed), axis=1) & np.all(np.isfinite(acceleration), axis=1)
    ranges = [np.stack([np.min(v[covered], axis=0), np.max(v[covered], axis=0)], axis=1)
              for v in (mean_speed, acceleration)]
    return TorqueCorrection(weights, np.max(np.abs(friction), axis=0), speed_scale,
                            np.max(np.abs(inertial), axis=0), *ranges), notes
