"""Decisions: residual alarms -> isolated wheel and fault type -> fault events with hysteresis.

1. **Alarms.** Evidence accumulates per residual over time (a CUSUM of the scores z = |r| / u):
   ``g_k = max(0, g_{k-1} + w_k (min(z_k, evidence_cap) - evidence_drift))``, each sample weighted
   by the time it stands for, ``w_k = min(1, dt_k / evidence_interval)``: residuals are correlated
   over tens of milliseconds, so a faster sampled base gains no more evidence per second than a
   slower one (no new false alarms at 250 Hz), and no single sample counts for more than one
   interval (none at 20 Hz); a residual alarms while ``g`` reaches its family's threshold
   (``family_thresholds``: ``identify`` raises them to meet ``false_alarm_target`` on its
   recording, ``fdi/alarm_rate.py``) and clears after
   ``release_time`` of excited samples below it (their time, counted the same way). A small
   persistent excess is found (it adds up), a single spike is not an alarm (it is capped and
   drains away). Torque and command-path evidence on half the wheels or more at once (half the
   threshold each, rising within ``shared_window`` of each other) is a change they share, not a
   wheel fault; so is a modest excess (score below ``second_fault_score``) while other wheels'
   evidence is up, or beside another wheel's fault (its wheel fault alarm set, or cleared less
   than ``heal_time`` ago: a faulty wheel drags the others off the model). A clear excess on a
   wheel that rose later is a second fault. A position
   reading that repeats exactly while the wheel is commanded and measured to turn (current
   mode: or the other wheels' rigid motion says it turns) is direct evidence of a frozen sensor
   (``frozen_samples`` in a row), at any rate. While the base breaks
   away from rest (``breakaway_time`` after a sample in which every wheel stood) the torque
   residuals add no evidence: the wheels slip and break static friction until the base has
   caught up with them, outside the rolling contact law the model is made of.
2. **Isolation** uses the fault signatures of the runtime residual set chosen by the structural
   analysis (``config/residuals/<model>.yaml``): a fault is a candidate when every alarming torque
   residual is in its signature, and the candidates whose torque signature has the fewest silent
   residuals win (a silent residual exonerates the faults it would see). A single alarming
   ``torque_<w>`` isolates wheel w's actuator/friction class; all four point at a speed sensor,
   and the ``observer_<w>`` residuals name which one.
3. **Fault type** (CONTRACT.md vocabulary): ``encoder_freeze`` when the position stops following
   the speed (``encoder_<w>``), ``comm_loss`` when the effort froze with it; ``stuck`` when the
   wheel stands while its current is up; otherwise ``torque_loss`` or ``friction`` by which explains
   the torque residual better over the last ``classification_window``: the measured torque (less
   torque than the current implies) or the speed (more friction). ``runaway`` when only the command
   path disagrees: the wheel does what its current says, not what it was told. The type named at
   the alarm is refined once, when the window is full.
4. **Events**: one per change of a component's (level, fault), stamped with the sample's header
   stamp; ``OK`` when every alarm behind a fault has cleared, counting only samples in which the
   wheel moved or carried current (a standing wheel proves nothing).
5. **The load condition** (the residual generator's platform-wide load factor, common-mode
   rejection): a ``WARN`` event ``load_change`` not tied to a wheel, "surface or load changed"
   with the factor, when it departs from 1 by more than ``load_warn``; ``OK`` again below half
   of that. It is never a wheel fault.
6. **The calibrated range** of a learned correction: a ``WARN`` ``unseen_operating_point`` (not
   tied to a wheel; the detail names the wheels) when a wheel's operating point leaves what
   ``identify`` saw, so the physics alone judges it; ``OK`` after ``unseen_release`` s back inside.
"""
from __future__ import annotations

from dataclasses import dataclass
import json
from typing import TYPE_CHECKING

import numpy as np

from youbot_fdi.errors import ConfigError
from youbot_fdi.faults import FaultKind, Level, LOAD_CHANGE, REFINABLE, UNSEEN_OPERATING_POINT
from youbot_fdi.fdi.learned import masked_wheels
from youbot_fdi.fdi.lifecycle import EventLifecycle, FAULT_CHANNEL, LifecycleSettings
from youbot_fdi.fdi.recursions import (ExponentialAverage, NEVER, bounded_cusum, clip, cusum,
                                       last_true_value, shifted)
from youbot_fdi.fdi.residuals import FAMILIES, SPEED_NOISE_SIGMAS, ResidualBatch
from youbot_fdi.naming import wheel_suffix

if TYPE_CHECKING:  # names in annotations only
    from collections.abc import Sequence
    from youbot_fdi.fdi.residuals import ResidualFrame
    from youbot_fdi.fdi.settings import FdiSettings

OK, WARN, ERROR = Level.OK, Level.WARN, Level.ERROR  # short names for this module
TORQUE, COMMAND, ENCODER = (FAMILIES.index(f) for f in ('torque', 'command', 'encoder'))
#: Families judged against the other wheels, and the share of the threshold that counts as evidence.
SHARED_FAMILIES = [TORQUE, COMMAND]
WHEEL_FAULT_FAMILIES = [TORQUE, COMMAND, ENCODER]  # an alarm of these can name a wheel's fault
SHARED_SHARE = 0.5
LOAD_RELEASE = 0.5  # the load WARN ends below this share of ``load_warn`` (hysteresis) [-]
AT_BOUND = 1.0  # the score |r| / u of a residual at its bound [-]
MIN_STALE_SAMPLES = 2  # identical messages in a row (every field) that name comm_loss, not a freeze
#: A wheel whose torque exceeds this many torque_sigma carries current (it is excited).
EXCITED_TORQUE_SIGMAS = 3.0
#: The torque shift CUSUMs stay below this many shift_threshold, so a shift that has ended stops
#: counting within a few samples however long it lasted.
SHIFT_CEILING = 2.0
#: A torque level is a reference once this share of its memory holds samples (``shift_time_constant``
#: x ln 2 after the start or a gap): the first samples' mean is not yet the wheel's normal.
SHIFT_KNOWN_LEVEL = 0.5
#: Rows searched at once for the next change of operating point: from the first size, twice the
#: rows to the last change after one, doubling up to the most while none is found (a search costs
#: its block, and an aggressive drive changes its operating point every few dozen rows).
OPERATING_BLOCK_FIRST, OPERATING_BLOCK_MOST = 16, 256
#: Rows judged at once after an alarm changed what judges the rows after it (``_alarms``; a part
#: costs its rows, which a change soon after judges again).
REJUDGED_ROWS = 64
BASE = None  # the component of faults not tied to one wheel
BASE_NAME = 'base'  # how the base component is named for people
STAMP_TOLERANCE = 1e-9  # [s] rounding allowance when a time condition is turned into a row index
ACTUATOR_CLASS = ('actuator', 'friction')
SENSOR_CLASS = 'velocity_sensor'


@dataclass(frozen=True)
class FaultEvent:
    """One change of a component's fault state (CONTRACT.md fault event)."""

    stamp: float  # [s], header stamp of the sample that changed the state
    level: str  # OK | WARN | ERROR
    wheel: object  # joint name, or None when not tied to one wheel
    fault: str  # FaultKind value
    residuals: tuple = ()  # the alarming residuals behind it
    detail: str = ''

    def to_dict(self) -> dict:
        """The JSON object of an events file line."""
        return {'stamp': round(self.stamp, 6), 'level': self.level, 'wheel': self.wheel,
                'fault': self.fault, 'residuals': list(self.residuals), 'detail': self.detail}

    def to_json(self) -> str:
        """One line of an events file."""
        return json.dumps(self.to_dict())


@dataclass
class _Component:
    level: str = OK
    fault: str = ''
    since: float = 0.0
    refined: bool = False
    cleared: int = -1  # the classification history counts rows after this one


def condition_changes(level: Level, enter: np.ndarray, leave: np.ndarray) -> list[tuple[int, Level]]:
    """Where a two-state base condition changes over rows: starting at ``level`` (OK or WARN) it
    goes to WARN at the first row of ``enter`` (N,) bool while OK and back to OK at the first row
    of ``leave`` (N,) bool while WARN; returns [(row, new level)] in row order."""
    changes, k = [], 0
    while k < len(enter):
        found = (enter if level == OK else leave)[k:].nonzero()[0]
        if not len(found):
            break
        k += int(found[0])
        level = WARN if level == OK else OK
        changes.append((k, level))
        k += 1
    return changes


@dataclass
class _BlockStates:
    """The states after each row (N, ...) of the last block :meth:`DecisionMaker._alarms_holding`
    judged, for :meth:`DecisionMaker._rewind` (the torque levels keep theirs in
    :class:`~youbot_fdi.fdi.recursions.ExponentialAverage`)."""

    evidence: np.ndarray | None = None  # the magnitude CUSUMs (N, families, n)
    shift: np.ndarray | None = None  # the torque shift CUSUMs (N, 2, n)
    stamps: np.ndarray | None = None  # [s] (N,)
    judged: np.ndarray | None = None  # the evidence in thresholds (N, families, n)
    rise: np.ndarray | None = None  # [s] the shared families' last rise (N, shared, n)
    below: np.ndarray | None = None  # [s] excited time below the threshold (N, families, n)
    alarm: np.ndarray | None = None  # (N, families, n) bool


class DecisionMaker:
    """Turns :class:`~youbot_fdi.fdi.residuals.ResidualFrame` s into :class:`FaultEvent` s.

    Parameters
    ----------
    wheel_names : sequence of str
    settings : FdiSettings
    residual_data : dict
        The runtime residual set (``config/residuals/*.yaml``): ``faults`` and ``residuals`` with
        their fault signatures.
    """

    def __init__(self, wheel_names: Sequence[str], settings: FdiSettings, residual_data: dict) -> None:
        self.wheel_names = list(wheel_names)
        self.suffixes = [wheel_suffix(w) for w in self.wheel_names]
        self.settings = settings
        self.n = len(self.wheel_names)
        self.signatures = self._signatures(residual_data)
        #: the evidence each family needs to alarm (F, 1)
        self._thresholds = np.asarray(settings.family_thresholds, dtype=float)[:, None]
        if self._thresholds.shape != (len(FAMILIES), 1):
            msg = (f'family_thresholds has {len(settings.family_thresholds)} values; one per '
                   f'family is needed: {", ".join(FAMILIES)}')
            raise ConfigError(msg)
        shape = (len(FAMILIES), self.n)
        self._evidence = np.zeros(shape)  # the magnitude CUSUMs
        self._shift = np.zeros((2, self.n))  # the torque shift CUSUMs, upward and downward
        self._level = ExponentialAverage(self.n)  # each wheel's recent torque residual [N·m]
        self._typical_bound = ExponentialAverage(self.n)  # ... and the log of its usual bound
        self._last_stamp = np.nan  # [s] of the last row judged
        self._rest_stamp = NEVER  # [s] of the last row in which every wheel stood
        #: the sum (n + 1,) and count of the wheel speeds [rad/s] and load factors read since the
        #: torque levels' operating point started (count 0: none yet)
        self._operating_point = (np.zeros(self.n + 1), 0)
        #: the mean speeds of the operating point each row of the last block was judged against
        #: (:meth:`operating_point_changes`) (N, n) [rad/s]
        self.reference_speeds = np.zeros((0, self.n))
        #: the wheel speeds averaged over load_time_constant (:meth:`friction_change`) [rad/s],
        #: and the stamp [s] of the last row they took
        self._speed_average, self._speed_stamp = ExponentialAverage(self.n), np.nan
        self._pass = _BlockStates()  # the states after each row of the last block judged
        self._rise = np.full(shape, NEVER)  # stamp [s] at which the evidence last rose to SHARED_SHARE
        self._below = np.zeros(shape)  # excited time below the threshold since the last alarm [s]
        self.load_level = OK  # of the load condition (OK or WARN)
        self.range_level = OK  # of the learned correction's calibrated range (OK or WARN)
        self._outside_stamp = NEVER  # [s] of the last row outside that range
        self.alarm = np.zeros(shape, dtype=bool)
        self._fault_stamp = np.full(self.n, NEVER)  # [s] of the last row with a wheel fault's alarm set
        self.components = {w: _Component() for w in self.wheel_names}
        self.components[BASE] = _Component()
        self.samples = 0
        # The recent rows (stamps; torque residual, its score, torque, speed) for naming fault
        # types; row r of the arrays is row ``_recent_first + r`` of the stream, ``_row`` the one
        # being judged.
        self._recent = (np.empty(0), *(np.empty((0, self.n)),) * 4)
        self._recent_first = 0
        self._row = -1
        self._isolation_cache = {}
        self._used_scores = False  # the last diagnosis depended on the scores, not only the alarms
        #: what is published: the raw states above as episodes (youbot_fdi/fdi/lifecycle.py)
        self.lifecycle = EventLifecycle(LifecycleSettings.of(settings))
        #: a list to keep the evidence of every row judged, in thresholds (N, families, n) per
        #: block (reports, incident pages); None (the default): not kept
        self.evidence_trace = None

    def _signatures(self, residual_data):
        """fault -> (kind, wheel index, set of torque-family wheel indices, observer indices)."""
        index = {s: i for i, s in enumerate(self.suffixes)}
        by_fault = {f: set() for f in residual_data['faults']}
        for residual in residual_data['residuals']:
            for fault in residual['faults']:
                by_fault[fault].add(residual['name'])
        table = {}
        for fault, names in by_fault.items():
            suffix = next((w for w in self.suffixes if fault.endswith('_' + w)), None)
            if suffix is None:
                continue
            kind = fault[:-len(suffix) - 1]
            torque = {index[n.split('_', 1)[1]] for n in names
                      if n.startswith('torque_') and n.split('_', 1)[1] in index}
            observer = {index[n.split('_', 1)[1]] for n in names
                        if n.startswith('observer_') and n.split('_', 1)[1] in index}
            table[fault] = (kind, index[suffix], frozenset(torque), frozenset(observer))
        return table

    # ------------------------------------------------------------------ alarms
    def _excited(self, velocity, torque):
        """Wheels (..., n) that move or carry current: only they can show that they are healthy
        again (a fault is not cleared because the wheel stood still)."""
        return ((np.abs(velocity) > self.settings.stuck_speed)
                | (np.abs(torque) > EXCITED_TORQUE_SIGMAS * self.settings.torque_sigma))

    def _breaking_away(self, velocity, stamps):
        """Rows (N,) of speeds ``velocity`` (N, n) [rad/s] at ``stamps`` (N,) [s] in which the base
        breaks away from rest: some wheel turns, less than ``breakaway_time`` after a row in which
        every wheel stood (slower than ``stuck_speed``). Leaves the state after the last row."""
        resting = (np.abs(velocity) <= self.settings.stuck_speed).all(axis=1)
        stamps = np.asarray(stamps, dtype=float)
        rest = last_true_value(resting, stamps, self._rest_stamp)
        self._rest_stamp = float(rest[-1])
        return ~resting & (stamps - rest < self.settings.breakaway_time)

    def operating_point_changes(self, velocity: np.ndarray, load_factor: np.ndarray) -> np.ndarray:
        """Rows (N,) of speeds ``velocity`` (N, n) [rad/s] and load factors ``load_factor`` (N,)
        [-] in which the wheels leave the operating point the torque levels were learned at, which
        then starts afresh there. The operating point is the mean of the speeds and of the load
        factor since it started; a row leaves it when some wheel's speed differs from its mean by
        more than ``shift_operating_range`` of that mean plus the reading's noise
        (``SPEED_NOISE_SIGMAS`` x ``speed_sigma``: a quantised or noisy reading is not a move),
        or the load factor differs from its mean by more than ``shift_operating_range`` of it.
        A creeping wheel is not a standing one here: between rest and a few tenths of a rad/s a
        wheel's friction goes from whatever static friction holds to its sliding level, over a
        width the model's Coulomb step (a regularisation) does not know, so a level learned at
        rest says nothing of a creep (the randomized suite's seed 8, fresh when found, plants 78
        and 96: a start on a floor x2.4 with the load factor at 2.7, every wheel below
        ``stuck_speed`` for 0.4 s while one's residual rose 0 -> 0.2 N·m against a level learned
        standing, a false ``stuck``; a wheel creeping from +0.03 through zero to -0.23 rad/s
        over 1.6 s beside wheels at 2-12 rad/s, judged against a level learned all along it, a
        false ``friction``). The model's bias depends on the operating point (the
        contact law, the friction split, the speed, and the load factor the explained friction is
        scaled by: a floor the factor has moved to is a model the level was not learned with), so
        a level learned at one says nothing of the residual at another; a fault changes the
        residual at the same one. Each wheel's range is its own: its bias is a function of its
        own speed (friction is not linear in it: the Coulomb step, the contact law), which a
        slow wheel beside a fast one changes by as much as the fast one's. Leaves the reference
        after the last row, and in ``reference_speeds`` (N, n) [rad/s] the mean speeds each row
        was judged against (a row that starts a point: its own; one that lacks a reading: NaN)."""
        points = np.concatenate([np.asarray(velocity, dtype=float),
                                 np.asarray(load_factor, dtype=float).reshape(-1, 1)], axis=1)
        total, count = self._operating_point
        if len(points) == 1 and count > 0:  # one row (the live path): the same, in plain steps
            row, mean = points[0], total / count
            finite = bool(np.isfinite(row).all())
            away = finite and bool(self._away(row, mean))
            self.reference_speeds = (row if away else mean if finite else np.full_like(row, np.nan))[None, :-1]
            if not finite:
                return np.zeros(1, dtype=bool)
            if away:
                self._operating_point = (row.copy(), 1)
                return np.ones(1, dtype=bool)
            self._operating_point = (total + row, count + 1)
            return np.zeros(1, dtype=bool)
        changes = np.zeros(len(points), dtype=bool)
        rows = np.flatnonzero(np.isfinite(points).all(axis=1))  # a wheel without a reading: skipped
        reference = np.full(points.shape, np.nan)  # a skipped row has none
        reference[rows] = points[rows]  # a row that starts a point is its own
        usable = points[rows]
        k, size = 0, OPERATING_BLOCK_FIRST
        while k < len(usable):
            if count == 0:
                total, count, k = usable[k].copy(), 1, k + 1
                continue
            block = usable[k:k + size]
            sums = total + np.cumsum(block, axis=0)
            means = np.concatenate([(total / count)[None],
                                    sums[:-1] / (count + np.arange(1, len(block)))[:, None]])
            away = self._away(block, means).nonzero()[0]
            if not len(away):
                reference[rows[k:k + len(block)]] = means
                total, count, k = sums[-1], count + len(block), k + len(block)
                size = min(2 * size, OPERATING_BLOCK_MOST)
                continue
            reference[rows[k:k + int(away[0])]] = means[:int(away[0])]
            size = min(max(2 * int(away[0]), OPERATING_BLOCK_FIRST), OPERATING_BLOCK_MOST)
            k += int(away[0])
            changes[rows[k]] = True
            total, count, k = usable[k].copy(), 1, k + 1
        self._operating_point = (total, count)
        self.reference_speeds = reference[:, :-1]
        return changes

    def _away(self, points, means):
        """Whether operating points ``points`` (..., n + 1: the speeds [rad/s], the load factor)
        are away from the means ``means`` (..., n + 1) (see :meth:`operating_point_changes`),
        (...)."""
        s, n = self.settings, self.n
        speeds = means[..., :n]
        allowance = (s.shift_operating_range * np.abs(speeds)
                     + SPEED_NOISE_SIGMAS * s.speed_sigma)
        return ((np.abs(points[..., :n] - speeds) > allowance).any(axis=-1)
                | (np.abs(points[..., n] - means[..., n]) > s.shift_operating_range * means[..., n]))

    def friction_change(self, velocity: np.ndarray, friction_level: np.ndarray,
                        stamps: np.ndarray) -> np.ndarray:
        """How far [N·m] (N, n) each wheel's friction may have moved without a fault between the
        speeds of the operating point its torque level stands for (``reference_speeds``, from
        :meth:`operating_point_changes` on the same rows) and its speed now, for its friction
        level ``friction_level`` (N, n) [N·m] (at the load factor): the level times the change
        of speed relative to the faster of the two (at least ``stuck_speed``: slower is
        standing, the Coulomb span's, ``ResidualEvaluator.shift_scale``). The change of speed is
        the larger of the reading ``velocity`` (N, n) [rad/s] at ``stamps`` (N,) [s] averaged over
        ``load_time_constant`` (the time over which friction is estimated) and the reading itself
        less its noise (``SPEED_NOISE_SIGMAS`` x ``speed_sigma``) from the reference: a quantised
        or noisy reading's jitter is no change of speed (the residual's friction is at the
        wheel's speed, not at its reading), and a change beyond the noise is one at once, before
        the average has followed it. Continues (and leaves) the average's state.

        Why: the level stands for every speed within ``shift_operating_range`` of its mean, and
        how a friction level changes with the speed depends on its split into Coulomb (it stays)
        and viscous friction (it follows the speed), which a calibration at one speed, on one
        floor, cannot pin down and a floor or load factor it did not see changes. So the torque
        shift's scale allows the change an all-viscous friction would make (a Robotino wheel on
        another covering at x2.1 slowing from 1.8 to 1.4 rad/s within its operating point drifted
        its residual by 0.3 N·m, 1.5 scales without this: a false torque_loss alarm of the real
        folds). A steady speed adds nothing."""
        velocity = np.asarray(velocity, dtype=float)
        stamps = np.asarray(stamps, dtype=float)
        steps = stamps - shifted(self._speed_stamp, stamps)
        gain = -np.expm1(-np.where(np.isnan(steps), np.inf, steps) / self.settings.load_time_constant)
        read = np.isfinite(velocity)
        self._speed_average.advance(np.where(read, gain[:, None], 0.0), np.where(read, velocity, 0.0))
        speed = np.where(read, self._speed_average.after(), np.nan)
        if len(stamps):
            self._speed_stamp = float(stamps[-1])
        reference = self.reference_speeds
        departure = np.maximum(np.abs(speed - reference),
                               np.abs(velocity - reference) - SPEED_NOISE_SIGMAS * self.settings.speed_sigma)
        faster = np.maximum(np.maximum(np.abs(speed), np.abs(reference)), self.settings.stuck_speed)
        change = np.abs(friction_level) * departure / faster
        return np.where(np.isfinite(change), change, 0.0)

    def sample_weights(self, stamps: np.ndarray) -> np.ndarray:
        """The evidence weight of each row at ``stamps`` (N,) [s]: ``min(1, dt / evidence_interval)``
        with dt since the row before (1 for the first row after a start)."""
        stamps = np.asarray(stamps, dtype=float)
        steps = stamps - shifted(self._last_stamp, stamps)
        interval = self.settings.evidence_interval
        weight = np.where(steps >= interval - STAMP_TOLERANCE, 1.0, steps / interval)  # stamps round
        return np.where(np.isfinite(weight) & (weight > 0.0), weight, 1.0)

    def evidence(self, z: np.ndarray, shift: np.ndarray, weight: np.ndarray) -> np.ndarray:
        """The accumulated evidence (N, families, n) after each row of scores ``z`` (N, families,
        n) and torque shift scores ``shift`` (N, n), each row weighted by ``weight`` (N,)
        (:meth:`sample_weights`), continuing from the state before; leaves the state after the last
        row.

        The magnitude CUSUM of each residual, ``min(z, cap) - evidence_drift``; for the torque
        residuals also the CUSUMs of their shift, up and down, ``min(+-shift, cap) - shift_drift``
        (held below ``SHIFT_CEILING`` thresholds). Judged in thresholds (:meth:`_judged`).
        """
        magnitude, shift_up_down = self.increments(z, shift, weight)
        g = cusum(magnitude, self._evidence)
        shifted = bounded_cusum(shift_up_down, self._shift,
                                SHIFT_CEILING * self.settings.shift_threshold)
        self._pass.evidence, self._pass.shift = g, shifted
        self._evidence, self._shift = g[-1], shifted[-1]
        return self._judged(g, shifted)

    def increments(self, z: np.ndarray, shift: np.ndarray,
                   weight: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The CUSUMs' increments: of the magnitudes (N, families, n), ``min(z, cap) -
        evidence_drift``, and of the torque shifts up and down (N, 2, n), ``min(+-shift, cap) -
        shift_drift``, each row weighted by ``weight`` (N,). Stateless (``identify`` bounds the
        alarm rate of the same increments, fdi/alarm_rate.py)."""
        s = self.settings
        w = np.asarray(weight, dtype=float)[:, None, None]
        return (w * (np.minimum(z, s.evidence_cap) - s.evidence_drift),
                w * (self.shift_scores(shift) - s.shift_drift))

    def shift_scores(self, shift: np.ndarray) -> np.ndarray:
        """The scores (N, 2, n) the torque shift CUSUMs (up, down) take from the torque shift
        ``shift`` (N, n), in its scale (:meth:`torque_shift`): ``+shift`` and ``-shift``, each
        capped at ``evidence_cap``."""
        cap = self.settings.evidence_cap
        capped = clip(shift, -cap, cap)[:, None]
        return np.concatenate([capped, -capped], axis=1)

    def _judged(self, magnitude, shift):
        """The evidence in thresholds (..., families, n), an alarm from 1: the magnitude CUSUMs
        ``magnitude`` (..., families, n) over their family's threshold, the torque family's
        raised to its shift CUSUMs ``shift`` (..., 2, n) over ``shift_threshold``."""
        judged = magnitude / self._thresholds
        judged[..., TORQUE, :] = np.maximum(judged[..., TORQUE, :],
                                            shift.max(axis=-2) / self.settings.shift_threshold)
        return judged

    def torque_shift(self, residual: np.ndarray, bound: np.ndarray, scale: np.ndarray,
                     stamps: np.ndarray, hold: np.ndarray, fresh: np.ndarray) -> np.ndarray:
        """Each wheel's torque residual's departure from its recent level, in its scale: ``(r_k -
        m_{k-1}) / s_k`` (N, n), from the torque residuals ``residual``, their bounds ``bound`` and
        scales ``scale`` (the bound without its allowances for steady biases, which cancel in a
        departure from the level) (N, n) [N·m] at ``stamps`` (N,) [s] (0 where it does not count).
        Leaves the state after the last row.

        The level m is the exponential average over ``shift_time_constant`` of the residual
        clipped to its bound (an excess beyond it is the magnitude CUSUM's, and a spike moves the
        level little), each sample weighted by its precision against the wheel's usual bound,
        ``min(1, (typical / u)^2)`` with ``typical`` the geometric average of the bound over the same
        memory (a manoeuvre's transient, judged with a bound a hundred times wider, says little
        about the level). It holds still for the wheels in ``hold`` (n,) (those whose torque alarm
        is set: a fault does not become the new normal) and for missing residuals, and starts
        afresh at the rows ``fresh`` (N,): where the base breaks away from rest or the wheels leave
        the operating point the level was learned at (:meth:`operating_point_changes`: the
        model's bias changes with it), which add nothing to it and have no shift. Slow changes of friction or
        contact move it along; a fault shifts the residual faster than it follows. The shift
        counts once half the memory holds samples (``SHIFT_KNOWN_LEVEL``).
        """
        stamps = np.asarray(stamps, dtype=float)
        steps = stamps - shifted(self._last_stamp, stamps)
        memory = -np.expm1(-np.where(np.isnan(steps), 0.0, steps) / self.settings.shift_time_constant)
        present = np.isfinite(residual)
        residual = np.where(present, residual, 0.0)
        log_bound = np.log(np.where(present, bound, 1.0))
        typical_before, _ = self._typical_bound.advance(memory[:, None] * present, log_bound)
        precision = np.minimum(1.0, np.exp(2.0 * (typical_before - log_bound)))
        steady = ~fresh[:, None]  # rows that tell nothing of the level start it afresh
        judged = present & steady
        level_before, weight_before = self._level.advance(
            memory[:, None] * precision * (judged & ~hold), clip(residual, -bound, bound),
            keep=steady | hold)
        known = judged & (weight_before >= SHIFT_KNOWN_LEVEL)
        shift = np.divide(residual - level_before, scale, out=np.zeros_like(level_before),
                          where=known & (scale > 0.0))
        self._pass.stamps = stamps
        self._last_stamp = stamps[-1]
        return shift

    def _alarms(self, z, excited, stamps, torque, torque_bound, torque_scale, breaking_away,
                moved):
        """Alarm states (N, families, n) after each row of scores ``z`` (N, families, n),
        ``excited`` (N, n), stamps (N,) [s] and the torque residuals ``torque`` with their bounds
        ``torque_bound`` and shift scales ``torque_scale`` (N, n) [N·m], continuing the counters;
        leaves the state after the last
        row. In the rows ``breaking_away`` (N,) the torque family adds no evidence (score 0) and
        its recent levels start afresh (:meth:`torque_shift`), as they do in the rows ``moved``
        (N,) (:meth:`operating_point_changes`).

        The torque levels hold still for the wheels whose torque alarm is set, and a wheel's
        torque and command evidence is judged as a second fault's beside another wheel's fault
        (:meth:`_faults_elsewhere`; both after the row before), so the block is judged in parts
        within which no torque, command or encoder alarm changes: when one changes, the rows
        after it are judged again from the state after that row.
        """
        rows, start, parts = len(z), 0, []
        if breaking_away.any():
            z = z.copy()
            z[breaking_away, TORQUE] = 0.0
        fresh = breaking_away | moved
        judged, size = [], rows
        while start < rows:
            state = self.alarm.copy()
            part = slice(start, min(start + size, rows))
            alarm = self._alarms_holding(z[part], excited[part], stamps[part], torque[part],
                                         torque_bound[part], torque_scale[part], state[TORQUE],
                                         fresh[part], self._faults_elsewhere(state, stamps[part]))
            # The rows after a change are judged again only if it changes what judges them: the
            # wheels whose torque level holds, or the wheels with a wheel fault's alarm (their
            # neighbours' second-fault rule); one family's alarm giving way to another's on a
            # faulty wheel changes neither, nor does an observer alarm (no wheel fault's, no
            # level's). The last row's change has no rows after it: one row, the live path, has none.
            changes = () if len(alarm) == 1 else (
                (alarm[:-1, TORQUE] != state[TORQUE]).any(axis=1)
                | (alarm[:-1, WHEEL_FAULT_FAMILIES].any(axis=1)
                   != state[WHEEL_FAULT_FAMILIES].any(axis=0)).any(axis=1)).nonzero()[0]
            if not len(changes):
                parts.append(alarm)
                judged.append(self._pass.judged)
                self._remember_faults(alarm, stamps[part])
                start, size = start + len(alarm), 2 * size
                continue
            changed = int(changes[0])  # judged alike with the old hold up to here
            parts.append(alarm[:changed + 1])
            judged.append(self._pass.judged[:changed + 1])
            self._rewind(changed)
            self._remember_faults(alarm[:changed + 1], stamps[start:start + changed + 1])
            # after a change the next may come soon (an alarm at its threshold): the rest is
            # judged in parts, the first REJUDGED_ROWS long, doubling while nothing changes
            start, size = start + changed + 1, REJUDGED_ROWS
        if self.evidence_trace is not None:
            self.evidence_trace.append(np.concatenate(judged))
        return parts[0] if len(parts) == 1 else np.concatenate(parts)

    def _rewind(self, row):
        """Go back to the state after ``row`` of the last block :meth:`_alarms_holding` judged
        (from the per-row states it kept, :class:`_BlockStates`)."""
        states = self._pass
        self._evidence, self._shift = states.evidence[row], states.shift[row]
        self._level.rewind(row)
        self._typical_bound.rewind(row)
        self._last_stamp = states.stamps[row]
        self._rise[SHARED_FAMILIES] = states.rise[row]
        self._below, self.alarm = states.below[row], states.alarm[row]

    def _faults_elsewhere(self, alarm, stamps):
        """Rows x wheels (N, n) at ``stamps`` (N,) [s] beside another wheel's fault: one whose
        wheel fault alarm (torque, command or encoder: an observer alarm alone names no wheel's
        fault) is set in ``alarm`` (families, n), or was less than ``heal_time`` ago (its episode
        is published until then, youbot_fdi/fdi/lifecycle.py)."""
        stamps = np.asarray(stamps, dtype=float)
        heal = self.settings.heal_time
        if not alarm.any() and self._fault_stamp.max() <= stamps.min() - heal:
            return np.zeros((len(stamps), self.n), dtype=bool)  # no fault to be beside (nearly always)
        faulty = alarm[WHEEL_FAULT_FAMILIES].any(axis=0)
        recent = faulty | (stamps[:, None] - self._fault_stamp < heal)
        return recent.sum(axis=1, keepdims=True) - recent > 0

    def _remember_faults(self, alarm, stamps):
        """Keep the stamp of the last of the rows ``alarm`` (N, families, n) at ``stamps`` (N,)
        [s] in which each wheel had a wheel fault's alarm set."""
        if not alarm.any():  # no alarm at all (nearly always)
            return
        faulty = alarm[:, WHEEL_FAULT_FAMILIES].any(axis=1)
        if faulty.any():
            self._fault_stamp = last_true_value(faulty, np.asarray(stamps, dtype=float),
                                                self._fault_stamp)[-1]

    def _alarms_holding(self, z, excited, stamps, torque, torque_bound, torque_scale, hold, fresh,
                        elsewhere):
        """:meth:`_alarms` with the torque levels of the wheels in ``hold`` (n,) held throughout,
        each row's wheels in ``elsewhere`` (N, n) judged beside another wheel's fault
        (:meth:`_shared`).

        Sequentially: an alarm is set where the evidence is at the threshold and grows, cleared
        once ``below`` (excited time since it last was at the threshold, each row's weighted time)
        reaches ``release_time``, and otherwise kept. So the alarm after row k is decided by the
        latest row that set or cleared it. Evidence at the threshold that drains tells of an
        excess past, which was not a fault then (it was shared with other wheels, whose evidence
        has since drained faster): it holds an alarm, it does not raise one.
        """
        threshold = 1.0  # the evidence is judged in thresholds
        before = self._judged(self._evidence, self._shift)
        weight = self.sample_weights(stamps)
        step = weight * self.settings.evidence_interval  # [s] the time each row counts for
        evidence = self.evidence(z, self.torque_shift(torque, torque_bound, torque_scale, stamps,
                                                      hold, fresh), weight)
        self._pass.judged = evidence
        over = evidence >= threshold
        over[:, SHARED_FAMILIES] &= ~self._shared(before[SHARED_FAMILIES], evidence[:, SHARED_FAMILIES],
                                                 z[:, SHARED_FAMILIES], stamps, elsewhere)
        rows = len(over)
        previous = before[None] if rows == 1 else np.concatenate([before[None], evidence[:-1]])
        growing = evidence > previous
        raised = over & growing
        release = self.settings.release_time - STAMP_TOLERANCE  # summed steps round
        if rows == 1:  # the same latch, one row (the live path)
            self._below = np.where(over[0], 0.0, self._below + excited[0] * step[0])
            self.alarm = raised[0] | (self.alarm & (self._below < release))
            return self.alarm[None]
        counted = np.cumsum((excited[:, None, :] & ~over) * step[:, None, None], axis=0)
        at_last_over = np.maximum.accumulate(np.where(over, counted, -1), axis=0)
        below = np.where(at_last_over >= 0, counted - at_last_over, self._below + counted)
        index = np.arange(rows)[:, None, None]
        last_set = np.maximum.accumulate(np.where(raised, index, -1), axis=0)
        last_clear = np.maximum.accumulate(np.where(below >= release, index, -1), axis=0)
        alarm = np.where(last_set > last_clear, True, np.where(last_clear > last_set, False, self.alarm))
        self._pass.below, self._pass.alarm = below, alarm
        self._below, self.alarm = below[-1], alarm[-1]
        return alarm

    def _shared(self, before, evidence, z, stamps, elsewhere):
        """Rows x families x wheels (N, f, n) whose evidence is shared with the other wheels', from
        the evidence (N, f, n) and scores ``z`` (N, f, n); ``before`` (f, n) is the evidence before
        the first row. Shared is a wheel's evidence with a score below ``second_fault_score``
        beside another wheel's fault (``elsewhere`` (N, n), :meth:`_faults_elsewhere`: a fault
        elsewhere changes how the base moves, see below), and evidence past ``SHARED_SHARE`` of
        the threshold on half the wheels or more, when either

        - it rose within ``shared_window`` of the rise on those wheels (a surface, load or timing
          change they share, until the load factor has caught up), or
        - this wheel's score is below ``second_fault_score``: a modest excess while other wheels'
          evidence is up (a fault elsewhere changes how the base moves) is not a fault of its own;
          a clear one is (a second fault).
        """
        s = self.settings
        level = SHARED_SHARE  # of the threshold
        up = evidence >= level
        beside = elsewhere[:, None, :] & (z < s.second_fault_score) if elsewhere.any() else None
        if not up.any():  # nothing shared (nearly every live row): no rise, nothing to compare
            self._pass.rise = self._rise[SHARED_FAMILIES][None].repeat(len(up), axis=0)
            return up if beside is None else beside
        was_up = np.concatenate([(before >= level)[None], up[:-1]])
        rise = np.where(up & ~was_up, np.asarray(stamps, dtype=float)[:, None, None], NEVER)
        rise = np.maximum(np.maximum.accumulate(rise, axis=0), self._rise[SHARED_FAMILIES])
        self._pass.rise = rise
        self._rise[SHARED_FAMILIES] = rise[-1]
        together = (up[..., None, :]
                    & (np.abs(rise[..., :, None] - rise[..., None, :]) <= s.shared_window))
        rose_together = together.sum(axis=-1) * 2 >= self.n
        co_occurring = (up.sum(axis=-1) * 2 >= self.n)[..., None]
        shared = rose_together | (co_occurring & (z < s.second_fault_score))
        return shared if beside is None else shared | beside

    def _load_events(self, stamps, factors):
        """WARN/OK events of the load condition over rows (stamps (N,), load factors (N,))."""
        departure = np.abs(np.asarray(factors, dtype=float) - 1.0)
        warn = self.settings.load_warn
        changes = condition_changes(self.load_level, departure > warn,
                                    departure < LOAD_RELEASE * warn)
        events = [FaultEvent(float(stamps[k]), level, BASE, LOAD_CHANGE, ('load_factor',),
                             f'surface or load changed: friction x{factors[k]:.2f} on every wheel'
                             if level == WARN else f'load back to normal (x{factors[k]:.2f})')
                  for k, level in changes]
        if changes:
            self.load_level = changes[-1][1]
        return events

    def _range_events(self, stamps, outside):
        """WARN/OK events of the calibrated range over rows (stamps (N,), wheel bit masks (N,),
        see :func:`~youbot_fdi.fdi.learned.wheel_mask`): WARN at the first row outside, OK at the
        first row ``unseen_release`` s after the last one outside."""
        outside = np.asarray(outside, dtype=float)
        out = outside > 0.0
        if self.range_level == OK and not out.any():  # the usual case: nothing to do
            return []
        stamps = np.asarray(stamps, dtype=float)
        last_out = last_true_value(out, stamps, self._outside_stamp)
        back = ~out & (stamps - last_out >= self.settings.unseen_release)
        events = []
        for k, level in condition_changes(self.range_level, out, back):
            if level == WARN:
                wheels = ', '.join(self.suffixes[w] for w in masked_wheels(outside[k], self.n))
                detail = (f'operating point beyond what calibration covered ({wheels}): bounds '
                          "widened with the prior's uncertainty there, the physics without the "
                          'learned correction')
            else:
                detail = 'operating point back within the calibrated range'
            events.append(FaultEvent(float(stamps[k]), level, BASE, UNSEEN_OPERATING_POINT,
                                     ('outside_calibration',), detail))
            self.range_level = level
        if len(stamps):
            self._outside_stamp = float(last_out[-1])
        return events

    def _can_diagnose(self, alarm, position_frozen, silent):
        """Rows of ``alarm`` (N, families, n) that give a diagnosis when every component is OK:
        a torque or encoder alarm, a position frozen while moving (``position_frozen`` (N, n)
        counts), a wheel silent for ``wheel_timeout`` (``silent`` (N, n) [s]), or fewer than half
        the wheels off their command path."""
        frozen = (position_frozen >= self.settings.frozen_samples).any(axis=1)
        if not alarm.any():  # no alarm (nearly every row): a frozen position or a silent wheel
            return frozen | self._silent(silent).any(axis=1)
        commands = alarm[:, COMMAND].sum(axis=1)
        return (alarm[:, TORQUE].any(axis=1) | alarm[:, ENCODER].any(axis=1)
                | frozen | self._silent(silent).any(axis=1)
                | ((commands > 0) & (commands * 2 < self.n)))

    def _silent(self, silent):
        """Wheels (..., n) without a reading for ``wheel_timeout``, from their silent times [s]:
        no fresh data from their module (the driver's NaN) for more samples in a row than the
        stated rate allows (``silent_samples``), as the base's comm_loss is for all."""
        return silent >= self.settings.wheel_timeout

    def _family(self, name):
        return self.alarm[FAMILIES.index(name)]

    # ------------------------------------------------------------------ isolation
    def _isolate_torque(self, fired, z_observer):
        """Wheel diagnoses from the alarming torque residuals: {wheel index: structural class}.

        Hypotheses: every single fault whose torque signature covers the alarms, and the set of
        actuator/friction faults of exactly the alarming wheels. The fewest silent residuals win
        (a silent residual exonerates the faults it would see), then the fewest faults.
        """
        if not fired:
            return {}
        if fired not in self._isolation_cache:
            hypotheses = [(len(torque - fired), 1, kind, wheel)
                          for kind, wheel, torque, _ in self.signatures.values() if fired <= torque]
            hypotheses.append((0, len(fired), 'actuator', None))
            silent, size, kind, _ = min(hypotheses, key=lambda h: (h[0], h[1]))
            winners = [h for h in hypotheses if (h[0], h[1]) == (silent, size)]
            self._isolation_cache[fired] = (
                None if any(h[2] in ACTUATOR_CLASS for h in winners)
                else [h[3] for h in winners if h[2] == SENSOR_CLASS])
        sensors = self._isolation_cache[fired]
        if sensors is None:
            return {w: 'actuator' for w in fired}
        self._used_scores = True
        observed = [w for w in sensors if self._family('observer')[w]]
        wheel = max(observed or sensors, key=lambda w: z_observer[w])
        return {wheel: SENSOR_CLASS}

    def _name_actuator_fault(self, wheel, frame, component):
        """stuck, torque_loss or friction for a wheel in the actuator/friction class, or
        encoder_freeze when its readings are frozen while its current is fresh: a reading frozen
        near standstill looks like a wheel that does not move for its torque."""
        frozen = self.settings.frozen_samples
        if frame.frozen[wheel] >= frozen and frame.effort_frozen[wheel] < frozen:
            return FaultKind.ENCODER_FREEZE
        speed, torque = frame.velocity[wheel], frame.torque[wheel]
        commanded = frame.command[wheel] if frame.velocity_mode else np.inf
        if abs(speed) < self.settings.stuck_speed and (abs(commanded) > self.settings.stuck_speed
                                                       or abs(torque) > self.settings.torque_sigma * 10):
            return FaultKind.STUCK
        residual, _, measured, speeds = self._recent_rows(wheel, component)
        known = np.isfinite(residual) & np.isfinite(measured) & np.isfinite(speeds)
        residual, measured, speeds = residual[known], measured[known], speeds[known]
        if len(residual) < 2:
            return FaultKind.UNKNOWN
        errors = []
        for regressor in (measured, speeds):
            denominator = float(regressor @ regressor)
            gain = float(regressor @ residual) / denominator if denominator > 0 else 0.0
            errors.append(float(np.sum((residual - gain * regressor) ** 2)))
        return FaultKind.TORQUE_LOSS if errors[0] <= errors[1] else FaultKind.FRICTION

    def _active(self, faults):
        """Wheel indices currently in ERROR with one of ``faults`` (FaultKind values)."""
        return {w for w, name in enumerate(self.wheel_names)
                if self.components[name].level == ERROR and self.components[name].fault in faults}

    def _diagnose(self, frame, z):
        """{wheel index: (FaultKind, residual names)} for this frame (None: the actuator/friction
        class, to be named).

        Faults already found explain the residuals they disturb: a speed-sensor fault explains
        every torque and command residual (M couples the wheels), any fault explains the other
        wheels' command paths (a wheel that misbehaves drags the base).
        """
        diagnoses = {}
        self._used_scores = False
        sensor_faults = (FaultKind.ENCODER_FREEZE.value, FaultKind.COMM_LOSS.value)
        still_frozen = {w for w in self._active(sensor_faults)
                        if frame.frozen[w] >= self.settings.frozen_samples}
        stopped = set(np.flatnonzero(frame.position_frozen >= self.settings.frozen_samples).tolist())
        # A wheel without any reading for wheel_timeout (its module silent: the driver's NaN)
        # lost its communication, whatever else is known of it.
        for w in np.flatnonzero(self._silent(frame.silent)):
            diagnoses[int(w)] = (FaultKind.COMM_LOSS, (f'silent_{self.suffixes[w]}',))
        # A freeze shows as a position that stops following the speed (encoder_<w>), or repeats
        # exactly while the wheel is commanded and measured (current mode: or witnessed by the
        # other wheels) to turn; frozen readings alone prove nothing: a standing wheel reads the
        # same every sample.
        for w in sorted((set(np.flatnonzero(self._family('encoder'))) | still_frozen | stopped)
                        - set(diagnoses)):
            # Every reading of the module stale together (effort too, as long as the rest): no
            # fresh data from it. Evidence may name the fault before frozen_samples are counted.
            stale = frame.effort_frozen[w]
            frozen_effort = (stale >= self.settings.frozen_samples
                             or (stale >= MIN_STALE_SAMPLES and stale >= frame.frozen[w]))
            kind = FaultKind.COMM_LOSS if frozen_effort else FaultKind.ENCODER_FREEZE
            diagnoses[int(w)] = (kind, (f'encoder_{self.suffixes[w]}',))
        if diagnoses:
            return diagnoses
        fired = frozenset(int(w) for w in np.flatnonzero(self._family('torque')))
        for wheel, kind in self._isolate_torque(fired, z[FAMILIES.index('observer')]).items():
            names = tuple(f'torque_{self.suffixes[w]}' for w in sorted(fired))
            if kind == SENSOR_CLASS:
                diagnoses[wheel] = (FaultKind.UNKNOWN, names + (f'observer_{self.suffixes[wheel]}',))
            else:
                diagnoses[wheel] = (None, names)  # named by _step, only if it needs the name
        faulty = self._active({k.value for k in FaultKind}) | set(diagnoses)
        disagreeing = np.flatnonzero(self._family('command'))
        # Half the wheels or more off their command path at once is not one wheel running away: the commands
        # and the samples disagree in time (late commands, a clock offset), or the base is held.
        if len(disagreeing) * 2 >= self.n:
            return diagnoses
        for w in disagreeing:
            if not fired and not faulty - {int(w)}:
                # A wheel that stands while commanded to turn is blocked, not running away.
                # A wheel that lags behind its command path (slower, same direction) lacks torque
                # or meets friction, named from the torque history, unless its torque residual
                # stayed within bounds all along: then its current explains its motion, and its
                # drive holds a set-point it was not given (a runaway held below the command).
                # One that is faster or turns the other way runs away.
                speed = frame.velocity[w]
                predicted = speed - frame.values['command'][w]
                lagging = (frame.velocity_mode and abs(speed) < abs(predicted)
                           and speed * predicted >= 0.0
                           and not self._torque_within_bounds(w, self.components[self.wheel_names[w]]))
                kind = None if lagging else FaultKind.RUNAWAY
                diagnoses[int(w)] = (kind, (f'command_{self.suffixes[w]}',))
        return diagnoses

    # ------------------------------------------------------------------ state and events
    def _transition(self, key, level, fault, stamp, residuals=(), detail=''):
        component = self.components[key]
        if (component.level, component.fault) == (level, fault):
            return None
        if level != OK and component.level == OK:
            component.since, component.refined = stamp, False
            component.cleared = self._row
        component.level, component.fault = level, fault
        return FaultEvent(stamp, level, key, fault, tuple(residuals), detail)

    def update(self, frame: ResidualFrame) -> list[FaultEvent]:
        """Process one residual frame; returns the fault events it causes (usually none): a
        batch of one (:meth:`update_batch`)."""
        return self.update_batch(ResidualBatch.of_frames([frame]))

    def update_batch(self, batch: ResidualBatch) -> list[FaultEvent]:
        """Process a :class:`~youbot_fdi.fdi.residuals.ResidualBatch`; returns its events (the
        same whatever the batches it is cut into)."""
        return self.lifecycle.feed(self._update_batch(batch), batch.stamp)

    def _update_batch(self, batch):
        """The raw events of a :class:`~youbot_fdi.fdi.residuals.ResidualBatch` (before the
        lifecycle). The alarms are computed for the whole batch.
        Frames are examined one by one only where something can change: not while every component
        is OK and no alarm can give a diagnosis, and not while a row repeats the alarms and frozen
        flags of a row that changed nothing (unless the diagnosis depended on the scores, or a
        fault type is due to be refined).
        """
        rows = len(batch)
        if not rows:
            return []
        z = batch.scores()
        judged = z.copy()  # a wheel's torque evidence: as far as the parity relations confirm it
        judged[:, TORQUE] *= batch.torque_confirmed
        breaking_away = self._breaking_away(batch.velocity, batch.stamp)
        moved = self.operating_point_changes(batch.velocity, batch.load_factor)
        scale = batch.torque_scale + self.friction_change(batch.velocity, batch.friction_level,
                                                          batch.stamp)
        alarm = self._alarms(judged, self._excited(batch.velocity, batch.torque), batch.stamp,
                             batch.values['torque'], batch.bounds['torque'], scale, breaking_away,
                             moved)
        capable = self._can_diagnose(alarm, batch.position_frozen, batch.silent).nonzero()[0]
        frozen = self.settings.frozen_samples
        load_events = (self._load_events(batch.stamp, batch.load_factor)
                       + self._range_events(batch.stamp, batch.outside_calibration))
        if rows == 1:  # one row (the live path): it is the change
            changed = np.zeros(1, dtype=int)
        else:
            flags = np.concatenate([alarm.reshape(rows, -1), batch.frozen >= frozen,
                                    batch.effort_frozen >= frozen, batch.position_frozen >= frozen,
                                    self._silent(batch.silent)], axis=1)
            changed = np.flatnonzero(np.concatenate([[True], (flags[1:] != flags[:-1]).any(axis=1)]))
        self.samples += rows
        self._remember(batch.values['torque'], z[:, TORQUE], batch.torque, batch.velocity, batch.stamp)
        first = self._recent_first + len(self._recent[0]) - rows
        final, events, k = self.alarm, [], 0
        while k < rows:
            if self._all_ok():
                following = capable[capable.searchsorted(k):]
                if not len(following):
                    break
                k = int(following[0])
            before = self._state()
            self._row, self.alarm = first + k, alarm[k]  # the diagnosis sees the row's alarms
            found = self._step(batch.frame(k), z[k])
            events += found
            k += 1
            if not found and not self._used_scores and self._state() == before:
                following = changed[changed.searchsorted(k):]
                stop = int(following[0]) if len(following) else rows
                due = int(batch.stamp.searchsorted(self._refinement_due() - STAMP_TOLERANCE))
                k = max(k, min(stop, due))
        self._row, self.alarm = first + rows - 1, final
        if load_events:  # in stamp order with the wheels' (a stable sort keeps same-row order)
            events = sorted(load_events + events, key=lambda e: e.stamp)
        return events

    def _state(self):
        return [(c.level, c.fault, c.refined) for c in self.components.values()]

    def _refinement_due(self):
        """The earliest stamp [s] at which a latched fault type is due to be refined (inf: none)."""
        window = self.settings.classification_window
        return min((c.since + window for c in self.components.values()
                    if c.level == ERROR and c.fault in REFINABLE and not c.refined), default=np.inf)

    def _all_ok(self):
        return all(c.level == OK for c in self.components.values())

    def _remember(self, residual, score, torque, velocity, stamp):
        """Append rows (torque residual, its score |r|/u, torque, speed (N, n); stamps (N,)) to
        the recent rows, dropping those older than ``classification_window`` before the oldest
        new one."""
        old_stamp = self._recent[0]
        keep = int(old_stamp.searchsorted(stamp[0] - self.settings.classification_window))
        self._recent = tuple(np.concatenate([old[keep:], new]) for old, new in
                             zip(self._recent, (stamp, residual, score, torque, velocity)))
        self._recent_first += keep

    def _torque_within_bounds(self, wheel, component):
        """True when ``wheel``'s torque residual has stayed within its bound (score below 1)
        over the classification window up to the row being judged: its current explains its
        motion."""
        scores = self._recent_rows(wheel, component)[1]
        return bool(len(scores)) and float(scores.max()) < AT_BOUND

    def _recent_rows(self, wheel, component):
        """(torque residual, its score, torque, speed) of ``wheel`` over the classification
        window up to the row being judged, since the component's episode began."""
        stamps = self._recent[0]
        row = self._row - self._recent_first
        start = max(int(np.searchsorted(stamps[:row + 1],
                                        stamps[row] - self.settings.classification_window)),
                    component.cleared + 1 - self._recent_first)
        return tuple(values[start:row + 1, wheel] for values in self._recent[1:])

    def _step(self, frame, z):
        """Diagnose one frame with its scores ``z`` (families, n) and the alarms in ``self.alarm``."""
        diagnoses = self._diagnose(frame, z)
        events = []
        for w, name in enumerate(self.wheel_names):
            component = self.components[name]
            if w in diagnoses:
                kind, residuals = diagnoses[w]
                if component.level == ERROR:
                    # One episode, one type: named at the alarm, refined once when the window is
                    # full (only between the types the window decides), then kept until OK.
                    due = (component.fault in REFINABLE and not component.refined
                           and frame.stamp - component.since >= self.settings.classification_window)
                    if due:
                        kind = kind or self._name_actuator_fault(w, frame, component)
                    if due and kind.value in REFINABLE:
                        component.refined = True
                    else:
                        kind = FaultKind(component.fault)
                elif kind is None:
                    kind = self._name_actuator_fault(w, frame, component)
                detail = f'|r|/u = {z[TORQUE][w]:.1f} (torque), {z[COMMAND][w]:.1f} (command)'
                event = self._transition(name, ERROR, kind.value, frame.stamp, residuals, detail)
            elif component.level != OK and not self._wheel_alarms(w):
                event = self._transition(name, OK, component.fault, frame.stamp, (), 'residuals back in bounds')
            else:
                event = None
            if event is not None:
                events.append(event)
        return events

    def _wheel_alarms(self, w):
        return bool(self.alarm[:, w].any())

    def data_stalled(self, last_stamp: float) -> list[FaultEvent]:
        """No /joint_states since ``last_stamp`` for longer than comm_timeout: comm_loss of the base."""
        event = self._transition(BASE, ERROR, FaultKind.COMM_LOSS.value,
                                 last_stamp + self.settings.data_timeout, (),
                                 f'no /joint_states for more than {self.settings.data_timeout:g} s')
        return self.lifecycle.immediate(event) if event is not None else []

    def data_resumed(self, stamp: float) -> list[FaultEvent]:
        """Fresh data after a stall: the base's comm_loss clears."""
        if self.components[BASE].level == OK:
            return []
        event = self._transition(BASE, OK, FaultKind.COMM_LOSS.value, stamp, (), 'data resumed')
        return self.lifecycle.feed([event], [stamp]) if event is not None else []

    def reset(self, stamp: float, detail: str = 'reset after a repair') -> list[FaultEvent]:
        """Clear every latched fault (after a repair): the evidence, the alarms and the load
        condition start afresh; one OK event per component that was not OK, stamped ``stamp``
        [s]. Returns (events, what was cleared as 'wheel: fault' strings)."""
        for key in self.components:
            self.components[key] = _Component()
        self.load_level = self.range_level = OK
        events = self.lifecycle.reset(stamp, detail)
        cleared = [f'{e.wheel or BASE_NAME}: {e.fault}' for e in events]
        self._outside_stamp = NEVER
        self._evidence[:] = 0.0
        self._shift[:] = 0.0
        self._level = ExponentialAverage(self.n)
        self._typical_bound = ExponentialAverage(self.n)
        self._last_stamp = np.nan
        self._rest_stamp = NEVER
        self._operating_point = (np.zeros(self.n + 1), 0)
        self._speed_average, self._speed_stamp = ExponentialAverage(self.n), np.nan
        self._below[:] = 0
        self.alarm[:] = False
        self._fault_stamp[:] = NEVER
        self._rise[:] = NEVER
        return events, cleared

    def freeze_frame(self, frame: ResidualFrame | None = None) -> dict:
        """The decision's state now, for an incident's sidecar (plain YAML types): per wheel
        (suffix) the evidence of each family in thresholds (an alarm from 1) and the alarming
        families; with the last residual ``frame``, its stamp [s], each residual and bound, and
        the load factor [-]."""
        judged = self._judged(self._evidence, self._shift)
        wheels = {}
        for w, suffix in enumerate(self.suffixes):
            entry = {'evidence': {f: round(float(judged[i, w]), 4) for i, f in enumerate(FAMILIES)},
                     'alarm': [f for i, f in enumerate(FAMILIES) if self.alarm[i, w]]}
            if frame is not None:
                entry['residual'] = {f: round(float(frame.values[f][w]), 6) for f in FAMILIES}
                entry['bound'] = {f: round(float(frame.bounds[f][w]), 6) for f in FAMILIES}
                entry['speed'] = round(float(frame.velocity[w]), 4)
                entry['torque'] = round(float(frame.torque[w]), 5)
            wheels[suffix] = entry
        state = {'samples': self.samples, 'load_condition': str(self.load_level),
                 'wheels': wheels}
        if frame is not None:
            state = {'stamp': round(float(frame.stamp), 6),
                     'load_factor': round(float(frame.load_factor), 4), **state}
        return state

    def states(self) -> dict[str, tuple[Level, str]]:
        """Component -> (level, fault) as published (the base's own faults, not its conditions)."""
        return {k: self.lifecycle.shown((k, FAULT_CHANNEL)) for k in self.components}
