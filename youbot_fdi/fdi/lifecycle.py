"""The event lifecycle: an alarm is an episode, confirmed once, held, and healed with hysteresis.

The decision judges every sample; its raw state of a component (a wheel, the base, each base
condition) can flap where the evidence hovers at its threshold. What users see are episodes:

- **confirm**: a raw alarm (ERROR, or a condition's WARN) is published once it has stood
  ``confirm_time``;
- **hold**: the episode stays published while the raw state drops and returns; each return is
  counted (an intermittent fault is one episode with a count, not a flap);
- **heal**: OK is published once the raw state has been OK for ``heal_time``;
- **dwell**: no two events of one component closer than ``dwell`` (a type refined within an
  episode waits for it);
- **one type**: an episode's type is refined at most once among the types the classification
  decides between (``REFINABLE``): the decision names an actuator fault afresh from the torque
  history at hand each time its raw alarm returns, and a type that flips between
  ``torque_loss`` and ``friction`` within one episode is that classification's noise, not news.

Timed by the sample stamps of the rows the decision judged, never by a wall clock, so a replay
and the live nodes publish the same events; :meth:`EventLifecycle.feed` takes a block of rows
(the replay) or one (the nodes). Plain Python, one explicit state record per component.
"""
from __future__ import annotations

from dataclasses import dataclass, replace
import math
from typing import TYPE_CHECKING

import numpy as np

from youbot_fdi.faults import CONDITIONS, Level, REFINABLE

if TYPE_CHECKING:  # names in annotations only
    from collections.abc import Iterable
    from youbot_fdi.fdi.settings import FdiSettings
    from youbot_fdi.fdi.decision import FaultEvent

OK = Level.OK
FAULT_CHANNEL = 'fault'  # a wheel's faults, or the base's own (comm_loss): one channel each
NEVER = -math.inf


@dataclass(frozen=True)
class LifecycleSettings:
    """Times of the lifecycle [s] (``config/fdi.yaml``)."""

    confirm_time: float = 0.0
    heal_time: float = 1.0
    dwell: float = 0.5

    @classmethod
    def of(cls, settings: FdiSettings) -> LifecycleSettings:
        """From :class:`~youbot_fdi.fdi.settings.FdiSettings`."""
        return cls(settings.confirm_time, settings.heal_time, settings.dwell)


@dataclass
class Episode:
    """What one component shows and what its raw state is doing."""

    shown: object = None  # the last published event (None: OK, nothing published)
    raw: object = None  # the latest raw event (None: OK from the start)
    raw_since: float = NEVER  # [s] when the raw (level, fault) began
    last_event: float = NEVER  # [s] of the last published event
    returns: int = 0  # raw alarms that came back within the shown episode
    refined: bool = False  # the shown episode's type was refined (among REFINABLE) once

    @property
    def shown_state(self):
        return (OK, '') if self.shown is None or self.shown.level == OK else (self.shown.level,
                                                                               self.shown.fault)

    @property
    def raw_state(self):
        return (OK, '') if self.raw is None or self.raw.level == OK else (self.raw.level, self.raw.fault)


def component(event: FaultEvent) -> str:
    """The lifecycle component of an event: (wheel or None, channel)."""
    return (event.wheel, event.fault if event.fault in CONDITIONS else FAULT_CHANNEL)


def closest_events(events: Iterable[FaultEvent]) -> float:
    """The shortest time [s] between two published events of one component in ``events`` (any
    order; inf with no component evented twice): the dwell bounds it from below (the fault
    benchmark prints it per suite)."""
    last, closest = {}, math.inf
    for event in sorted(events, key=lambda e: e.stamp):
        key = component(event)
        if key in last:
            closest = min(closest, event.stamp - last[key])
        last[key] = event.stamp
    return closest


class EventLifecycle:
    """Raw decision events in, published episodes out (see the module docstring)."""

    def __init__(self, settings: LifecycleSettings) -> None:
        self.settings = settings
        self.episodes = {}  # component -> Episode

    # ------------------------------------------------------------------ timing
    def _due(self, episode):
        """The stamp [s] at which ``episode``'s raw state is to be published (inf: nothing to
        publish): confirmation or healing time after it began, and the dwell after the last
        event."""
        raw, shown = episode.raw_state, episode.shown_state
        if raw == shown:
            return math.inf
        if raw[0] == OK:
            wait = self.settings.heal_time
        elif shown[0] == OK:
            wait = self.settings.confirm_time
        else:
            wait = 0.0  # the type refined within an episode: only the dwell
        return max(episode.raw_since + wait, episode.last_event + self.settings.dwell)

    def _publish(self, episode, stamp):
        raw = episode.raw
        if episode.raw_state[0] == OK:
            fault = episode.shown.fault
            detail = (f'healed: no evidence for {self.settings.heal_time:g} s'
                      + (f'; it came back {episode.returns} time(s) within the episode'
                         if episode.returns else ''))
            published = replace(raw, stamp=stamp, fault=fault, residuals=(), detail=detail) \
                if raw is not None else None
            episode.returns, episode.refined = 0, False
        else:
            published = replace(raw, stamp=stamp)
            was = episode.shown_state[1]
            episode.refined |= was in REFINABLE and raw.fault in REFINABLE  # within the episode
        episode.shown = published
        episode.last_event = stamp
        return published

    # ------------------------------------------------------------------ input
    def _take(self, event):
        """A raw event: the component's raw state changes (or, the same state, its detail)."""
        key = component(event)
        episode = self.episodes.setdefault(key, Episode())
        shown = episode.shown_state
        if (episode.refined and event.level == shown[0] and event.fault != shown[1]
                and event.fault in REFINABLE and shown[1] in REFINABLE):
            event = replace(event, fault=shown[1])  # refined once already: the episode's type
        state = (OK, '') if event.level == OK else (event.level, event.fault)
        if state == episode.raw_state:
            if state[0] != OK:
                episode.raw = event  # a fresher detail for the same state
            return
        if state[0] != OK and episode.raw_state[0] == OK and episode.shown_state[0] != OK:
            episode.returns += 1  # back within the episode: held, counted
        episode.raw, episode.raw_since = event, event.stamp

    def feed(self, raw_events: list[FaultEvent], stamps: np.ndarray) -> list[FaultEvent]:
        """The published events of a block of rows stamped ``stamps`` (N,) [s] (sorted) whose raw
        events are ``raw_events`` (stamped at those rows, in order). A row's raw events are taken
        before anything due at that row is published; publications carry their row's stamp."""
        stamps = np.asarray(stamps, dtype=float)
        published = []
        if not len(stamps):
            for event in raw_events:
                self._take(event)
            return published
        k, row = 0, 0
        while row < len(stamps):
            at = stamps[row]
            while k < len(raw_events) and raw_events[k].stamp <= at:
                self._take(raw_events[k])
                k += 1
            for episode in self.episodes.values():
                if self._due(episode) <= at:
                    event = self._publish(episode, float(at))
                    if event is not None:
                        published.append(event)
            # skip to the next row where something can happen
            due = min((self._due(e) for e in self.episodes.values()), default=math.inf)
            following = raw_events[k].stamp if k < len(raw_events) else math.inf
            row = max(row + 1, int(stamps.searchsorted(min(due, following), side='left')))
        for event in raw_events[k:]:  # stamped after the last row: taken, timed later
            self._take(event)
        return published

    def immediate(self, event: FaultEvent) -> list[FaultEvent]:
        """A raw event that is its own confirmation (the base silent for the data timeout):
        published at once (the dwell still holds it back if an event was just published)."""
        self._take(event)
        episode = self.episodes[component(event)]
        if self._due(episode) <= event.stamp:
            return [e for e in (self._publish(episode, event.stamp),) if e is not None]
        return []

    def reset(self, stamp: float, detail: str) -> list[FaultEvent]:
        """Every component back to OK at once (a repair): the OK events of what was shown."""
        events = []
        for episode in self.episodes.values():
            if episode.shown_state[0] != OK:
                events.append(replace(episode.shown, stamp=stamp, level=OK, residuals=(),
                                      detail=detail))
        self.episodes.clear()
        return events

    def shown(self, key: tuple[str, str]) -> tuple[Level, str]:
        """(level, fault) a component shows."""
        episode = self.episodes.get(key)
        return (OK, '') if episode is None else episode.shown_state
