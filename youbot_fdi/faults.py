"""The fault vocabulary of CONTRACT.md, shared by fault injection and fault decisions."""
import enum


class FaultKind(str, enum.Enum):
    """Fault types, as they appear in fault events (``"fault": "runaway"``)."""

    RUNAWAY = 'runaway'  # the wheel keeps being driven although its command changed or stopped
    TORQUE_LOSS = 'torque_loss'  # less torque than the current implies
    STUCK = 'stuck'  # the wheel is blocked
    FRICTION = 'friction'  # friction well above the model's
    ENCODER_FREEZE = 'encoder_freeze'  # the position/velocity reading stops changing
    COMM_LOSS = 'comm_loss'  # no fresh data from the base
    UNKNOWN = 'unknown'  # detected, not identified


class Level(enum.StrEnum):
    """An event's level (CONTRACT.md ``"level"``). A ``str``: events serialise and compare as the
    plain words they are in the events file."""

    OK = 'OK'  # the component is healthy again (a fault or condition cleared)
    WARN = 'WARN'  # a condition, not a fault (load_change, unseen_operating_point)
    ERROR = 'ERROR'  # a fault: an alarm
    INFO = 'INFO'  # a reaction's line in the events file (youbot_fdi/fdi/reactions.py)


#: Not a fault: the platform-wide friction/load condition changed (floor covering, payload, slope).
#: Reported as a WARN event not tied to a wheel, with the factor in its detail.
LOAD_CHANGE = 'load_change'

#: Not a fault: the operating point is outside what the learned correction was calibrated on, so
#: the physics alone judges the wheels named in the WARN's detail (youbot_fdi/fdi/learned.py).
UNSEEN_OPERATING_POINT = 'unseen_operating_point'

#: The base conditions reported beside the faults (WARN/OK, not tied to a wheel).
CONDITIONS = (LOAD_CHANGE, UNSEEN_OPERATING_POINT)

#: Fault types the decision's classification window decides between (the torque history: less
#: torque than the current implies, or more friction; or not yet known): an episode's type may
#: be refined among them once (youbot_fdi/fdi/decision.py, lifecycle.py).
REFINABLE = (FaultKind.TORQUE_LOSS.value, FaultKind.FRICTION.value, FaultKind.UNKNOWN.value)

#: Fault kinds a virtual base can inject (everything but ``unknown``).
INJECTABLE = tuple(k for k in FaultKind if k is not FaultKind.UNKNOWN)


def parse_fault_kind(text):
    """``'torque_loss'`` -> FaultKind.TORQUE_LOSS; ValueError naming the choices otherwise."""
    try:
        return FaultKind(text)
    except ValueError:
        msg = f'unknown fault {text!r}; one of {[k.value for k in FaultKind]}'
        raise ValueError(msg) from None
