"""Settings of ``youbot-fdi fleet`` (``config/fleet.yaml``)."""
from dataclasses import dataclass

from youbot_fdi.errors import ConfigError


@dataclass(frozen=True)
class FleetSettings:
    """Units in the comments; the reasoning is in ``config/fleet.yaml``."""

    trend_rate: float = 0.01  # [1/day] relative friction rise that is flagged
    trend_significance: float = 0.05  # p-value of the slope below which a rise is real
    trend_min_recordings: int = 3
    fault_free_margin: float = 0.5  # [s]

    def validate(self, source='<settings>'):
        problems = [name for name in ('trend_rate', 'fault_free_margin') if getattr(self, name) < 0]
        if not 0.0 < self.trend_significance < 1.0:
            problems.append('trend_significance')
        if self.trend_min_recordings < 3:
            problems.append('trend_min_recordings')
        if problems:
            msg = f'{source}: out of range: {problems}'
            raise ConfigError(msg)
