"""The FDI pipeline: residual generator + decision, fed sample by sample.

The same object serves the offline replay and the live nodes, so a recording replayed offline
gives the same decisions as the nodes gave live.
"""
from dataclasses import dataclass
from pathlib import Path

import yaml

from youbot_fdi.config_paths import config_dir
from youbot_fdi.errors import ConfigError
from youbot_fdi.fdi.decision import DecisionMaker
from youbot_fdi.fdi.residuals import ResidualGenerator
from youbot_fdi.fdi.settings import FdiSettings
from youbot_fdi.model.profile import load_model, load_profile
from youbot_fdi.settings import settings_from_mapping

DEFAULT_RESIDUAL_MODEL = 'youbot'


def configure(settings, params_path=None):
    """The model and settings to run with: an ``identify`` parameter file overrides the profile
    and the noise floors of ``settings``."""
    if not params_path:
        return load_model(settings.profile), settings
    overrides = load_profile(params_path).fdi or {}
    if overrides:
        settings = settings_from_mapping(FdiSettings, {**settings.__dict__, **overrides},
                                         source=str(params_path))
    return load_model(params_path), settings


def load_residual_data(path=None):
    """The runtime residual set written by ``youbot-fdi structure --write-residuals``."""
    path = Path(path) if path else config_dir() / 'residuals' / f'{DEFAULT_RESIDUAL_MODEL}.yaml'
    try:
        data = yaml.safe_load(path.read_text())
    except (OSError, yaml.YAMLError) as err:
        msg = f'{path}: cannot read the residual set: {err}'
        raise ConfigError(msg) from err
    if not isinstance(data, dict) or 'residuals' not in data or 'faults' not in data:
        msg = f'{path}: not a residual set (needs faults and residuals)'
        raise ConfigError(msg)
    return data


@dataclass(frozen=True)
class ReplayResult:
    """What a replay of a recording found."""

    events: list  # FaultEvent, in order
    counters: dict  # the reader's message counters (used, skipped ...)
    has_commands: bool  # the recording had the command topic


class FdiPipeline:
    """Residuals and decisions for one base.

    Parameters
    ----------
    model : PlatformModel
    settings : FdiSettings
    residual_data : dict, optional
        Default: the shipped residual set of the youBot model.
    keep_frames : bool
        Keep every residual frame (for reports); off for live use.
    """

    def __init__(self, model, settings=FdiSettings(), residual_data=None, keep_frames=False):
        self.model = model
        self.settings = settings
        residual_data = residual_data or load_residual_data(settings.residual_file or None)
        self.generator = ResidualGenerator(model, settings)
        self.decision = DecisionMaker(model.wheel_names, settings, residual_data)
        self.frames = [] if keep_frames else None
        self.last_frame = None
        self._last_stamp = None

    def command(self, sample):
        """A /wheel_commands sample."""
        self.generator.command(sample)

    def joint_state(self, sample):
        """A /joint_states sample; returns the fault events it causes."""
        events = []
        if self._last_stamp is not None and sample.stamp - self._last_stamp > self.settings.comm_timeout:
            events += self.decision.data_stalled(self._last_stamp)
        events += self.decision.data_resumed(sample.stamp)
        if self._last_stamp is None or sample.stamp > self._last_stamp:
            self._last_stamp = sample.stamp
        frame = self.generator.update(sample)
        if frame is None:
            return events
        self.last_frame = frame
        if self.frames is not None:
            self.frames.append(frame)
        return events + self.decision.update(frame)

    def feed(self, sample):
        """Either kind of sample (the reader's stream); returns events."""
        if hasattr(sample, 'kind'):
            self.command(sample)
            return []
        return self.joint_state(sample)

    def replay(self, path, joint_topic=None, command_topic=None, on_event=None, on_progress=None):
        """Feed a rosbag2 recording through the pipeline, streaming.

        ``on_event(event)`` is called as each event is found (so a caller keeps them even when the
        recording breaks part-way and :class:`~youbot_fdi.bag.reader.RecordingError` is raised);
        ``on_progress(done, total)`` after every message.
        """
        from youbot_fdi.bag.reader import JOINT_STATES, RecordingReader, WHEEL_COMMANDS
        events = []
        with RecordingReader(path, self.model.wheel_names, joint_topic or JOINT_STATES,
                             command_topic or WHEEL_COMMANDS) as reader:
            total = reader.message_count
            for done, sample in enumerate(reader.samples(), 1):
                for event in self.feed(sample):
                    events.append(event)
                    if on_event is not None:
                        on_event(event)
                if on_progress is not None:
                    on_progress(done, total)
            return ReplayResult(events, dict(reader.counters), reader.has_commands)
