"""The launcher's restart policy (pure): a service that dies is restarted after a backoff that doubles
with each quick death and resets once it has stayed up; only a person's stop, or a camera whose
source ended (exit code SOURCE_ENDED_EXIT: `loop = false`, max_frames), ends a deployment. Every exit
and restart is an incident the run keeps (`incidents.jsonl` in the run folder, counted in summary.json),
not only a printed line."""

from __future__ import annotations

import json
import logging
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from shared.runtime.settings import SOURCE_ENDED_EXIT

log = logging.getLogger(__name__)


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
    # Each exit and restart, as it happened (`record` also gets each one: the run's incidents.jsonl).
    incidents: list[dict[str, Any]] = field(default_factory=list)
    record: Callable[[dict[str, Any]], None] | None = None
    wall_clock: Callable[[], int] = time.time_ns
    # What a process's death takes down beside itself (its router's clients), said when it dies.
    hosts: dict[str, str] = field(default_factory=dict)
    _started_at: dict[str, float] = field(default_factory=dict)
    _backoff: dict[str, float] = field(default_factory=dict)
    _down_since: dict[str, float] = field(default_factory=dict)  # exited, not ready again yet
    _ready_at: dict[str, float] = field(default_factory=dict)  # back after an exit: when
    ended: set[str] = field(default_factory=set)  # cameras whose source ended (said once, never restarted)

    def started(self, name: str, *, pid: int | None = None) -> None:
        """A service (re)started now (a restart is an incident: `pid` is its new process)."""
        self._started_at[name] = self.clock()
        if self.restarts.get(name):
            self._note({"event": "restarted", "name": name, "restart": self.restarts[name], "pid": pid})

    def ready(self, name: str) -> float | None:
        """`name`'s liveliness token is back: seconds since it exited (an incident), or None when it
        had not exited (its first start, or a token that came and went with the network)."""
        since = self._down_since.pop(name, None)
        if since is None:
            return None
        down_secs = round(self.clock() - since, 1)
        self._ready_at[name] = self.clock()
        self._note({"event": "ready", "name": name, "down_secs": down_secs})
        return down_secs

    def handover(self, worker: str, *, up: bool, moved: dict[str, str | None]) -> None:
        """A fleet's edge worker came or went and robots moved (`moved`: robot -> its new worker, None:
        computed on board): an incident, so the run's record keeps it (a fleet trial found hand-overs
        only in the launcher's live lines)."""
        self._note({"event": "handover", "name": worker, "worker": "up" if up else "gone", "moved": moved})

    def down(self) -> list[str]:
        """The processes that exited and are not ready again (restarting), by name."""
        return sorted(self._down_since)

    def back(self, within_secs: float) -> dict[str, float]:
        """The processes that came back from an exit in the last `within_secs`: name -> when (this
        supervisor's clock, time.monotonic by default)."""
        now = self.clock()
        return {n: t for n, t in sorted(self._ready_at.items()) if now - t <= within_secs and n not in self._down_since}

    def _note(self, incident: dict[str, Any]) -> None:
        incident = {"unix_nanos": self.wall_clock(), **incident}
        self.incidents.append(incident)
        if self.record is not None:
            self.record(incident)

    def exit_line(self, name: str, code: int | None, delay_secs: float, *, why: str | None = None) -> str:
        """What the launcher prints when `name` died (after `exited`); `why`: what its log said last."""
        hosted = f" ({self.hosts[name]})" if name in self.hosts else ""
        said = f": {why}" if why else ""
        return f"{name} exited ({code}){said}{hosted}; restart #{self.restarts.get(name, 0)} in {delay_secs:.0f} s"

    def summary(self) -> dict[str, Any]:
        """For summary.json: restarts per process, and how many exits (each in incidents.jsonl)."""
        return summarise_incidents(self.incidents)

    def exited(self, name: str, code: int | None, *, service: str | None = None) -> float | None:
        """Seconds to wait before restarting `name` (a process of kind `service`: by default its name),
        or None when its exit ends the deployment."""
        if name in self.ended:  # asked again about a camera whose source ended: already said
            return None
        up_secs = self.clock() - self._started_at.get(name, self.clock())
        said = {"event": "exited", "name": name, "code": code, "up_secs": round(up_secs, 1)}
        if (service or name) == "camera" and code == SOURCE_ENDED_EXIT:
            self.ended.add(name)
            self._note({**said, "source_ended": True})
            return None  # the source ended (a file without loop, max_frames): the run is complete
        self._down_since.setdefault(name, self.clock())
        if up_secs >= self.policy.healthy_after_secs or name not in self._backoff:
            backoff = self.policy.initial_backoff_secs
        else:
            backoff = min(2 * self._backoff[name], self.policy.max_backoff_secs)
        self._backoff[name] = backoff
        self.restarts[name] = self.restarts.get(name, 0) + 1
        self._note(
            {**said, "restart": self.restarts[name], "restart_in_secs": backoff, "takes_down": self.hosts.get(name)}
        )
        return backoff


def summarise_incidents(incidents: list[dict[str, Any]]) -> dict[str, Any]:
    """Restarts per process and how many exits, from the incidents (a live supervisor's, or a run's
    incidents.jsonl read back)."""
    exits = [i for i in incidents if i.get("event") == "exited"]
    restarts: dict[str, int] = {}
    for i in exits:
        if "restart" in i:
            restarts[str(i.get("name"))] = restarts.get(str(i.get("name")), 0) + 1
    out: dict[str, Any] = {"restarts": restarts, "exits": len(exits)}
    if handovers := [i for i in incidents if i.get("event") == "handover"]:
        out["handovers"] = len(handovers)
    return out


def read_incidents(path: Path) -> list[dict[str, Any]]:
    """A run's incidents.jsonl (a line that is not a JSON object, e.g. cut short by a crash, is skipped)."""
    out = []
    for line in path.read_text().splitlines():
        try:
            incident = json.loads(line)
        except ValueError:
            continue
        if isinstance(incident, dict):
            out.append(incident)
    return out


def incidents_file(path: Path) -> Callable[[dict[str, Any]], None]:
    """A `Supervisor.record` appending each incident to `path` as a JSON line, as it happens (a launcher
    that dies leaves the incidents until then). A write that fails (disk full, the folder gone) is said
    once and the run goes on: the record is a side file, not a reason to stop the robots."""
    failed: list[dict[str, Any]] = []

    def append(incident: dict[str, Any]) -> None:
        try:
            with path.open("a") as f:
                f.write(json.dumps(incident) + "\n")
        except OSError as exc:
            if not failed:
                log.warning("cannot record incidents in %s (%s): the run goes on without them", path, exc)
            failed.append(incident)

    return append
