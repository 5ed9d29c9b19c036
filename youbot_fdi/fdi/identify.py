"""Identify the model's parameters from a nominal recording (either control mode).

1. **Dynamics by Bayesian linear least squares.** ``tau = M(m, J_z, J_w) a + D w + F_c tanh(w / v_s)
   s_k`` is linear in (m, J_z, J_w, D_i, F_c,i) because M = m P_xy + J_z P_z + J_w I; the contact
   law's rolling share s_k (model/dynamics.py, ``roller_friction_ratio`` k) is searched on a grid,
   a linear fit each. Speeds are differentiated and torques smoothed with the same Savitzky-Golay
   filter (rows whose window spans a gap left out); the prior profile is a Gaussian prior, each
   parameter gets a standard deviation (posterior covariance, at least the block jackknife's),
   and the ones the recording does not excite are named and stay at the prior (a drive without
   rotation says nothing about J_z).
2. **The report's friction sweep** (Fig. 5.10): the open-loop model driven by the measured currents
   for D on a grid around the fitted one, RMSE against the measured speeds.
3. **Firmware PI gains and input delay.** Velocity-mode recordings: the command-path prediction
   fitted to the measured speeds over at most SEARCH_SECONDS of the recording: the delay on a
   2.5 ms grid (the prediction is not smooth in it) and, at each delay tried, least squares on
   log gains (a slower loop mimics a late one: the two are fitted together). Current-mode
   recordings: the delay that best matches the measured to the commanded effort. The FDI
   predicts with the delay (``input_delay``).
4. **Fit quality**: NRMSE per wheel (RMSE / range of the measured speed) of the current-driven and
   the command-driven predictions, to test the report's "< 1 %" claim.
5. **Bounds** as functions of the operating point: the residual generator run over the recording
   with the identified model; each bound's floor and weights (:data:`~youbot_fdi.fdi.residuals.
   BOUND_TERMS`) by linear quantile regression of |r| on its features (``bound_quantile``, robust
   to outliers: one bad sample moves a quantile by one sample), times ``bound_margin``. The
   coverage (share of the nominal samples inside the bound) is reported per family.
6. **Sample interval**: the median interval, so timeouts scale with the robot's rate.

A recording whose effort is a magnitude only (``drive.signed_effort: false``) is signed by the
explained torque, refitted a few times (the sign of friction and inertia, not of noise).
"""
from dataclasses import dataclass, replace
import functools
import math
from typing import NamedTuple

import numpy as np
import scipy.linalg
import scipy.optimize

from youbot_fdi.errors import FdiError
from youbot_fdi.fdi import alarm_rate
from youbot_fdi.fdi.learned import fit_torque_correction, inertial_feature
from youbot_fdi.fdi.observer import ModelObserver, commands_in_force
from youbot_fdi.fdi.recursions import savgol_filter
from youbot_fdi.fdi.residuals import (BOUND_TERMS, bound_weights, FAMILIES, ResidualEvaluator,
                                      ResidualGenerator, ResidualSpread)
from youbot_fdi.fdi.settings import FdiSettings
from youbot_fdi.model.dynamics import rolling_share
from youbot_fdi.model.firmware import response_time_constant
from youbot_fdi.model.profile import ModelProfile, PlatformModel
from youbot_fdi.samples import CommandBatch, EFFORT, JointBatch, VELOCITY

SAVGOL_WINDOW = 9  # samples
SAVGOL_ORDER = 2
#: The dynamics fit's smoothing window grows until the acceleration's noise is at most this share
#: of its spread (the inertias' errors-in-variables bias, :func:`smoothing_window`) [-] ...
ATTENUATION_SHARE = 0.01
#: ... by this factor per step (a search over windows, not a fine grid) [-]
WINDOW_GROWTH = 1.25
#: ... but keeps at least this share of the rows the shortest window keeps evenly sampled [-],
KEPT_SHARE = 0.5
#: ... and spans at most the time the shortest window spans at the youBot's 100 Hz [s].
SMOOTHING_TIME = SAVGOL_WINDOW * 0.01
#: The dynamics fit's first pass, which measures the noise, weighs the prior as if the noise
#: were this share of the torque's spread: barely (the data decide), yet never singular.
NOISE_PROBE = 1e-3
#: Rows of residual autocorrelation the fit's covariance counts (correlation_inflation): the
#: Savitzky-Golay window's reach several times over.
INFLATION_LAGS = 8  # smoothing windows
#: A design column shorter than this share of the longest is scaled as if it had that length.
COLUMN_FLOOR = 1e-9
#: Consecutive stretches of a recording the dynamics fit's jackknife leaves out one at a time.
JACKKNIFE_BLOCKS = 10
#: An interval longer than this many median intervals is a gap (a missed sample or more) [-].
UNEVEN_INTERVAL = 1.5
#: The report's friction sweep (Fig. 5.10) on a grid of these multiples of the fitted mean viscous
#: friction (the report's fixed 0.010-0.045 N·m·s/rad put the optimum at its edge on robots
#: whose friction lies outside it) [-]
SWEEP_FACTORS = np.linspace(0.25, 2.5, 10)
FLOOR_FRACTION = 0.25  # a learned floor never goes below this fraction of the configured one
MIN_SAMPLES = 50
DELAY_STEP = 0.0025  # input-delay grid step [s]
MAX_DELAY = 0.08  # [s]; the grid starts one sample interval early (commands stamped late)
WATCHDOG = FdiSettings().command_timeout  # the shim's command watchdog, the searches' default [s]
QUANTILE_ROWS = 6000  # rows the quantile regression uses at most (a random, seeded subset)
#: The range of a bound feature calibration covered: this quantile of its values, and the same for
#: the largest wheel torque measured (the whole range: it is what was seen).
RANGE_QUANTILE = 1.0
#: How fast the base drove: these quantiles of its wheel speeds' norm while it moved (a start's or
#: a stop's few samples are not a speed calibration drove at).
SPEED_QUANTILES = (0.05, 0.95)
#: The searches over the input delay and the firmware gains simulate the command path many
#: times: they run on the recording decimated to at most SEARCH_RATE and SEARCH_SAMPLES samples
#: (the discretisation is exact for any interval; every command is kept). The fits of the
#: dynamics and the bounds use every sample.
SEARCH_RATE = 100.0  # [Hz]
SEARCH_SAMPLES = 6000
#: The searches' cost grows with the driving they simulate (the firmware loop is stepped period by
#: period where it saturates): they see at most SEARCH_SECONDS of a longer recording, in
#: SEARCH_WINDOWS windows spread over all of it (the gains and the delay do not change along it).
SEARCH_SECONDS = 30.0  # [s]
SEARCH_WINDOWS = 6
#: The delay search: the grid every DELAY_COARSE_STEPS steps, then every step around the best.
DELAY_COARSE_STEPS = 4
MIN_INTEGRAL_SHARE = 0.05  # a P-only prior starts the gain fit at ki = this x kp [1/s]
SIGN_REFITS = 3  # fits of a magnitude-only effort, each signed by the previous fit
#: The PI-gain fit (least squares on log gains, the Jacobian by forward differences, then
#: Broyden's updates): the difference step on the log gains (a few per cent: the prediction is
#: piecewise smooth in the gains where the loop saturates), the tolerances on the log gains'
#: step and on the cost's relative change, and the residual evaluations least squares may make
#: (the forward differences' two simulations besides).
GAIN_DIFFERENCE_STEP = 0.02
GAIN_TOLERANCE = 0.01
GAIN_COST_TOLERANCE = 1e-4
GAIN_EVALUATIONS = 30
#: Roller friction ratios the dynamics fit tries (model/dynamics.py, the contact law) [-] ...
ROLLER_RATIOS = np.round(np.arange(0.0, 1.51, 0.125), 3)
#: ... and keeps one above 0 only where it lowers the torque fit's squared error by this share.
ROLLER_RATIO_MIN_GAIN = 0.05
#: Coulomb steps this many times wider than the model's smoothing, refitted to state how much
#: the parameters depend on the step's unknown width (a model-form uncertainty) [-].
COULOMB_STEP_WIDTHS = (10.0,)
#: The dynamics fit's first columns: mass, yaw inertia, wheel inertia (:func:`parameter_names`).
INERTIAS = 3


class IdentificationError(FdiError):
    """The recording cannot identify the model (too short, no effort, no motion)."""


@dataclass(frozen=True)
class RecordingArrays:
    """A recording as arrays, kinematic convention, SI."""

    time: np.ndarray  # (k,) header stamps [s]
    position: np.ndarray  # (k, n)
    velocity: np.ndarray  # (k, n)
    torque: np.ndarray  # (k, n)
    commands: list  # CommandSample list (driver convention, as recorded)
    damage: object = None  # youbot_fdi.bag.salvage.Damage of a damaged recording (read in part)
    # (K, n) which wheels answered in every sample read, those some wheels missed too (their
    # rows are not among the k above); None: every wheel answered every sample
    answered: np.ndarray = None

    @functools.cached_property
    def command_batch(self) -> CommandBatch:
        """The commands in stamp order as one :class:`~youbot_fdi.samples.CommandBatch` (built
        once: the searches run the generator over the same commands many times)."""
        commands = sorted(self.commands, key=lambda c: c.stamp)
        n = self.velocity.shape[1]
        return CommandBatch.from_samples(commands) if commands else CommandBatch.empty(n)


def require_samples(count, source=''):
    """Raise :class:`IdentificationError` unless ``count`` joint states are enough to identify."""
    if count < MIN_SAMPLES:
        msg = (f'{source or "recording"}: {count} usable joint states; identification needs at '
               f'least {MIN_SAMPLES}')
        raise IdentificationError(msg)


def _smooth(values, dt, deriv=0, window=SAVGOL_WINDOW):
    """Savitzky-Golay smoothing (or derivative) along time over ``window`` samples (odd); the
    window shrinks for short data."""
    window = min(window, len(values) if len(values) % 2 else len(values) - 1)
    return savgol_filter(values, window, SAVGOL_ORDER, deriv=deriv, delta=dt)


def smoothing_window(velocity, dt, noise):
    """The Savitzky-Golay window (odd, samples, at least SAVGOL_WINDOW, spanning at most
    SMOOTHING_TIME unless that is shorter) over which the speed
    readings ``velocity`` (k, n) [rad/s], sampled every ``dt`` [s] with ``noise`` [rad/s]
    (:func:`speed_noise`), give accelerations whose noise is at most ``ATTENUATION_SHARE`` of
    their spread. Why: the inertias are the coefficients of the acceleration, and noise in a
    regressor biases its coefficient towards zero by that share (errors in variables); a noisy
    reading sampled fast, differentiated over a few samples, is mostly noise (inertia found at
    a tenth of the truth at 500 Hz). The window's first-derivative filter (order 2, middle
    sample) is the straight line's, whose noise gain is 1 / (dt sqrt(sum j^2)), j = -m..m.
    The torque is smoothed alike, so the dynamics (linear in both) hold for the smoothed signals."""
    finite = velocity[np.isfinite(velocity).all(axis=1)]
    # never smoother in time than SMOOTHING_TIME: a faster rate buys a cleaner derivative over
    # the same span, not a longer smoothing of the motion
    half = SAVGOL_WINDOW // 2
    most = min((len(finite) - 1) // 2, max(half, int(SMOOTHING_TIME / dt) // 2))
    while half < most:
        gain_squared = 3.0 / (dt ** 2 * half * (half + 1) * (2 * half + 1))
        spread = float(np.var(savgol_filter(finite, 2 * half + 1, SAVGOL_ORDER, deriv=1, delta=dt)))
        if noise ** 2 * gain_squared <= ATTENUATION_SHARE * spread:
            break
        half = max(half + 1, int(half * WINDOW_GROWTH))
    return 2 * min(half, max(most, SAVGOL_WINDOW // 2)) + 1


def evenly_sampled(time, interval, window=SAVGOL_WINDOW):
    """Rows (k,) bool whose Savitzky-Golay ``window`` holds no interval longer than
    :data:`UNEVEN_INTERVAL` times the median ``interval`` [s]: the filter takes its rows as evenly
    spaced, so a window across a gap (a recording's pause, runs joined, a logger's stall) mixes
    speeds seconds apart into one "acceleration". Such rows are left out of the dynamics fit."""
    long = np.diff(time) > UNEVEN_INTERVAL * interval  # interval i lies between rows i and i + 1
    half = window // 2
    # Row r's window spans intervals r - half .. r + half - 1.
    counts = np.convolve(np.concatenate([np.zeros(half), long, np.zeros(half)]),
                         np.ones(2 * half), mode='valid')
    return counts[:len(time)] == 0


def readings_seen_share(time, commands, time_constant):
    """How much of the velocity loop's response to its commands the torque readings see [-]: the
    mean over the readings at ``time`` (k,) [s] of ``exp(-age / time_constant)``, ``age`` the
    time since the commands (:class:`~youbot_fdi.samples.CommandBatch`, velocity mode) last
    changed before the reading, over that mean over all time. The loop answers a change of its
    target with a torque that fades within ``time_constant`` [s]
    (:func:`~youbot_fdi.model.firmware.response_time_constant`): the wheels accelerate then.
    1: the readings fall at any phase of that answer (their mean is the torque's mean); below 1:
    they fall late in it (commands sent at each reading's instant reach the wheels just after it,
    and a loop faster than the readings has settled before the next one: the acceleration's
    torque happens between the readings, and inertias fitted to them come out low by about
    ``1 - share``). nan: no velocity commands to judge by. The commands' input delay is not
    known yet here; it only shifts the ages by a few milliseconds."""
    velocity = commands.velocity_mode
    stamps, values = commands.stamp[velocity], commands.values[velocity]
    if len(stamps) == 0 or len(time) == 0:
        return math.nan
    changed = np.concatenate([[True], np.any(values[1:] != values[:-1], axis=1)])
    changes = stamps[changed]
    latest = np.searchsorted(changes, time, side='left') - 1  # the last change strictly before
    judged = latest >= 0
    if not judged.any() or time[-1] <= changes[0]:
        return math.nan
    seen = float(np.mean(np.exp(-(time[judged] - changes[latest[judged]]) / time_constant)))
    # over all time from the first change to the last reading: each change's answer integrated
    # until the next change
    bounds = np.append(changes[changes < time[-1]], time[-1])
    held = np.diff(bounds)
    mean = float(np.sum(time_constant * -np.expm1(-held / time_constant)) / (time[-1] - changes[0]))
    return seen / mean if mean > 0.0 else math.nan


class FitRows(NamedTuple):
    """What the dynamics fit's rows are: ``by_speed`` the samples from the slowest to the fastest
    (the jackknife's regimes; None: time's only), ``correlation_lags`` how far the smoothing
    correlates them [rows]; and whether the fit states the jackknives' deviations (``stated``: a
    fit only compared by its error and values needs the posterior's alone)."""

    by_speed: np.ndarray | None = None
    correlation_lags: int = INFLATION_LAGS * SAVGOL_WINDOW
    stated: bool = True


class DynamicsFit(NamedTuple):
    """What :func:`fit_dynamics` found."""

    parameters: object  # DynamicParameters
    info: dict  # the fit's figures (roller_friction_ratio, conditioning, priors used, ...)
    fitted: np.ndarray  # the torques the fit explains on the rows it used, raveled (rows x n) [N·m]


def fit_dynamics(arrays, model, settings=None):
    """(m, J_z, J_w, D, F_c) by least squares with the prior profile's values as a Gaussian prior
    (:func:`_solve_dynamics`; ``settings`` (FdiSettings) give its spread), and the contact law's
    roller friction ratio k on the grid :data:`ROLLER_RATIOS` (each k a linear fit; k > 0 kept
    only where it lowers the torque fit's squared error by :data:`ROLLER_RATIO_MIN_GAIN`); a
    :class:`DynamicsFit` whose info holds each parameter's standard deviation and the ones the
    recording does not excite."""
    settings = settings or FdiSettings()
    if not np.all(np.isfinite(arrays.torque)):
        msg = 'the recording has no effort (measured current) on every sample; it is needed'
        raise IdentificationError(msg)
    dt = float(np.median(np.diff(arrays.time)))
    window = smoothing_window(arrays.velocity, dt, speed_noise(arrays))
    keep = evenly_sampled(arrays.time, dt, window)
    # A long window on a recording with dropped samples crosses a gap almost everywhere: it may
    # not leave out more than KEPT_SHARE of the rows the shortest window keeps (noise in the
    # acceleration traded for the recording's length), else it shrinks.
    shortest = evenly_sampled(arrays.time, dt).sum()
    while window > SAVGOL_WINDOW and keep.sum() < KEPT_SHARE * shortest:
        window = max(SAVGOL_WINDOW, 2 * int(window / WINDOW_GROWTH / 2) + 1)
        keep = evenly_sampled(arrays.time, dt, window)
    acceleration = _smooth(arrays.velocity, dt, deriv=1, window=window)
    speed, torque = _smooth(arrays.velocity, dt, window=window), _smooth(arrays.torque, dt, window=window)
    if keep.sum() >= MIN_SAMPLES:
        acceleration, speed, torque = acceleration[keep], speed[keep], torque[keep]
    forward = model.kinematics.forward_matrix
    p_xy = forward.T @ np.diag([1.0, 1.0, 0.0]) @ forward
    p_z = forward.T @ np.diag([0.0, 0.0, 1.0]) @ forward
    sign = np.tanh(speed / model.dynamics.parameters.coulomb_velocity_scale)
    slide = model.kinematics.roller_slide(speed)
    # the rollers' drag per unit D_r (WheelDynamics.roller_drag_shape): one column for the
    # base where it is fitted, else the prior's drag is known torque
    drag = model.dynamics.roller_drag_shape(speed).ravel()
    fit_drag = settings.fit_roller_drag
    known = 0.0 if fit_drag else model.dynamics.parameters.roller_drag * drag
    friction_signs = np.sign(speed).ravel()
    rows = FitRows(np.argsort(np.abs(speed).mean(axis=1), kind='stable'), INFLATION_LAGS * window)
    inertial = [(acceleration @ p_xy.T).ravel(), (acceleration @ p_z.T).ravel(), acceleration.ravel()]
    scale = model.dynamics.parameters.coulomb_velocity_scale

    def fit_law(ratio, width=1.0, with_drag=fit_drag, stated=False):
        """The fit with the contact law's roller friction ratio ``ratio``, the Coulomb step
        ``width`` times the model's and the rollers' drag fitted or not, with the jackknives'
        deviations if ``stated``: (squared error, ratio, params, info, fitted)."""
        step = sign if width == 1.0 else np.tanh(speed / (width * scale))
        coulomb = step * rolling_share(speed, slide, ratio) if ratio > 0.0 else step
        design = np.column_stack(inertial + _per_wheel_columns(speed) + _per_wheel_columns(coulomb)
                                 + ([drag] if with_drag else []))
        params, info, fitted, error = _fit_signed(
            design, torque, friction_signs, model, replace(settings, fit_roller_drag=with_drag),
            0.0 if with_drag else known, rows._replace(stated=stated))
        return error, ratio, replace(params, roller_friction_ratio=ratio), info, fitted

    fits = [fit_law(ratio) for ratio in ROLLER_RATIOS.tolist()]
    physics = fits[0]
    best = min(fits, key=lambda fit: fit[0])
    chosen = best if best[0] < (1.0 - ROLLER_RATIO_MIN_GAIN) * physics[0] else physics
    chosen = fit_law(chosen[1], stated=True)  # the same fit, now with its deviations
    # Model form. The Coulomb step is a smoothing of a width the model does not know: where the
    # plant's friction grows over a wider range of speeds (rolling resistance building up, a
    # Stribeck curve), the viscous and Coulomb terms share it differently; and the rollers'
    # drag (a term the model has, fitted only on request) takes a part of both where the base
    # glides. Where such a fit explains the torque as well (its squared error within
    # ROLLER_RATIO_MIN_GAIN of the chosen fit's, the margin by which a law counts as better) or
    # better, the parameters' change is a model-form uncertainty the stated deviation includes;
    # a law the data rule out adds none.
    names = parameter_names(model.dynamics.n_wheels, fit_drag)
    values = _parameter_values(chosen[2], fit_drag)
    form = np.zeros(len(names))
    laws = [(width, with_drag) for width in (1.0, *COULOMB_STEP_WIDTHS) for with_drag in {fit_drag, True}
            if (width, with_drag) != (1.0, fit_drag)]  # every other step and drag, not the chosen
    for other in (fit_law(chosen[1], width, with_drag) for width, with_drag in laws):
        if other[0] <= (1.0 + ROLLER_RATIO_MIN_GAIN) * chosen[0]:
            form = np.maximum(form, np.abs(_parameter_values(other[2], fit_drag) - values))
    stated = {name: max(chosen[3]['uncertainty'][name], float(f)) for name, f in zip(names, form)}
    info = {**chosen[3], 'uncertainty': stated,
            'uncertainty_law': {name: float(f) for name, f in zip(names, form)},
            'roller_friction_ratio': chosen[1]}
    return DynamicsFit(chosen[2], _inertias_seen(info, values[:INERTIAS], arrays, dt, model, settings),
                       chosen[4])


def _inertias_seen(info, found, arrays, interval, model, settings):
    """``info`` with the inertias' stated deviations widened to reach the prior where the torque
    readings, every ``interval`` [s], do not see the wheels accelerate
    (:func:`readings_seen_share`): the fitted values ``found`` (mass, yaw and wheel inertia) are
    low by about ``1 - share``, and once that may exceed the prior's own relative spread
    (``prior_inertia_sd``) the readings cannot tell the prior's value wrong: the deviation is at
    least the distance between the two (``uncertainty_unseen``). The values stay the fit's: they
    are what relates these readings to the speeds, which the FDI's predictions need."""
    time_constant = response_time_constant(model.dynamics, model.drive.torque_per_amp, model.firmware)
    share = readings_seen_share(arrays.time, arrays.command_batch, time_constant)
    info = {**info, 'readings_seen_share': None if math.isnan(share) else round(share, 3)}
    if not share < 1.0 - settings.prior_inertia_sd:
        return info
    names = parameter_names(model.dynamics.n_wheels)[:INERTIAS]
    prior = _parameter_values(model.dynamics.parameters)[:INERTIAS]
    unseen = {name: float(abs(p - f)) for name, p, f in zip(names, prior, found)}
    info['uncertainty'] = {name: max(sd, unseen.get(name, 0.0)) for name, sd in info['uncertainty'].items()}
    info['uncertainty_unseen'] = unseen
    info['inertias_unseen'] = (
        f'the torque readings see {share:.0%} of the velocity loop\'s answer to its commands '
        f'(it settles within {1000 * time_constant:.0f} ms; the readings come every '
        f'{1000 * interval:.0f} ms, late in it): the wheels accelerate between them, and the '
        'inertias fitted to the readings come out low')
    return info


def _parameter_values(params, roller_drag=False):
    """The values of :func:`parameter_names` from DynamicParameters ``params``, (k,)."""
    return np.array([params.mass, params.yaw_inertia, float(np.mean(params.wheel_inertia)),
                     *params.viscous_friction, *params.coulomb_friction,
                     *([params.roller_drag] if roller_drag else [])], dtype=float)


def _per_wheel_columns(law):
    """Design columns of a per-wheel term: wheel j's column is ``law[:, j]`` on its own rows."""
    k, n = law.shape
    out = []
    for j in range(n):
        mask = np.zeros((k, n))
        mask[:, j] = 1.0
        out.append((law * mask).ravel())
    return out


def _fit_signed(design, torque, friction_signs, model, settings, known=0.0, rows=FitRows()):
    """:func:`_solve_dynamics` of ``torque`` (k, n) less the ``known`` torque (raveled, or 0: a
    term held at its prior value); a magnitude-only effort is signed by the friction first
    (``friction_signs``, the speeds' signs, raveled), then by each fit's explained torque;
    ``rows`` (:class:`FitRows`) what the rows are (default: unsmoothed, in time order).
    Returns (params, info, fitted, squared error)."""
    n = torque.shape[1]
    if model.drive.signed_effort:
        target = torque.ravel() - known
        params, info, fitted = _solve_dynamics(design, target, model, n, settings, rows)
    else:
        signs = friction_signs
        for _ in range(SIGN_REFITS):
            target = np.abs(torque).ravel() * signs - known
            params, info, fitted = _solve_dynamics(design, target, model, n, settings, rows)
            signs = np.sign(fitted + known)
    return params, info, fitted, float(np.sum((target - fitted) ** 2))


def parameter_names(n, roller_drag=False):
    """The names of the dynamics fit's parameters, in its column order, for ``n`` wheels (and the
    rollers' drag where it is fitted)."""
    return ['mass', 'yaw_inertia', 'wheel_inertia', *(f'viscous_friction[{j}]' for j in range(n)),
            *(f'coulomb_friction[{j}]' for j in range(n)), *(['roller_drag'] if roller_drag else [])]


def prior_spread(prior, settings, n):
    """The prior's values and standard deviations in the fit's column order: each parameter
    ``prior_inertia_sd`` (mass, inertias) or ``prior_friction_sd`` (friction) times its prior
    value (a friction prior of 0 takes its family's largest, or 1: no knowledge)."""
    values = _parameter_values(prior, settings.fit_roller_drag)
    relative = np.array([settings.prior_inertia_sd] * INERTIAS
                        + [settings.prior_friction_sd] * (len(values) - INERTIAS))
    scale = np.abs(values)
    # the rollers' drag is a Coulomb-like contact torque: a prior of 0 takes the Coulomb family's
    coulomb = slice(INERTIAS + n, None)
    for family in (slice(3, 3 + n), coulomb):
        scale[family] = np.where(scale[family] > 0.0, scale[family], scale[family].max() or 1.0)
    return values, relative * np.where(scale > 0.0, scale, 1.0)


def correlation_inflation(residual, lags):
    """How many times fewer independent samples the residual (k, n) holds than rows: 1 + 2 x the
    Bartlett-weighted sum of its autocorrelation along time (mean over the columns) up to
    ``lags`` rows, at least 1. The smoothed signals and the model's own errors make neighbouring
    rows alike; a covariance that counted every row as new would claim precision it has not."""
    rows = len(residual)
    lags = int(min(lags, rows // 4))
    centred = residual - residual.mean(axis=0)
    variance = float(np.sum(centred ** 2))
    if lags < 1 or variance <= 0.0:
        return 1.0
    total = 0.0
    for lag in range(1, lags + 1):
        rho = float(np.sum(centred[lag:] * centred[:-lag])) / variance
        total += (1.0 - lag / (lags + 1.0)) * rho
    return max(1.0, 1.0 + 2.0 * total)


def _solve_dynamics(design, target, model, n, settings, rows=FitRows()):
    """Bayesian least squares of ``design @ p = target`` with the Gaussian prior of
    :func:`prior_spread`, parameters bounded at 0: a fit with the prior barely weighted gives the
    noise (its residual's variance, times :func:`correlation_inflation`), then the fit weighs data
    rows by that noise and prior rows by the prior's spread. The posterior covariance
    ``(X'X / s^2 + P^-1)^-1`` gives each parameter's standard deviation; a parameter whose
    spread the data shrink to no less than ``excitation_share`` of the prior's is not excited by
    this recording and stays near its prior (the posterior does that by itself)."""
    prior = model.dynamics.parameters
    values, spread = prior_spread(prior, settings, n)
    lower = np.zeros(design.shape[1])
    lower[:INERTIAS] = 1e-9
    norms = np.linalg.norm(design, axis=0)
    # Unknowns scaled by the column norms (conditioning), but a column that is zero to rounding
    # (no rotation in the drive: J_z's) is not blown up into a regressor of its rounding.
    column_scale = np.maximum(norms, COLUMN_FLOOR * max(float(norms.max()), 1e-300))
    scaled = design / column_scale
    gram, moment = scaled.T @ scaled, scaled.T @ target  # the data's normal equations, once

    def normal_equations(noise, data_gram=gram, data_moment=moment):
        # The prior's rows are weighted noise / spread, so both kinds of row are in units of
        # the noise; least squares over the data and prior rows by their normal equations.
        prior_row = noise / (spread * column_scale)
        return (data_gram + np.diag(prior_row ** 2),
                data_moment + prior_row * (noise * values / spread))

    def solve(normal, rhs):
        try:
            factor = np.linalg.cholesky(normal)
        except np.linalg.LinAlgError:  # not positive definite to rounding: nudge its diagonal
            factor = np.linalg.cholesky(normal + np.eye(len(normal)) * 1e-12 * np.trace(normal))
        free = scipy.linalg.cho_solve((factor, True), rhs)
        # The unconstrained optimum where it is feasible (with a prior, nearly always) is the
        # bounded one; else the bounded problem on the Cholesky factor (k x k, same minimiser).
        if np.all(free >= lower * column_scale):
            return free / column_scale
        reduced = scipy.linalg.solve_triangular(factor, rhs, lower=True)
        # BVLS: an exact active-set solution (k x k), where 'trf' stops early on weak columns.
        return scipy.optimize.lsq_linear(factor.T, reduced, bounds=(lower * column_scale, np.inf),
                                         method='bvls').x / column_scale

    def jackknife(noise, order=None):
        """The delete-a-block jackknife's standard deviation of the (unbounded) fit: the
        recording's samples in ``order`` (default: time) cut into JACKKNIFE_BLOCKS consecutive
        parts, the fit without each (the whole fit's normal equations less that part's),
        sqrt((B - 1) / B sum (p_b - mean)^2). Where the model misses (a friction law unlike the
        plant's, a bias that changes with speed) the recording's parts disagree by more than
        the noise says."""
        count = len(target) // n
        blocks = min(JACKKNIFE_BLOCKS, count)
        edges = np.linspace(0, count, blocks + 1).astype(int)
        samples = np.arange(count) if order is None else order
        fits = []
        for start, stop in zip(edges[:-1], edges[1:]):
            pick = (samples[start:stop, None] * n + np.arange(n)).ravel()
            part = scaled[pick]
            normal, rhs = normal_equations(noise, gram - part.T @ part,
                                           moment - part.T @ target[pick])
            fits.append(np.linalg.solve(normal, rhs) / column_scale)
        fits = np.array(fits)
        return np.sqrt((blocks - 1) / blocks * np.sum((fits - fits.mean(axis=0)) ** 2, axis=0))

    # The probe's noise is also the floor of the one measured: a model is not better than that
    # share of the torque's spread, and a noise of 0 (synthetic data) would leave the prior no
    # weight at all.
    floor = NOISE_PROBE * max(float(np.std(target)), 1e-12)
    rough = design @ solve(*normal_equations(floor))
    residual = (target - rough).reshape(-1, n)
    inflation = correlation_inflation(residual, rows.correlation_lags)
    noise = max(math.sqrt(float(np.mean(residual ** 2)) * inflation), floor)
    normal, rhs = normal_equations(noise)
    solution = solve(normal, rhs)
    fitted = design @ solution
    # The posterior covariance in the scaled unknowns, noise^2 (X'X + P'P)^-1 there: well
    # conditioned where the unscaled information matrix spans thirty decades.
    scaled_covariance = noise ** 2 * np.linalg.pinv(normal, hermitian=True)
    posterior = np.sqrt(np.clip(np.diag(scaled_covariance), 0.0, None)) / column_scale
    names = parameter_names(n, settings.fit_roller_drag)
    # Excitation is what the data can tell (the posterior); the stated deviation is at least
    # what the recording's parts disagree by, too (a model that misses, not noise).
    unexcited = [name for name, sd, wide in zip(names, posterior, spread)
                 if sd > settings.excitation_share * wide]
    # Parts in time disagree where the drive changes; parts by speed where the friction law is
    # not the plant's: a recording that drives alike throughout shows a wrong law only there
    # (the viscous and Coulomb terms trade off differently at each speed).
    deviation = posterior
    if rows.stated:
        deviation = np.maximum(deviation, jackknife(noise))
        if rows.by_speed is not None:
            deviation = np.maximum(deviation, jackknife(noise, rows.by_speed))
    r_squared = 1.0 - np.sum((target - fitted) ** 2) / max(np.sum((target - target.mean()) ** 2), 1e-12)
    params = replace(prior, mass=float(solution[0]), yaw_inertia=float(solution[1]),
                     wheel_inertia=(float(solution[2]),) * n,
                     viscous_friction=tuple(float(v) for v in solution[3:3 + n]),
                     coulomb_friction=tuple(float(v) for v in solution[3 + n:3 + 2 * n]),
                     roller_drag=(float(solution[3 + 2 * n]) if settings.fit_roller_drag
                                  else prior.roller_drag),
                     loop_inertias=())  # a prior's loop inertias are not the fit's (identify sets them)
    info = {'torque_fit_r_squared': float(r_squared),
            'uncertainty': {name: float(sd) for name, sd in zip(names, deviation)},
            'uncertainty_noise': {name: float(sd) for name, sd in zip(names, posterior)},
            'prior_sd': {name: float(sd) for name, sd in zip(names, spread)},
            'unexcited': unexcited, 'correlation_inflation': float(inflation)}
    return params, info, fitted


def simulate_from_currents(model, arrays):
    """Open-loop wheel speeds predicted from the measured torques (the report's §5.2.2 model): the
    residual generator's observer without its correction (Coulomb friction at the measured speed)."""
    # Without the commands: the command path (the firmware loop, its saturated rows stepped
    # period by period) is most of a run's cost and plays no part in this prediction.
    batch = run_generator(model, replace(arrays, commands=[]), own_settings(observer_time_constant=math.inf))
    predicted = arrays.velocity.copy()  # where the generator restarts: the measurement
    predicted[np.searchsorted(arrays.time, batch.stamp)] = batch.velocity - batch.values['observer']
    return predicted


def _block(model, arrays):
    """The recording as one block for the generator or its observer: (joints in the driver's
    convention, commands, how many commands came before each sample: a command counts as
    received before the joint states stamped at or after it)."""
    signs = model.kinematics.drive_signs
    command_batch = arrays.command_batch
    joints = JointBatch(arrays.time, signs * arrays.position, signs * arrays.velocity, signs * arrays.torque)
    return joints, command_batch, np.searchsorted(command_batch.stamp, arrays.time, side='right')


def own_settings(settings=None, **values):
    """``settings`` (default: FdiSettings()) with ``values`` set, for identify's own runs of the
    FDI: without the online shared drag (calibration is the floor the model is fitted to, so what
    the physics misses there is the learned corrections' and the bounds', not a change of floor)
    and without the loop's direction (the command bound identify fits is the path's own: a row
    the direction test judged holds the speed error instead of the path's residual)."""
    return replace(FdiSettings() if settings is None else settings, shared_drag=False,
                   loop_direction=False, **values)


def run_generator(model, arrays, settings):
    """The residual generator over the whole recording in one block (:func:`_block`). Returns a
    ResidualBatch."""
    return ResidualGenerator(model, settings).update_batch(*_block(model, arrays))


def run_command_path(model, arrays, settings):
    """(stamps (M,) [s], speeds (M, n) [rad/s]) the command path predicts over the whole
    recording: the generator's ``command_speed`` without its residuals (the searches call this
    tens of times; the residuals and bounds are a fifth of a generator's run). The rows that
    restart are left out, as the generator leaves them out."""
    joints, commands, before = _block(model, arrays)
    if not joints.complete().all():  # missing readings: the generator's own split
        batch = ResidualGenerator(model, settings).update_batch(joints, commands, before)
        return batch.stamp, batch.command_speed
    predictions = ModelObserver(model, settings).update_batch(joints, commands, before)
    kept = ~predictions.restart
    return predictions.stamp[kept], predictions.from_commands[kept]


def simulate_from_commands(model, arrays, input_delay=0.0, batch=None, command_timeout=WATCHDOG):
    """Wheel speeds predicted from the commands through the firmware loop (§5.2.3), the commands
    acting ``input_delay`` [s] after their stamps and held ``command_timeout`` [s] (inf: the
    driver holds the last one); from ``batch`` (the generator already run over ``arrays`` with
    that delay) where given."""
    if batch is None:
        stamp, speed = run_command_path(model, arrays, own_settings(input_delay=input_delay,
                                                                    command_timeout=command_timeout))
    else:
        stamp, speed = batch.stamp, batch.command_speed
    predicted = arrays.velocity.copy()  # where the generator restarts: the measurement
    predicted[np.searchsorted(arrays.time, stamp)] = speed
    return predicted


def command_speed_error(model, arrays, input_delay, command_timeout=WATCHDOG):
    """Mean squared difference [(rad/s)²] of the measured speeds and those the command path
    predicts (:func:`simulate_from_commands`): what the delay search on the coarse grid
    minimises (the gain fit minimises the same per speed, :func:`fit_firmware_gains`, where a
    missing reading adds nothing and an overflowed prediction counts as off by its wheel's
    range)."""
    predicted = simulate_from_commands(model, arrays, input_delay, command_timeout=command_timeout)
    return float(np.mean((arrays.velocity - predicted) ** 2))


def _effort_error(model, arrays, input_delay, command_timeout=WATCHDOG):
    """Mean squared difference [(N·m)²] of measured and commanded effort (current mode), the
    commands acting ``input_delay`` [s] after their stamps, held ``command_timeout`` [s]."""
    batch = run_generator(model, arrays, own_settings(input_delay=input_delay,
                                                      command_timeout=command_timeout))
    rows = ~batch.velocity_mode
    return float(np.mean(batch.values['command'][rows] ** 2)) if rows.any() else 0.0


def delay_grid(interval):
    """Input delays [s] to try: from one sample ``interval`` early (commands stamped after the
    samples they produce) to ``MAX_DELAY``, every ``DELAY_STEP``."""
    early = math.ceil(interval / DELAY_STEP) * DELAY_STEP
    return np.round(np.arange(-early, MAX_DELAY + DELAY_STEP / 2, DELAY_STEP), 6)


def for_search(arrays):
    """``arrays`` for the searches: at most :data:`SEARCH_SECONDS` of it, in
    :data:`SEARCH_WINDOWS` windows spread evenly over the recording (the prediction restarts from
    the measurement at each, as after any gap), decimated (:data:`SEARCH_RATE`,
    :data:`SEARCH_SAMPLES`)."""
    duration = float(arrays.time[-1] - arrays.time[0])
    if duration > SEARCH_SECONDS:
        width = SEARCH_SECONDS / SEARCH_WINDOWS
        starts = arrays.time[0] + np.linspace(0.0, duration - width, SEARCH_WINDOWS)
        keep = np.zeros(len(arrays.time), dtype=bool)
        for start in starts:
            keep |= (arrays.time >= start) & (arrays.time < start + width)
        arrays = replace(arrays, time=arrays.time[keep], position=arrays.position[keep],
                         velocity=arrays.velocity[keep], torque=arrays.torque[keep])
    interval = float(np.median(np.diff(arrays.time)))
    # Rounded first: 1 / (100 Hz x 0.01 s) is 1.0000000000000002 in floating point.
    every = max(1, int(math.ceil(round(1.0 / (SEARCH_RATE * interval), 6))),
                int(math.ceil(len(arrays.time) / SEARCH_SAMPLES)))
    if every == 1:
        return arrays
    pick = slice(None, None, every)
    return replace(arrays, time=arrays.time[pick], position=arrays.position[pick],
                   velocity=arrays.velocity[pick], torque=arrays.torque[pick])


def velocity_commanded(arrays):
    """Whether the recording ``arrays`` holds velocity commands (the firmware's PI loop is then
    in it, and its gains can be fitted)."""
    return any(c.kind == VELOCITY for c in arrays.commands)


def fit_input_delay(model, arrays, delays, command_timeout=WATCHDOG, refine=True):
    """The input delay [s] on the grid ``delays`` that best explains the measurements from the
    commands with ``model``'s gains: the speeds through the firmware loop (velocity commands),
    else the measured effort (current-mode commands), the grid searched as
    :func:`search_grid` does (without ``refine``: its coarse points only); commands held
    ``command_timeout`` [s]. Returns (delay, mean squared errors on the grid: NaN where not
    tried), or None without commands."""
    if velocity_commanded(arrays):
        def error(d):
            return command_speed_error(model, arrays, d, command_timeout)
    elif any(c.kind == EFFORT for c in arrays.commands):
        def error(d):
            return _effort_error(model, arrays, d, command_timeout)
    else:
        return None
    best, errors = search_grid(error, delays, refine)
    return float(delays[best]), errors


def fit_delay_and_gains(model, arrays, delays, command_timeout=WATCHDOG):
    """The input delay on the grid ``delays`` [s] and the velocity PI gains that together best
    predict the speeds from the velocity commands; commands held ``command_timeout`` [s].
    Returns (delay [s], FirmwareParameters, mean squared errors on the grid of the delays tried,
    each with the gains fitted at it: NaN where not tried), or None without velocity commands.

    From the delay that suits ``model``'s gains (:func:`fit_input_delay`), the delay walks
    downhill along the grid, first ``DELAY_COARSE_STEPS`` steps at a time, then step by step,
    and at each delay it tries the gains are fitted anew (:func:`fit_firmware_gains`, from those
    fitted at the nearest delay tried before). Why: the gains and the delay trade off (a slower
    loop mimics a later one), and the error is not convex across the trade: fitted in turn, gains
    at the delay the prior's gains suit and the delay again at those gains, the search stopped
    in the trade's nearest valley (randomized plants of the benchmark: k_i 2.5 to 4 times the
    truth's with a delay 30 ms late: plant 110, k_i 7.3 against 2.9); walking the error of the
    best gains at each delay, it finds the plant's (plant 110: 3.8)."""
    if not velocity_commanded(arrays):
        return None
    # The walk's start needs no finer delay than its first stride: the coarse grid's best.
    first, _ = fit_input_delay(model, arrays, delays, command_timeout, refine=False)
    fitted = {}

    def error(d):
        nearest = min(fitted, key=lambda tried: abs(tried - d), default=None)
        if nearest is None:
            fitted[d] = fit_firmware_gains(model, arrays, d, command_timeout)
        else:
            start = PlatformModel(replace(model.profile, firmware=fitted[nearest].firmware))
            fitted[d] = fit_firmware_gains(start, arrays, d, command_timeout, fitted[nearest].jacobian)
        return fitted[d].mean_squared_error

    errors = np.full(len(delays), np.nan)
    best = int(np.argmin(np.abs(delays - first)))
    for stride in (DELAY_COARSE_STEPS, 1):
        best = descend_grid(error, delays, best, errors, stride)
    return float(delays[best]), fitted[delays[best]].firmware, errors


def descend_grid(error, grid, start, errors, stride=1):
    """From index ``start`` of ``grid``, step ``stride`` points at a time while ``error`` falls,
    each way from ``start``; ``errors`` (NaN where not tried) filled in as tried. Returns the
    best index tried.

    Each way walks from ``start`` itself, not from the best the other way found: the error is
    flat in places along a delay grid (a delay moves commands across samples only at some grid
    points), and a first step that wins a tie by a rounding error must not hide a valley one
    step the other way (randomized plant 088: 17.5 and 20 ms fit alike to four digits; a walk
    that took 20 ms turned back at 22.5 and never tried 15 and 12.5 ms, which fit better, with
    the plant's gains)."""
    if np.isnan(errors[start]):
        errors[start] = error(grid[start])
    for direction in (stride, -stride):
        here, k = start, start + direction
        while 0 <= k < len(grid):
            if np.isnan(errors[k]):
                errors[k] = error(grid[k])
            if errors[k] >= errors[here]:
                break
            here, k = k, k + direction
    return int(np.nanargmin(errors))


def search_grid(error, grid, refine=True):
    """(index of the least ``error`` on ``grid`` found, errors on the grid: NaN where not tried):
    the grid every ``DELAY_COARSE_STEPS`` steps and its last point, then (``refine``) every
    step within ``DELAY_COARSE_STEPS`` of the best of those (the error is not smooth along the
    grid: a delay moves commands across samples)."""
    errors = np.full(len(grid), np.nan)
    coarse = list(range(0, len(grid), DELAY_COARSE_STEPS)) + [len(grid) - 1]
    for k in sorted(set(coarse)):
        errors[k] = error(grid[k])
    best = int(np.nanargmin(errors))
    if not refine:
        return best, errors
    for k in range(max(0, best - DELAY_COARSE_STEPS + 1), min(len(grid), best + DELAY_COARSE_STEPS)):
        if np.isnan(errors[k]):
            errors[k] = error(grid[k])
    return int(np.nanargmin(errors)), errors


def commands_past_watchdog(arrays, settings):
    """Samples (k,) of the recording whose command in force (the latest stamped at or before the
    sample less ``input_delay``) is older than the shim's watchdog (``command_timeout``) and
    not a stop: where a driver with that watchdog stands and one that holds commands drives."""
    commands = arrays.command_batch
    if not len(commands):
        return np.zeros(len(arrays.time), dtype=bool)
    index, expired = commands_in_force(commands.stamp, arrays.time, settings.input_delay,
                                       settings.command_timeout)
    moving = np.abs(commands.values[np.maximum(index, 0)]).max(axis=1) > 0.0
    return (index >= 0) & moving & expired


def commands_held(model, arrays, settings):
    """Whether the robot's driver holds its last command rather than stopping after
    ``command_timeout`` without one (our shim's watchdog), as the recording shows: on the samples
    :func:`commands_past_watchdog`, the speeds the command path predicts holding the command are
    nearer the measured ones than those it predicts with the watchdog (mean absolute error).
    False where no sample tells (commands sent with every sample, or only stops left standing).

    Why: a driver that is sent commands only when they change (or at a few hertz) and keeps
    them has no watchdog to model; judged as if it had, every wheel would be running away
    from a command it was never given."""
    past = commands_past_watchdog(arrays, settings)
    if not past.any():
        return False
    errors = []
    for timeout in (settings.command_timeout, math.inf):
        stamp, speed = run_command_path(model, arrays, replace(settings, command_timeout=timeout))
        rows = np.searchsorted(arrays.time, stamp)
        judged = past[rows]
        errors.append(float(np.nanmean(np.abs(arrays.velocity[rows[judged]] - speed[judged])))
                      if judged.any() else math.nan)
    return bool(errors[1] < errors[0])


def nrmse(measured, predicted):
    """Per-wheel RMSE over the range of the measured signal [-]."""
    span = np.ptp(measured, axis=0)
    return np.sqrt(np.mean((measured - predicted) ** 2, axis=0)) / np.where(span > 0, span, 1.0)


def friction_sweep(model, arrays, values=None):
    """RMSE [rad/s] of the current-driven prediction for each viscous friction in ``values``
    [N·m·s/rad] (default: :data:`SWEEP_FACTORS` times the model's mean viscous friction)."""
    if values is None:
        values = SWEEP_FACTORS * float(np.mean(model.dynamics.parameters.viscous_friction))
    rmse = []
    for value in values:
        params = replace(model.dynamics.parameters, viscous_friction=(float(value),) * model.dynamics.n_wheels)
        trial = PlatformModel(replace(model.profile, dynamics=params))
        predicted = simulate_from_currents(trial, arrays)
        rmse.append(float(np.sqrt(np.mean((arrays.velocity - predicted) ** 2))))
    return np.asarray(values, dtype=float), np.array(rmse)


class GainFit(NamedTuple):
    """Velocity PI gains fitted at one input delay (:func:`fit_firmware_gains`)."""

    firmware: object  # FirmwareParameters with the fitted velocity_kp [A·s/rad] and velocity_ki [A/rad]
    mean_squared_error: float  # of the predicted speeds with them [(rad/s)²]
    jacobian: np.ndarray  # (N, 2) of the scaled speed residuals in the log gains there


class BroydenJacobian:
    """The Jacobian of ``residuals`` (of x) for ``scipy.optimize.least_squares``: by forward
    differences (step ``step`` in each of x) where none is known, else the last one moved by
    Broyden's rank-one update from the last point it was asked at to this one (the residuals
    there were just computed: they are remembered, not simulated again). Why: each simulation
    of the command path costs tens of milliseconds, and forward differences take two a step;
    the update costs none, and from a nearby delay's Jacobian a fit takes two or three steps."""

    def __init__(self, residuals, step, start=None):
        self._residuals, self._step, self.matrix = residuals, step, start
        self._last = (None, None)  # (x bytes, residuals) of the last evaluation
        self._at = None  # (x, residuals) where self.matrix was last given

    def residuals(self, x):
        value = self._residuals(x)
        self._last = (x.tobytes(), value)  # least_squares asks the Jacobian where it last evaluated
        return value

    def __call__(self, x):
        seen, value = self._last
        if seen != x.tobytes():
            value = self.residuals(x)
        if self.matrix is None:
            columns = []
            for k in range(len(x)):
                moved = x.copy()
                moved[k] += self._step
                columns.append((self._residuals(moved) - value) / self._step)
            self.matrix = np.stack(columns, axis=1)
        elif self._at is not None:
            moved = x - self._at[0]
            length = float(moved @ moved)
            if length > 0.0:
                surprise = value - self._at[1] - self.matrix @ moved
                self.matrix = self.matrix + np.outer(surprise, moved) / length
        self._at = (x.copy(), value)
        return self.matrix


def fit_firmware_gains(model, arrays, input_delay=0.0, command_timeout=WATCHDOG, jacobian=None):
    """Velocity PI gains that make the command-path prediction match (commands acting
    ``input_delay`` [s] late, held ``command_timeout`` [s]): a :class:`GainFit`, None without
    velocity commands. ``jacobian``: a nearby fit's, to start from (else forward differences)."""
    if not velocity_commanded(arrays):
        return None
    kp = model.firmware.velocity_kp
    start = np.log([kp, max(model.firmware.velocity_ki, MIN_INTEGRAL_SHARE * kp)])  # ki may be 0
    scale = math.sqrt(arrays.velocity.size)  # the residuals' sum of squares is the mean squared error
    # A prediction that is not a number (a loop the gains make unstable overflowed) counts as off
    # by its wheel's whole measured range (worse than any prediction within it); a reading that
    # is missing tells nothing.
    measured = np.isfinite(arrays.velocity)
    diverged = np.broadcast_to(np.ptp(np.where(measured, arrays.velocity, 0.0), axis=0),
                               arrays.velocity.shape)

    def residuals(log_gains):
        kp, ki = np.exp(log_gains)
        trial = PlatformModel(replace(model.profile, firmware=replace(model.firmware, velocity_kp=kp,
                                                                      velocity_ki=ki)))
        predicted = simulate_from_commands(trial, arrays, input_delay, command_timeout=command_timeout)
        error = arrays.velocity - predicted
        return (np.where(measured, np.where(np.isfinite(error), error, diverged), 0.0) / scale).ravel()

    # Least squares on the speeds' residuals, not a simplex on their mean square: each step
    # takes the residuals' first-order change in both gains, and from the gains of a nearby
    # delay it converges in two to five simulations, where Nelder-Mead ran about 30 a fit
    # (docs/fdi.md, "Identification": the gains it finds and what they cost).
    jacobian = BroydenJacobian(residuals, GAIN_DIFFERENCE_STEP, jacobian)
    result = scipy.optimize.least_squares(jacobian.residuals, start, jac=jacobian, method='trf',
                                          xtol=GAIN_TOLERANCE, ftol=GAIN_COST_TOLERANCE,
                                          max_nfev=GAIN_EVALUATIONS)
    kp, ki = np.exp(result.x)
    return GainFit(replace(model.firmware, velocity_kp=float(kp), velocity_ki=float(ki)),
                   2.0 * float(result.cost), jacobian.matrix)


def quantile_fit(features, target, quantile, rows=QUANTILE_ROWS, seed=0):
    """Non-negative weights w minimising the quantile loss of ``target - features @ w`` (linear
    quantile regression as a linear program): about ``quantile`` of the rows end up below
    ``features @ w``. features (N, k), target (N,); at most ``rows`` random rows are used."""
    keep = np.isfinite(target) & np.isfinite(features).all(axis=1)
    features, target = features[keep], target[keep]
    if len(target) > rows:
        pick = np.random.default_rng(seed).choice(len(target), rows, replace=False)
        features, target = features[pick], target[pick]
    count, k = features.shape
    if count == 0:
        return None
    scale = np.maximum(np.abs(features).max(axis=0), 1e-12)  # conditioning
    # The primal, min q 1'u+ + (1 - q) 1'u- over F w + u+ - u- = y, w, u+, u- >= 0, has a
    # variable per row; its dual, max y'd over F'd <= 0, q - 1 <= d <= q, has k constraints and
    # solves ~8x faster by the dual simplex; w are the multipliers of those k constraints.
    result = scipy.optimize.linprog(-target, A_ub=(features / scale).T, b_ub=np.zeros(k),
                                    bounds=(quantile - 1.0, quantile), method='highs-ds')
    if not result.success:
        return None
    # The solver's tolerance may leave -1e-17.
    return np.maximum(-result.ineqlin.marginals, 0.0) / scale


def fit_bounds(batch, settings):
    """The bounds' floors and weights learned from the residuals (a ResidualBatch, the generator
    run over a nominal recording with the identified model), and their coverage.

    Per bound (:data:`~youbot_fdi.fdi.residuals.BOUND_TERMS`), the ``bound_quantile`` of |r| as a
    non-negative linear function of its operating-point features, times ``bound_margin``; a
    floor never below ``FLOOR_FRACTION`` of the configured one. The command bound is learned from
    velocity-mode rows, the effort bound from current-mode rows (after their command-step
    allowance). Returns ({setting: value}, {family: share of nominal rows inside the bound}).
    """
    velocity_rows = batch.velocity_mode & ~np.all((batch.values['command'] == 0.0)
                                                  & (batch.bounds['command'] == 1.0), axis=1)
    residual = {family: np.abs(batch.values[family]) for family in ('torque', 'observer', 'encoder')}
    residual['command'] = np.where(velocity_rows[:, None], np.abs(batch.values['command']), np.nan)
    allowance = batch.bounds['command'] - batch.features['effort'] @ bound_weights(settings, 'effort')
    effort_rows = ~batch.velocity_mode
    residual['effort'] = np.where(effort_rows[:, None], np.abs(batch.values['command']) - allowance, np.nan)
    learned, coverage = {}, {}
    for family, names in BOUND_TERMS.items():
        features = batch.features[family]
        target = residual[family]
        rows = np.isfinite(target).all(axis=1)
        if rows.sum() < MIN_SAMPLES:
            continue
        weights = quantile_fit(features[rows].reshape(-1, len(names)), target[rows].ravel(),
                               settings.bound_quantile)
        if weights is None:
            continue
        weights = weights * settings.bound_margin
        weights[0] = max(weights[0], FLOOR_FRACTION * getattr(settings, names[0]))
        learned.update({name: float(w) for name, w in zip(names, weights)})
        coverage[family] = float(np.mean(target[rows] <= features[rows] @ weights))
        covered = np.quantile(features[rows].reshape(-1, len(names)), RANGE_QUANTILE, axis=0)
        covered[0] = math.inf  # the floor's constant feature
        learned[f'{family}_feature_range'] = [float(v) for v in covered]
    return learned, coverage


def calibrated_speed_range(arrays, settings):
    """[low, high] of the norm of the wheel speeds [rad/s] while the base moved (faster than
    ``stuck_speed`` on some wheel), :data:`SPEED_QUANTILES`."""
    norm = np.linalg.norm(arrays.velocity, axis=1)
    moving = np.abs(arrays.velocity).max(axis=1) > settings.stuck_speed
    if moving.sum() < MIN_SAMPLES:
        return [0.0, math.inf]
    return [float(q) for q in np.quantile(norm[moving], SPEED_QUANTILES)]


def calibrated_slip(model, arrays):
    """The largest wheel speed no rigid base motion explains [rad/s] over the recording's
    complete rows (``Kinematics.slip_speed``; 0 for a base of three wheels), or inf without
    enough of them."""
    complete = np.isfinite(arrays.velocity).all(axis=1)
    if complete.sum() < MIN_SAMPLES:
        return math.inf
    return float(model.kinematics.slip_speed(arrays.velocity[complete]).max())


def speed_noise(arrays):
    """The speed reading's noise [rad/s]: the robust spread of its second differences over the
    samples, sqrt(6) times the noise of independent errors (the motion's own curvature over two
    intervals is far smaller at any rate a driver samples)."""
    second = np.diff(arrays.velocity, n=2, axis=0)
    mad = np.median(np.abs(second - np.median(second, axis=0)))
    return float(1.4826 * mad / math.sqrt(6.0))


#: The tests whose false-alarm rate identify states and meets: each evidence family, the torque
#: residual's shift from its level, and a wheel's silence; the target is shared among them equally.
RATE_TESTS = (*FAMILIES, 'torque shift', 'silence')


def held_out_scores(model, batch, settings):
    """Scores |r| / u (N, families, n) of a nominal recording's residuals ``batch`` (from the
    generator run with ``settings``), each half judged with bounds fitted on the other half (the
    part of a bound that is not learned, its allowances, kept); and the held-out torque bounds
    with and without those allowances (the scale of the torque shift,
    ``ResidualEvaluator.shift_scale``)."""
    rows = len(batch)
    half = rows // 2
    full = ResidualEvaluator(model, settings)
    scores = np.zeros((rows, len(FAMILIES), model.dynamics.n_wheels))
    torque_bound = np.ones((rows, model.dynamics.n_wheels))
    torque_scale = np.ones((rows, model.dynamics.n_wheels))
    for fit, judge in ((slice(half, rows), slice(0, half)), (slice(0, half), slice(half, rows))):
        learned, _ = fit_bounds(batch.select(fit), settings)
        held = ResidualEvaluator(model, replace(settings, **learned))
        part = batch.select(judge)
        for k, family in enumerate(FAMILIES):
            was, now = _learned_bound(full, family, part), _learned_bound(held, family, part)
            settling = part.bounds[family] == 1.0  # the command path while it settles: not judged
            bound = np.where(settling, 1.0, part.bounds[family] - was + now)
            value = np.where(settling, 0.0, part.values[family])
            scores[judge, k] = np.abs(value) / bound
            if family == 'torque':
                torque_bound[judge] = bound
                torque_scale[judge] = held.shift_scale(now, part.velocity, part.load_factor[:, None])
    scores[~np.isfinite(scores)] = 0.0
    return scores, torque_bound, torque_scale


def _learned_bound(evaluator, family, batch):
    """The learned part of ``family``'s bound (N, n) on the rows of ``batch`` with
    ``evaluator``'s weights; the command family by mode (its velocity bound, or the effort one)."""
    if family != 'command':
        return evaluator.bound(family, batch.features[family])
    return np.where(batch.velocity_mode[:, None], evaluator.bound('command', batch.features['command']),
                    evaluator.bound('effort', batch.features['effort']))


def false_alarm_rates(model, batch, settings, residual_data):
    """Per test of :data:`RATE_TESTS`, the :class:`~youbot_fdi.fdi.alarm_rate.RateEstimate` of
    its CUSUM on this nominal recording's held-out scores (:func:`held_out_scores`), with the
    decision's increments (sample weights, cap, drift); ``residual_data`` the decision's residual
    set."""
    from youbot_fdi.fdi.decision import DecisionMaker
    scores, torque_bound, torque_scale = held_out_scores(model, batch, settings)
    decision = DecisionMaker(model.wheel_names, settings, residual_data)
    weight = decision.sample_weights(batch.stamp)
    interval = float(np.median(np.diff(batch.stamp))) if len(batch) > 1 else settings.evidence_interval
    fresh = (decision._breaking_away(batch.velocity, batch.stamp)
             | decision.operating_point_changes(batch.velocity, batch.load_factor))  # levels afresh
    torque_scale = torque_scale + decision.friction_change(batch.velocity, batch.friction_level,
                                                           batch.stamp)
    shift = decision.torque_shift(batch.values['torque'], torque_bound, torque_scale, batch.stamp,
                                  np.zeros(model.dynamics.n_wheels, dtype=bool), fresh)
    magnitude, shift_up_down = decision.increments(scores, shift, weight)
    estimates = {family: alarm_rate.estimate(magnitude[:, k], scores[:, k], interval)
                 for k, family in enumerate(FAMILIES)}
    rows = len(batch)
    estimates['torque shift'] = alarm_rate.estimate(
        shift_up_down.reshape(rows, -1), decision.shift_scores(shift).reshape(rows, -1), interval)
    return estimates


def silence_estimate(arrays, interval):
    """The :class:`~youbot_fdi.fdi.alarm_rate.SilenceEstimate` of a recording's missed answers
    (``arrays.answered``; none recorded: every wheel answered every sample), sampled every
    ``interval`` [s]."""
    answered = (arrays.answered if arrays.answered is not None
                else np.ones(arrays.velocity.shape, dtype=bool))
    return alarm_rate.silence_estimate(answered, interval)


def rate_thresholds(estimates, settings):
    """The thresholds that meet ``false_alarm_target`` (shared equally among the tests), never
    below the configured ones: ({setting: value}, {test: (threshold, alarms per hour)})."""
    share = settings.false_alarm_target / len(RATE_TESTS)
    thresholds = []
    for k, family in enumerate(FAMILIES):
        thresholds.append(max(settings.family_thresholds[k], estimates[family].threshold(share)))
    shift = max(settings.shift_threshold, estimates['torque shift'].threshold(share))
    silence = estimates['silence'].threshold(share)
    chosen = dict(zip(FAMILIES, thresholds), **{'torque shift': shift, 'silence': silence})
    stated = {test: (chosen[test], estimates[test].rate(chosen[test])) for test in RATE_TESTS}
    return {'family_thresholds': [float(t) for t in thresholds], 'shift_threshold': float(shift),
            # inf (every sample missed): no count, the wheel's comm_loss after data_timeout
            'silent_samples': int(silence) if math.isfinite(silence) else 0}, stated


def contact_share_floor(model, arrays, settings):
    """The lowest rolling share (model/dynamics.py) of a turning wheel the recording covers: the
    ``1 - bound_quantile`` quantile over the samples of wheels faster than ``stuck_speed``
    [rad/s]; 0 (no limit) without the contact law or without such samples. Below it the law is
    extrapolated, and the torque bound allows for it (``contact_share_floor``)."""
    dynamics = model.dynamics
    mean_speed = 0.5 * (arrays.velocity[1:] + arrays.velocity[:-1])
    turning = np.abs(mean_speed) > settings.stuck_speed
    if not dynamics.contact_law or not turning.any():
        return 0.0
    shares = dynamics.rolling_shares(mean_speed)[turning]
    return float(np.quantile(shares, 1.0 - settings.bound_quantile))


def _rms(batch):
    """{family: RMS of its residuals over the rows and wheels} of a ResidualBatch."""
    return ResidualSpread().add(batch).rms()


def learn_corrections(model, arrays, settings, physics):
    """The learned torque correction (:mod:`youbot_fdi.fdi.learned`) of ``model`` on this nominal
    recording, from its physics residuals ``physics`` (the generator's ResidualBatch). Returns
    (the ``learned`` profile section or None, notes to print, residual spread: {'physics' |
    'learned': {family: RMS over the recording and the wheels}}, the same twice when nothing is
    learned)."""
    index = np.searchsorted(arrays.time, physics.stamp)
    before = np.maximum(index - 1, 0)
    mean_speed = 0.5 * (arrays.velocity[index] + arrays.velocity[before])
    change = arrays.velocity[index] - arrays.velocity[before]
    interval = (arrays.time[index] - arrays.time[before])[:, None]
    acceleration = inertial_feature(
        np.divide(change, interval, out=np.full_like(change, np.nan), where=interval > 0.0),
        arrays.torque[index], arrays.torque[before], model.drive.max_torque)
    correction, notes = fit_torque_correction(mean_speed, acceleration, physics.values['torque'],
                                              model.dynamics.parameters.coulomb_velocity_scale,
                                              settings.torque_sigma)
    if correction is None:  # the learned variant is the physics one
        return None, notes, {'physics': _rms(physics), 'learned': _rms(physics)}
    learned = {'torque': correction.to_mapping()}
    corrected = run_generator(PlatformModel(replace(model.profile, learned=learned)), arrays, settings)
    return learned, notes, {'physics': _rms(physics), 'learned': _rms(corrected)}


@dataclass(frozen=True)
class IdentificationResult:
    """What ``identify`` found."""

    profile: ModelProfile
    nrmse_currents: np.ndarray  # (n,) current-driven prediction
    nrmse_commands: object  # (n,) command-driven prediction, or None
    sweep: tuple  # (values, rmse)
    fdi: dict  # learned FDI settings (bound floors and weights, input delay, sample interval)
    info: dict
    coverage: dict = None  # family -> share of the nominal samples inside the learned bound
    damage: object = None  # youbot_fdi.bag.salvage.Damage when the recording was read in part


def model_for_loop_fit(arrays, prior_model, model, settings, info):
    """The model the firmware loop's gains and input delay are fitted on (a PlatformModel):
    ``model`` with its dynamics fitted again from ``prior_model`` with the rollers' drag
    (:func:`fit_dynamics`, ``fit_roller_drag``; the firmware loop keeps ``model``'s loop
    inertias where it has its own), where the wheels' rollers turn them (a mecanum base) and
    ``model`` has no drag; else ``model``. ``info`` gets the drag fitted
    (``loop_fit_roller_drag`` [N·m]).

    Why: the gains are the modules' and the delay the transport's, not the floor's. A torque the
    model misses is a disturbance the loop rejects, and a faster loop acting later mimics that
    rejection in the speeds' mean square: the randomized suite's plant 92 of seed 16 (its speed
    reading encoder-derived, a 0.5 ms delay, k_p 1.63, k_i 4.46) was fitted at 20 ms with
    3.27/6.6 without the drag, and at 12.5 ms with 1.57/4.55 with it; simulated without its
    floor's drag, the same plant was fitted at 1.57/4.7. A loop fitted too fast forgets a
    transient sooner than the wheel does (the command path's `runaway` false alarms after steps,
    docs/fdi.md "The PI gains are taken as exact"). The FDI's own model keeps no drag unless asked
    (``fit_roller_drag``: the bounds it learns with one are tighter than other floors allow)."""
    if model.dynamics.parameters.roller_drag > 0.0 or not model.dynamics.drag_share.any():
        return model
    with_drag = fit_dynamics(arrays, prior_model, replace(settings, fit_roller_drag=True)).parameters
    info['loop_fit_roller_drag'] = round(float(with_drag.roller_drag), 5)
    loop = model.dynamics.parameters.loop_inertias  # the prior's where the readings do not see them
    return PlatformModel(replace(model.profile, dynamics=replace(with_drag, loop_inertias=loop)))


def identify(arrays, prior_model, settings, residual_data, fit_gains=True, learn=True, source=''):
    """Identify a model from a nominal recording's :class:`RecordingArrays`, starting from
    ``prior_model``; with ``learn``, also the learned corrections of the physics (issue 12)
    before the bounds. ``residual_data`` is the decision's residual set (for the stated
    false-alarm rate); ``source`` names the recording in the result.
    (:func:`youbot_fdi.app.recordings.identify_recording` reads a recording and calls this.)"""
    require_samples(len(arrays.time), source)
    settings = own_settings(settings)
    fit = fit_dynamics(arrays, prior_model, settings)
    dynamics, info = fit.parameters, fit.info
    if 'inertias_unseen' in info:
        # The fitted inertias relate the readings to the speeds (the explained torque needs
        # that); the firmware loop, stepped at its own period, moves what the readings cannot
        # tell from the prior's (_inertias_seen). Fitted there, its path is of a base that
        # weighs next to nothing: a loop unstable at its own period (20 Hz plants of the
        # randomized suite, a wheel inertia fitted at its bound of 1e-9 kg·m²), whose gains then
        # come out anywhere.
        loop = prior_model.dynamics.loop.parameters
        dynamics = replace(dynamics, loop_inertias=(loop.mass, loop.yaw_inertia,
                                                    float(np.mean(loop.wheel_inertia))))
        info['loop_inertias'] = 'the prior\'s (the readings do not see the wheels accelerate)'
    interval = float(np.median(np.diff(arrays.time)))
    info['sample_period'] = interval
    model = PlatformModel(replace(prior_model.profile, dynamics=dynamics))
    firmware, delay = None, None
    held = commands_held(model, arrays, settings)
    timeout = math.inf if held else settings.command_timeout
    info['command_watchdog'] = ('none: the wheels keep driving after the last command' if held
                                else f'{settings.command_timeout:g} s (the shim\'s)')
    delays = delay_grid(interval)
    searched = for_search(arrays)
    found = None
    if fit_gains:
        joint = (fit_delay_and_gains(model_for_loop_fit(arrays, prior_model, model, settings, info),
                                     searched, delays, command_timeout=timeout)
                 if velocity_commanded(arrays) else None)
        if joint is not None:  # velocity commands: the delay and the gains together
            delay, firmware, delay_errors = joint
            model = PlatformModel(replace(model.profile, firmware=firmware))
            found = (delay, delay_errors)
        else:  # current-mode commands (or none): the delay alone
            found = fit_input_delay(model, searched, delays, command_timeout=timeout)
    if found is not None:
        delay, delay_errors = found
        tried = np.isfinite(delay_errors)
        info['input_delay_grid'] = {'delay_s': [round(float(d), 4) for d in delays[tried]],
                                    'mse': [float(f'{e:.4g}') for e in delay_errors[tried]]}
    sweep = friction_sweep(model, searched)
    nrmse_currents = nrmse(arrays.velocity, simulate_from_currents(model, arrays))
    settings = replace(settings, sample_interval=interval, speed_sigma=speed_noise(arrays),
                       contact_share_floor=contact_share_floor(model, arrays, settings),
                       command_timeout=timeout)
    if delay is not None:
        settings = replace(settings, input_delay=delay)
    physics = run_generator(model, arrays, settings)  # the residuals both fits below start from
    nrmse_commands = (nrmse(arrays.velocity, simulate_from_commands(model, arrays, delay, physics))
                      if firmware is not None else None)
    fdi, coverage = fit_bounds(physics, settings)
    estimates = false_alarm_rates(model, physics, settings, residual_data)
    estimates['silence'] = silence_estimate(arrays, interval)
    thresholds, stated = rate_thresholds(estimates, settings)
    fdi.update(thresholds)
    info['false_alarm_rate'] = {test: {'threshold': round(float(t), 4), 'per_hour': float(f'{r:.3g}')}
                                for test, (t, r) in stated.items()}
    learned, notes, spread = (learn_corrections(model, arrays, settings, physics) if learn
                              else (None, [], None))
    if learned is not None:
        model = PlatformModel(replace(model.profile, learned=learned))
    info['learning'] = {'notes': notes, 'residual_rms': spread} if learn else 'physics only'

    fdi['sample_interval'] = interval
    fdi['speed_sigma'] = settings.speed_sigma
    fdi['calibrated_speed_range'] = calibrated_speed_range(arrays, settings)
    fdi['calibrated_slip'] = calibrated_slip(model, arrays)
    fdi['calibrated_effort'] = float(np.quantile(np.abs(arrays.torque[np.isfinite(arrays.torque)]),
                                                 RANGE_QUANTILE)) if np.isfinite(arrays.torque).any() \
        else math.inf
    fdi['contact_share_floor'] = settings.contact_share_floor
    fdi['command_timeout'] = settings.command_timeout
    if delay is not None:
        fdi['input_delay'] = delay
    info.update({'recording': source, 'samples': int(len(arrays.time)),
                 'duration_s': float(arrays.time[-1] - arrays.time[0]),
                 'commands': len(arrays.commands)})
    identification = {
        **info,
        'nrmse_from_currents': [round(float(v), 5) for v in nrmse_currents],
        'nrmse_from_commands': (None if nrmse_commands is None
                                else [round(float(v), 5) for v in nrmse_commands]),
        'friction_sweep': {'viscous_friction': [round(float(v), 4) for v in sweep[0]],
                           'rmse': [round(float(v), 5) for v in sweep[1]]},
        'bound_coverage': {family: round(share, 4) for family, share in coverage.items()},
    }
    profile = replace(model.profile, name=f'{prior_model.profile.name}_identified',
                      description=f'identified from {source}', fdi=fdi, identification=identification)
    return IdentificationResult(profile, nrmse_currents, nrmse_commands, sweep, fdi, info, coverage,
                                arrays.damage)
