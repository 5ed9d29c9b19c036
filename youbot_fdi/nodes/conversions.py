"""Message <-> core conversions shared by the nodes (and `youbot-fdi echo`)."""
from array import array

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
import numpy as np
from sensor_msgs.msg import JointState

from youbot_fdi.faults import Level
from youbot_fdi.fdi.decision import BASE_NAME, FaultEvent
from youbot_fdi.nodes.common import NAME_PREFIX, seconds_to_stamp, stamp_to_seconds

LEVELS = {Level.OK: DiagnosticStatus.OK, Level.WARN: DiagnosticStatus.WARN,
          Level.ERROR: DiagnosticStatus.ERROR, 'STALE': DiagnosticStatus.STALE}
LEVEL_NAMES = {value: name for name, value in LEVELS.items()}
BASE_COMPONENT = BASE_NAME  # the hardware id and name of faults not tied to a wheel


def joint_state(stamp, names, position=(), velocity=(), effort=()):
    """A sensor_msgs/JointState stamped ``stamp`` [s]."""
    msg = JointState()
    msg.header.stamp = seconds_to_stamp(stamp)
    msg.name = list(names)
    msg.position = array('d', np.asarray(position, dtype=float).tobytes())
    msg.velocity = array('d', np.asarray(velocity, dtype=float).tobytes())
    msg.effort = array('d', np.asarray(effort, dtype=float).tobytes())
    return msg


def fault_status(event, component_prefix='decision'):
    """One DiagnosticStatus for a fault event (the content of /youbot_fdi/faults)."""
    status = DiagnosticStatus()
    status.level = LEVELS[event.level]
    status.name = f'{NAME_PREFIX}/{component_prefix}: {event.wheel or BASE_COMPONENT}'
    status.message = event.fault if event.level != Level.OK else f'ok ({event.fault} cleared)'
    status.hardware_id = event.wheel or BASE_COMPONENT
    status.values = [KeyValue(key='stamp', value=repr(event.stamp)),
                     KeyValue(key='level', value=event.level),
                     KeyValue(key='wheel', value=event.wheel or ''),
                     KeyValue(key='fault', value=event.fault),
                     KeyValue(key='residuals', value=','.join(event.residuals)),
                     KeyValue(key='detail', value=event.detail)]
    return status


def fault_array(events, stamp):
    """A DiagnosticArray with one status per event (changed component)."""
    array = DiagnosticArray()
    array.header.stamp = seconds_to_stamp(stamp)
    array.status = [fault_status(e) for e in events]
    return array


def event_from_status(status):
    """The :class:`FaultEvent` a /youbot_fdi/faults status carries."""
    values = {kv.key: kv.value for kv in status.values}
    return FaultEvent(stamp=float(values.get('stamp', 'nan')),
                      level=values.get('level') or LEVEL_NAMES.get(status.level, Level.ERROR),
                      wheel=values.get('wheel') or None, fault=values.get('fault', 'unknown'),
                      residuals=tuple(r for r in values.get('residuals', '').split(',') if r),
                      detail=values.get('detail', ''))


def reaction_array(reactions, stamp):
    """A DiagnosticArray with one status per fault reaction (/youbot_fdi/reactions): level OK
    (INFO is not a REP-107 level; the ``level`` KeyValue says INFO), name
    ``youbot_fdi/kinematics_bridge: reaction <wheel|base>``, the event in its KeyValues."""
    array = DiagnosticArray()
    array.header.stamp = seconds_to_stamp(stamp)
    for reaction in reactions:
        status = DiagnosticStatus(level=DiagnosticStatus.OK,
                                  name=f'{NAME_PREFIX}/kinematics_bridge: reaction '
                                       f'{reaction.wheel or BASE_COMPONENT}',
                                  hardware_id=reaction.wheel or BASE_COMPONENT,
                                  message=f'{reaction.action}: {reaction.detail}')
        status.values = [KeyValue(key=key, value=repr(value) if key == 'stamp' else str(value or ''))
                         for key, value in reaction.to_dict().items() if key != 'residuals']
        array.status.append(status)
    return array


def reaction_from_status(status):
    """The :class:`~youbot_fdi.fdi.reactions.Reaction` a /youbot_fdi/reactions status carries."""
    from youbot_fdi.fdi.reactions import Reaction
    values = {kv.key: kv.value for kv in status.values}
    return Reaction(stamp=float(values.get('stamp', 'nan')), action=values.get('action', ''),
                    wheel=values.get('wheel') or None, fault=values.get('fault', ''),
                    detail=values.get('detail', ''))


def labelled_vector(stamp, labels, values, bounds):
    """A labelled vector as JointState: name = label, position = value, velocity = bound."""
    return joint_state(stamp, labels, position=values, velocity=bounds)


def message_seconds(msg):
    """Header stamp of a stamped message [s]."""
    return stamp_to_seconds(msg.header.stamp)

