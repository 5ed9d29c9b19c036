"""Fault reactions: from fault events to what the base is commanded (the report's robust control).

Plain numpy, no rclpy. :class:`Reactor` takes the fault events of the decision
(:class:`~youbot_fdi.fdi.decision.FaultEvent`), applies the policy of ``config/reactions.yaml``
(:class:`ReactionSettings`) and says, per /cmd_vel, what the wheels are commanded
(:meth:`Reactor.wheel_speeds`) and, per /joint_states, what odometry and control take as the
wheel speeds (:meth:`Reactor.readings`). Each reaction it starts or ends is a
:class:`Reaction`: an INFO event line (``"level": "INFO", "action": …``).
"""
from dataclasses import dataclass
import json

import numpy as np

from youbot_fdi.errors import ConfigError
from youbot_fdi.faults import CONDITIONS, FaultKind, Level
from youbot_fdi.model.allocation import Allocation, AllocationError
from youbot_fdi.model.kinematics import limit_wheel_speeds

MOTOR_OFF, STOP, DEGRADE, SUBSTITUTE, NONE = 'motor_off', 'stop', 'degrade', 'substitute', 'none'
ACTIONS = (MOTOR_OFF, STOP, DEGRADE, SUBSTITUTE, NONE)
INFO = Level.INFO
#: Actions that switch the wheel's motor off: a runaway, and a frozen encoder (the module's own
#: velocity loop runs on the frozen reading and would drive the wheel to its current limit).
SWITCHES_OFF = (MOTOR_OFF, SUBSTITUTE)


@dataclass(frozen=True)
class ReactionSettings:
    """The reaction policy (``config/reactions.yaml``): an action per fault kind."""

    react: bool = False  # apply the reactions at all
    on_runaway: str = MOTOR_OFF
    on_stuck: str = STOP
    on_comm_loss: str = STOP
    on_torque_loss: str = DEGRADE
    on_friction: str = DEGRADE
    on_encoder_freeze: str = SUBSTITUTE
    on_unknown: str = STOP
    #: wheel-speed cap while driving degraded [rad/s], in place of the bridge's ``max_wheel_speed``:
    #: the healthy wheels turn faster than their rolling speed to carry a lost one. Default: the
    #: firmware's factory maximum positioning velocity (4000 rpm motor, TMCM-1632 base.cfg).
    degraded_max_wheel_speed: float = 16.2
    motor_off_service: str = '/driver_shim/switch_off_motor'  # + '_<wheel suffix>'
    #: a reaction starts only once its alarm has stood this long without clearing [s]: a reaction
    #: to a false alarm (a wheel switched off, the base stopped) costs more than waiting
    confirmation_time: float = 0.1

    def validate(self, source='<settings>'):
        for kind in FaultKind:
            action = getattr(self, f'on_{kind.value}')
            if action not in ACTIONS:
                msg = f'{source}: on_{kind.value} must be one of {", ".join(ACTIONS)}, got {action!r}'
                raise ConfigError(msg)
        if not self.degraded_max_wheel_speed > 0.0:
            msg = f'{source}: degraded_max_wheel_speed must be > 0, got {self.degraded_max_wheel_speed}'
            raise ConfigError(msg)
        if not self.confirmation_time >= 0.0:
            msg = f'{source}: confirmation_time must be >= 0 s, got {self.confirmation_time}'
            raise ConfigError(msg)

    def action(self, fault):
        """The action for a fault kind (its value, e.g. ``'torque_loss'``); ``unknown``'s for
        anything else."""
        return getattr(self, f'on_{fault}', self.on_unknown)


@dataclass(frozen=True)
class Reaction:
    """A reaction started (or ended): one INFO line of the events file."""

    stamp: float  # [s], the fault event's stamp
    action: str  # one of ACTIONS, or 'end_<action>' when it ends
    wheel: object  # joint name or None
    fault: str
    detail: str = ''
    level: str = INFO

    def to_dict(self):
        """The JSON object of an events file line (the fault-event keys plus ``action``)."""
        return {'stamp': round(self.stamp, 6), 'level': self.level, 'wheel': self.wheel,
                'fault': self.fault, 'action': self.action, 'residuals': [], 'detail': self.detail}

    def to_json(self):
        """One line of an events file."""
        return json.dumps(self.to_dict())


class Reactor:
    """The reactions in force for one base.

    Parameters
    ----------
    kinematics : Kinematics
    settings : ReactionSettings
    """

    def __init__(self, kinematics, settings=ReactionSettings()):
        self.kinematics = kinematics
        self.settings = settings
        self.names = list(kinematics.platform.names)
        self._active = {}  # component (wheel or None) -> (fault, action)
        self._pending = {}  # component -> the ERROR event waiting for its confirmation_time
        #: action -> the Allocation without its wheels (DEGRADE: driving, SUBSTITUTE: readings)
        self._around = {DEGRADE: None, SUBSTITUTE: None}

    # ------------------------------------------------------------------ state
    @property
    def pending(self):
        """True while an alarm waits for its confirmation (:meth:`confirm`)."""
        return bool(self._pending)

    @property
    def stopped(self):
        """True while a reaction holds the base still."""
        return any(action in (STOP, MOTOR_OFF) for _, action in self._active.values())

    def _lost(self, action):
        allocation = self._around[action]
        return [self.names[k] for k in (allocation.lost if allocation else ())]

    @property
    def degraded(self):
        """Wheel names driven around (degraded driving), in wheel order."""
        return self._lost(DEGRADE)

    @property
    def driving_degraded(self):
        """True while the other wheels carry a lost wheel (degraded or substituted) and the base
        is not stopped: the wheel-speed cap is ``degraded_max_wheel_speed``."""
        return self._around[DEGRADE] is not None and not self.stopped

    @property
    def substituted(self):
        """Wheel names whose reading is replaced by its kinematic estimate."""
        return self._lost(SUBSTITUTE)

    def _wheels(self, action):
        """Wheel indices the allocation of ``action`` leaves out: a substituted wheel is driven
        around too (its firmware loop runs on the frozen reading, so its motor is off)."""
        actions = (DEGRADE, SUBSTITUTE) if action == DEGRADE else (action,)
        return sorted((self.names.index(w) for w, (_, a) in self._active.items()
                       if a in actions and w in self.names))

    def _rebuild(self, stamp):
        """The allocations of the reactions in force (built once here, not per sample); a layout
        that loses rank turns degraded driving or substitution into a stop (a Reaction saying so)."""
        notes = []
        for action in self._around:
            wheels = self._wheels(action)
            try:
                self._around[action] = (Allocation.for_lost(self.kinematics.jacobian, wheels, self.names)
                                        if wheels else None)
            except AllocationError as err:
                self._around[action] = None
                for wheel in (self.names[k] for k in wheels):
                    fault = self._active[wheel][0]
                    self._active[wheel] = (fault, STOP)
                    notes.append(Reaction(stamp, STOP, wheel, fault, str(err)))
        return notes

    def on_event(self, event):
        """Take a fault event; returns the reactions it starts or ends (in order). An ERROR starts
        its fault's action (replacing that component's previous one) once it is confirmed: it
        has stood ``confirmation_time`` without an OK (:meth:`confirm`; at once when that is
        0); an OK (cleared, or the decision's reset) ends it, or drops it unconfirmed."""
        if (not self.settings.react or event.level not in (Level.ERROR, Level.OK)
                or event.fault in CONDITIONS):  # a base condition, not a fault: nothing to do
            return []
        if event.level == Level.OK and self._pending.pop(event.wheel, None) is not None \
                and event.wheel not in self._active:
            return []  # cleared before it was confirmed: nothing was started
        if event.level == Level.ERROR and self.settings.confirmation_time > 0.0:
            self._pending[event.wheel] = event
            return self.confirm(event.stamp)
        return self._start(event)

    def confirm(self, stamp):
        """The reactions of the alarms confirmed by ``stamp`` [s] (they have stood
        ``confirmation_time``); call with every sample's stamp."""
        due = [e for e in self._pending.values()
               if stamp - e.stamp >= self.settings.confirmation_time]
        reactions = []
        for event in sorted(due, key=lambda e: e.stamp):  # each still sees the others pending
            reactions += self._start(event)
        for event in due:
            del self._pending[event.wheel]
        return reactions

    def _start(self, event):
        """Start (ERROR) or end (OK) a component's reaction now."""
        component = event.wheel
        previous = self._active.pop(component, None)
        reactions = []
        if previous is not None:
            reactions.append(Reaction(event.stamp, f'end_{previous[1]}', component, previous[0],
                                      'fault cleared' if event.level == Level.OK else
                                      f'replaced by the reaction to {event.fault}'))
        if event.level == Level.ERROR:
            action = self.settings.action(event.fault)
            if component is None and action in (MOTOR_OFF, DEGRADE, SUBSTITUTE):
                action = STOP  # a fault of the whole base: nothing to do per wheel
            if action == SUBSTITUTE and self._frozen_elsewhere(component):
                # Two wheels' readings frozen: two encoders failing together is far less likely
                # than the data path repeating old readings (a base-level data problem), and
                # substituting or stopping on it would act on a false alarm.
                reactions.append(Reaction(event.stamp, NONE, component, event.fault,
                                          SEVERAL_FROZEN))
                return reactions + self._rebuild(event.stamp)
            if action != NONE:
                self._active[component] = (event.fault, action)
                reactions.append(Reaction(event.stamp, action, component, event.fault,
                                          _DETAILS[action].format(cap=self.settings.degraded_max_wheel_speed)))
        return reactions + self._rebuild(event.stamp)

    # ------------------------------------------------------------------ commands
    def wheel_speeds(self, twist, measured=None):
        """Wheel speeds (n,) [rad/s] (kinematic convention) for the set-point ``twist`` (3,):
        zero while stopped; in degraded driving the healthy wheels carry the twist given the lost
        wheels' ``measured`` speeds (n,, kinematic convention; default: rolling freely), scaled as
        a whole so that no wheel exceeds ``degraded_max_wheel_speed``."""
        if self.stopped:
            return np.zeros(len(self.names))
        allocation = self._around[DEGRADE]
        if allocation is None:
            return self.kinematics.inverse(twist)
        lost = None if measured is None else np.asarray(measured, float)[list(allocation.lost)]
        return limit_wheel_speeds(allocation.wheel_speeds(np.asarray(twist, dtype=float), lost),
                                  self.settings.degraded_max_wheel_speed)

    def readings(self, speeds):
        """Measured wheel speeds (n,) with the substituted wheels replaced by their kinematic
        estimate from the others (for odometry and control)."""
        allocation = self._around[SUBSTITUTE]
        if allocation is None:
            return np.asarray(speeds, dtype=float)
        return allocation.substitute(speeds)

    def _frozen_elsewhere(self, component):
        """True when another wheel's reading is substituted, or waits for confirmation as frozen."""
        return (any(a == SUBSTITUTE for w, (_, a) in self._active.items() if w != component)
                or any(self.settings.action(e.fault) == SUBSTITUTE
                       for w, e in self._pending.items() if w != component))

    def motors_to_switch_off(self):
        """Wheel names whose motor a reaction wants off."""
        return [w for w, (_, a) in self._active.items() if a in SWITCHES_OFF and w is not None]


SEVERAL_FROZEN = ("several wheels' readings look frozen at once: a base-level data problem, not "
                  'a wheel fault; nothing substituted, the base not stopped')
_DETAILS = {
    MOTOR_OFF: 'motor off through the driver shim; base stopped',
    STOP: 'base stopped (zero wheel commands) until the fault clears or decision ~/reset',
    DEGRADE: 'degraded driving: the other wheels carry the base (wheel speeds up to {cap:g} rad/s)',
    SUBSTITUTE: 'reading replaced by its kinematic estimate from the other wheels; motor off '
                '(its loop runs on the frozen reading), the other wheels carry the base',
}
