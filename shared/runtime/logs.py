"""Process-wide logging set-up for entry points (services and CLI)."""

from __future__ import annotations

import logging
import os


def setup_logging(name: str) -> logging.Logger:
    """Configure the root logger once (level from SPLITTAG_LOG_LEVEL, default INFO)."""
    level = os.environ.get("SPLITTAG_LOG_LEVEL", "INFO").upper()
    logging.basicConfig(
        level=level,
        format=f"%(asctime)s.%(msecs)03d {name} %(levelname)s %(name)s: %(message)s",
        datefmt="%H:%M:%S",
    )
    return logging.getLogger(name)


class SpellCount:
    """Counts events that come in spells (frames computed on board while the edge is away) and says when
    to log them: at a spell's first event, then at most once every `every_secs` while it goes on, and
    the spell's total when it ends. A count logged only at the 1st and every 100th event read as a total:
    a researcher took "1 frames computed on board" for the run's figure when 17 had been. Pure: the
    caller's clock (monotonic seconds) comes in."""

    def __init__(self, *, every_secs: float = 10.0) -> None:
        if every_secs <= 0:
            raise ValueError(f"every_secs must be > 0, not {every_secs}")
        self.every_secs = every_secs
        self.total = 0  # every event so far
        self.spell = 0  # events in the spell going on (0: none)
        self.since_said = 0  # events of the spell between its last two reports ("running": what it adds)
        self._said_at = 0.0
        self._said_spell = 0

    def add(self, now_secs: float) -> str | None:
        """Count one event at `now_secs`: "first" when it starts a spell, "running" when `every_secs` have
        passed since the spell was last said (`spell` so far, `since_said` of them since then), else None."""
        self.total += 1
        self.spell += 1
        if self.spell == 1:
            self._said_at, self._said_spell = now_secs, 1
            return "first"
        if now_secs - self._said_at >= self.every_secs:
            self.since_said = self.spell - self._said_spell
            self._said_at, self._said_spell = now_secs, self.spell
            return "running"
        return None

    def end(self) -> int:
        """The spell is over: its count (0 when none was going on); the next event starts a new one."""
        spell, self.spell, self._said_spell = self.spell, 0, 0
        return spell
