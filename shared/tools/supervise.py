"""The launcher's restart policy (pure): a service that dies is restarted after a backoff that doubles
with each quick death and resets once it has stayed up; only a person's stop, or a camera whose
source ended (exit code 0, `loop = false`), ends a deployment."""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field


@dataclass(frozen=True)
class RestartPolicy:
    """Backoff bounds, seconds."""

    initial_backoff_secs: float = 1.0
    max_backoff_secs: float = 30.0
    healthy_after_secs: float = 60.0  # up this long: the next death starts the backoff over


@dataclass
class Supervisor:
    """Decides, for each service exit, whether and when to restart it."""

    policy: RestartPolicy = field(default_factory=RestartPolicy)
    clock: Callable[[], float] = time.monotonic
    restarts: dict[str, int] = field(default_factory=dict)
    _started_at: dict[str, float] = field(default_factory=dict)
    _backoff: dict[str, float] = field(default_factory=dict)

    def started(self, name: str) -> None:
        """A service (re)started now."""
        self._started_at[name] = self.clock()

    def exited(self, name: str, code: int | None, *, service: str | None = None) -> float | None:
        """Seconds to wait before restarting `name` (a process of kind `service`: by default its name),
        or None when its exit ends the deployment."""
        if (service or name) == "camera" and code == 0:
            return None  # the source ended (a file without loop, max_frames): the run is complete
        up_secs = self.clock() - self._started_at.get(name, self.clock())
        if up_secs >= self.policy.healthy_after_secs or name not in self._backoff:
            backoff = self.policy.initial_backoff_secs
        else:
            backoff = min(2 * self._backoff[name], self.policy.max_backoff_secs)
        self._backoff[name] = backoff
        self.restarts[name] = self.restarts.get(name, 0) + 1
        return backoff
