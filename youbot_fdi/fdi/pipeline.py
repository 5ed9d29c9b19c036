"""The FDI pipeline: residual generator + decision, fed a recording chunk by chunk.

The same object serves the offline replay and the live nodes, so a recording replayed offline
gives the same decisions as the nodes gave live.
"""
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import yaml

from youbot_fdi.config_paths import config_dir
from youbot_fdi.errors import ConfigError
from youbot_fdi.fdi.decision import DecisionMaker
from youbot_fdi.fdi.residuals import ResidualBatch, ResidualGenerator, ResidualSpread
from youbot_fdi.fdi.settings import FdiSettings
from youbot_fdi.model.profile import load_model, load_profile, PlatformModel
from youbot_fdi.samples import CommandBatch, RepeatedMessages
from youbot_fdi.settings import load_settings, settings_from_mapping
from youbot_fdi.structure.generate import wheel_suffix
from youbot_fdi.topics import JOINT_STATES, WHEEL_COMMANDS
from youbot_fdi.yamlio import load_yaml

DEFAULT_RESIDUAL_MODEL = 'youbot'


def configure(settings, params_path=None):
    """The model and settings to run with: an ``identify`` parameter file overrides the profile
    and the noise floors of ``settings``."""
    if not params_path:
        return load_model(settings.profile), settings
    profile = load_profile(params_path)
    if profile.fdi:
        settings = settings_from_mapping(FdiSettings, {**settings.__dict__, **profile.fdi},
                                         source=str(params_path))
    return PlatformModel(profile), settings


def build_pipeline(params_path=None, fdi_config=None, keep_frames=False):
    """The model and pipeline a replay (and a benchmark) uses: ``config/fdi.yaml`` (or
    ``fdi_config``), overridden by an ``identify`` parameter file."""
    model, settings = configure(load_settings(FdiSettings, 'fdi', fdi_config), params_path)
    return model, FdiPipeline(model, settings, keep_frames=keep_frames)


def load_residual_data(path=None, wheel_names=None):
    """The runtime residual set written by ``youbot-fdi structure --write-residuals``: ``path``,
    or the shipped set (``config/residuals/``) whose faults cover every wheel of ``wheel_names``
    (the youBot's first)."""
    if not path:
        shipped = sorted((config_dir() / 'residuals').glob('*.yaml'),
                         key=lambda p: p.stem != DEFAULT_RESIDUAL_MODEL)
        path = shipped[0] if shipped else config_dir() / 'residuals' / f'{DEFAULT_RESIDUAL_MODEL}.yaml'
        for candidate in shipped if wheel_names else ():
            faults = set((_read_residual_file(candidate) or {}).get('faults', ()))
            if all(f'actuator_{wheel_suffix(w)}' in faults for w in wheel_names):
                path = candidate
                break
    data = _read_residual_file(Path(path))
    if not isinstance(data, dict) or 'residuals' not in data or 'faults' not in data:
        msg = f'{path}: not a residual set (needs faults and residuals)'
        raise ConfigError(msg)
    return data


def _read_residual_file(path):
    try:
        return load_yaml(path.read_text())
    except (OSError, yaml.YAMLError) as err:
        msg = f'{path}: cannot read the residual set: {err}'
        raise ConfigError(msg) from err


@dataclass(frozen=True)
class ReplayResult:
    """What a replay of a recording found."""

    events: list  # FaultEvent, in order
    counters: dict  # the reader's message counters (used, skipped ...) and the generator's restarts
    has_commands: bool  # the recording had the command topic
    damage: object = None  # youbot_fdi.bag.salvage.Damage of a damaged recording, else None
    spread: object = None  # youbot_fdi.fdi.residuals.ResidualSpread of the residuals


class FdiPipeline:
    """Residuals and decisions for one base, fed a recording's chunks
    (:class:`~youbot_fdi.samples.SampleChunk`).

    The residual generator and the decision maker are the objects the live nodes run (one sample
    at a time there, a block at a time here: the same computation).

    Parameters
    ----------
    model : PlatformModel
    settings : FdiSettings
    residual_data : dict, optional
        Default: the shipped residual set of the youBot model.
    keep_frames : bool
        Keep every residual frame (for reports, :meth:`residuals`).
    """

    def __init__(self, model, settings=FdiSettings(), residual_data=None, keep_frames=False):
        self.model = model
        self.settings = settings
        residual_data = residual_data or load_residual_data(settings.residual_file or None,
                                                            model.wheel_names)
        self.generator = ResidualGenerator(model, settings)
        self.decision = DecisionMaker(model.wheel_names, settings, residual_data)
        self._kept = [] if keep_frames else None
        #: the pooled RMS of every residual family so far
        self.spread = ResidualSpread()
        self._last_stamp = None
        #: re-sent /joint_states messages, left out (youbot_fdi.samples.RepeatedMessages)
        self.repeated = RepeatedMessages()

    def residuals(self):
        """Every residual frame so far as one :class:`~youbot_fdi.fdi.residuals.ResidualBatch`
        (None unless ``keep_frames``)."""
        if self._kept is None:
            return None
        return ResidualBatch.concatenate(self._kept) if self._kept else None

    def feed(self, chunk):
        """A chunk of samples; returns the fault events it causes, in order.

        A gap in /joint_states longer than ``data_timeout`` is the base's comm_loss (raised at the
        gap, cleared by the sample after it).
        """
        joints, commands, before = chunk.joints, chunk.commands, chunk.commands_before
        fresh = self.repeated.fresh(joints)
        if not fresh.all():  # re-sent messages: no fresh data, as if missing
            joints, before = joints.select(fresh), before[fresh]
        rows = len(joints)
        seen = np.maximum.accumulate(np.concatenate([[-np.inf if self._last_stamp is None
                                                      else self._last_stamp], joints.stamp]))
        gaps = np.flatnonzero(np.isfinite(seen[:-1])
                              & (joints.stamp - seen[:-1] > self.settings.data_timeout))
        if rows:
            self._last_stamp = float(seen[-1])
        events, applied = [], 0
        bounds = [0, *(g for g in gaps.tolist() if g > 0), rows]  # one segment at least
        for start, stop in zip(bounds[:-1], bounds[1:]):
            if start in gaps:
                events += self.decision.data_stalled(float(seen[start]))
            if start < rows:
                events += self.decision.data_resumed(float(joints.stamp[start]))
            last = stop == rows
            upto = len(commands) if last else int(before[stop - 1])
            batch = self.generator.update_batch(
                joints.rows(start, stop),
                CommandBatch(commands.stamp[applied:upto], commands.velocity_mode[applied:upto],
                             commands.values[applied:upto]),
                before[start:stop] - applied)
            applied = upto
            if self._kept is not None and len(batch):
                self._kept.append(batch)
            self.spread.add(batch)
            events += self.decision.update_batch(batch)
        if (self._last_stamp is not None and len(commands)
                and commands.stamp.max() - self._last_stamp > self.settings.data_timeout):
            # Commands go on, joint states do not: the base went silent (what the decision
            # node's timer finds live); cleared by the next joint state. Judged after this
            # chunk's samples, which would otherwise clear it at once.
            events += self.decision.data_stalled(self._last_stamp)
        return events

    def replay(self, path, joint_topic=None, command_topic=None, on_event=None, on_progress=None):
        """Feed a rosbag2 recording through the pipeline, streaming, a chunk at a time.

        ``on_event(event)`` is called as each event is found (a caller can write them as they
        come); ``on_progress(messages done, total)`` after every chunk. A damaged recording is
        analysed as far as it can be read (the result's ``damage`` says where it ended).
        """
        from youbot_fdi.bag.reader import RecordingReader
        events = []
        with RecordingReader(path, self.model.wheel_names, joint_topic or JOINT_STATES,
                             command_topic or WHEEL_COMMANDS, keep_partial=True) as reader:
            for chunk in reader.chunks(on_progress=on_progress):
                for event in self.feed(chunk):
                    events.append(event)
                    if on_event is not None:
                        on_event(event)
            return ReplayResult(events, {**reader.counters, **self.generator.counters,
                                         'messages_repeated': self.repeated.count},
                                reader.has_commands, reader.damage, self.spread)
