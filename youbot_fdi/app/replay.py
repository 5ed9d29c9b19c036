"""Replay a rosbag2 recording through an :class:`~youbot_fdi.fdi.pipeline.FdiPipeline`."""
from dataclasses import dataclass

from youbot_fdi.bag.reader import RecordingReader
from youbot_fdi.topics import JOINT_STATES, WHEEL_COMMANDS


@dataclass(frozen=True)
class ReplayResult:
    """What a replay of a recording found."""

    events: list  # FaultEvent, in order
    counters: dict  # the reader's message counters (used, skipped ...) and the generator's restarts
    has_commands: bool  # the recording had the command topic
    damage: object = None  # youbot_fdi.bag.salvage.Damage of a damaged recording, else None
    spread: object = None  # youbot_fdi.fdi.residuals.ResidualSpread of the residuals


def replay_recording(pipeline, path, joint_topic=None, command_topic=None, on_event=None,
                     on_progress=None):
    """Feed the recording at ``path`` through ``pipeline``, streaming, a chunk at a time; a
    :class:`ReplayResult`.

    ``on_event(event)`` is called as each event is found (a caller can write them as they
    come); ``on_progress(messages done, total)`` after every chunk. A damaged recording is
    analysed as far as it can be read (the result's ``damage`` says where it ended).
    """
    events = []
    with RecordingReader(path, pipeline.model.wheel_names, joint_topic or JOINT_STATES,
                         command_topic or WHEEL_COMMANDS, keep_partial=True) as reader:
        for chunk in reader.chunks(on_progress=on_progress):
            for event in pipeline.feed(chunk):
                events.append(event)
                if on_event is not None:
                    on_event(event)
        return ReplayResult(events, {**reader.counters, **pipeline.generator.counters,
                                     'messages_repeated': pipeline.repeated.count},
                            reader.has_commands, reader.damage, pipeline.spread)
