"""The fault events file: one JSON line per event (CONTRACT.md), written and flushed as each event
comes, so a process killed at any moment leaves every event it had reported as whole lines."""
from pathlib import Path


class EventLog:
    """Append :class:`~youbot_fdi.fdi.decision.FaultEvent` s to ``path`` (created, truncated)."""

    def __init__(self, path):
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._file = self.path.open('w', encoding='utf-8')
        self.count = 0

    def write(self, event):
        """One event as one line, flushed to the operating system before returning."""
        self._file.write(event.to_json() + '\n')
        self._file.flush()
        self.count += 1

    def close(self):
        self._file.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
