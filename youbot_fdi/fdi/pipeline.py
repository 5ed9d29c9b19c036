"""The FDI pipeline: residual generator + decision, fed a recording chunk by chunk.

The same objects serve the offline replay (:func:`youbot_fdi.app.replay.replay_recording`) and
the live nodes, so a recording replayed offline gives the same decisions as the nodes gave live.
"""
import numpy as np

from youbot_fdi.fdi.decision import DecisionMaker
from youbot_fdi.fdi.residuals import ResidualBatch, ResidualGenerator, ResidualSpread
from youbot_fdi.samples import CommandBatch, RepeatedMessages


class FdiPipeline:
    """Residuals and decisions for one base, fed a recording's chunks
    (:class:`~youbot_fdi.samples.SampleChunk`).

    The residual generator and the decision maker are the objects the live nodes run (one sample
    at a time there, a block at a time here: the same computation).

    Parameters
    ----------
    model : PlatformModel
    settings : FdiSettings
    residual_data : dict
        The runtime residual set of the structural analysis
        (:func:`youbot_fdi.app.config.load_residual_data` reads it).
    keep_frames : bool
        Keep every residual frame (for reports, :meth:`residuals`).
    """

    def __init__(self, model, settings, residual_data, keep_frames=False):
        self.model = model
        self.settings = settings
        self.generator = ResidualGenerator(model, settings)
        self.decision = DecisionMaker(model.wheel_names, settings, residual_data)
        self._kept = [] if keep_frames else None
        if keep_frames:
            self.decision.evidence_trace = []
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

    def evidence(self):
        """The decision's evidence after every residual frame so far, in thresholds (N,
        families, n) (None unless ``keep_frames``)."""
        trace = self.decision.evidence_trace
        if not trace:
            return None
        return np.concatenate(trace)

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
