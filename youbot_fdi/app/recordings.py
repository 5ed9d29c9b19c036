"""Recordings read into the core's arrays: identification's :class:`~youbot_fdi.fdi.identify.
RecordingArrays`, and ``identify`` on a recording."""
import numpy as np

from youbot_fdi.app.config import residual_data_for
from youbot_fdi.bag.reader import RecordingReader
from youbot_fdi.fdi.identify import identify, RecordingArrays, require_samples
from youbot_fdi.samples import JointBatch, RepeatedMessages
from youbot_fdi.topics import JOINT_STATES, WHEEL_COMMANDS


def read_arrays(path, model, joint_topic=JOINT_STATES, command_topic=WHEEL_COMMANDS):
    """Read a recording into :class:`~youbot_fdi.fdi.identify.RecordingArrays` (a damaged one as
    far as it can be read); speeds, positions and efforts in the model's convention (drive signs
    applied)."""
    signs = model.kinematics.drive_signs
    blocks, commands = [], []
    with RecordingReader(path, model.wheel_names, joint_topic, command_topic,
                         keep_partial=True) as reader:
        for chunk in reader.chunks():  # whole blocks: a Python object per sample costs more
            blocks.append(chunk.joints)
            commands.extend(chunk.commands.sample(k) for k in range(len(chunk.commands)))
        damage = reader.damage
    count = sum(len(b) for b in blocks)
    require_samples(count, str(path))
    stamp = np.concatenate([b.stamp for b in blocks])
    order = np.argsort(stamp, kind='stable')
    joints = JointBatch(stamp[order], *(signs * np.concatenate([getattr(b, f) for b in blocks])[order]
                                        for f in ('position', 'velocity', 'effort')))
    joints = joints.select(RepeatedMessages().fresh(joints))  # re-sent messages carry nothing
    answered = joints.answered()  # samples some wheels' modules missed count their misses ...
    complete = joints.select(joints.complete())  # ... and are not fitted
    require_samples(len(complete), str(path))
    return RecordingArrays(complete.stamp, complete.position, complete.velocity, complete.effort,
                           commands, damage, answered if not answered.all() else None)


def identify_recording(path, prior_model, settings, fit_gains=True, learn=True):
    """:func:`~youbot_fdi.fdi.identify.identify` on the recording at ``path`` (the residual set
    ``settings`` names, else the shipped one)."""
    return identify(read_arrays(path, prior_model), prior_model, settings,
                    residual_data_for(prior_model, settings), fit_gains=fit_gains, learn=learn,
                    source=str(path))
