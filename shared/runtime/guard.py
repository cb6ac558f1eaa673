"""One guarded place per service for its inputs: whatever handling one message raises (bad bytes, a
geometry the maths cannot take, a state the core refuses) is counted by reason, logged at most once
per interval with the text truncated, and the service goes on with the next message. The counts are
served on `splittag/<robot_id>/<service>/stats` (JSON), so a test or an operator can see them."""

from __future__ import annotations

import json
import logging
import threading
import time
from collections import Counter
from collections.abc import Callable
from typing import Any, TypeVar

import zenoh

from shared.transport.query import get_until_answered
from shared.wire import keys

T = TypeVar("T")
log = logging.getLogger(__name__)


class InputGuard:
    """Counts accepted and rejected inputs of one service; thread-safe (Zenoh callbacks use it too)."""

    def __init__(
        self,
        service: str,
        *,
        log_every_secs: float = 1.0,
        max_chars: int = 300,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.service = service
        self.log_every_secs = log_every_secs
        self.max_chars = max_chars
        self._clock = clock
        self._lock = threading.Lock()
        self.accepted = 0
        self.accepted_by_input: Counter[str] = Counter()  # slam takes TagPoses, ground truth, frame stamps...
        self.rejected: Counter[str] = Counter()
        # The newest rejection's text per reason, on the stats key: a sender on another host sees why
        # without the service's log (the log says one line a second; a trial's never showed its error).
        self.last_rejected: dict[str, str] = {}
        self._last_log = -float("inf")
        self._unlogged = 0

    def run(self, what: str, payload_bytes: int, handle: Callable[[], T]) -> T | None:
        """handle() for one `what` message; None (after counting and maybe logging) if it raised."""
        try:
            result = handle()
        except Exception as exc:  # the guard's point: no input may take the service down
            self.reject(what, payload_bytes, exc)
            return None
        with self._lock:
            self.accepted += 1
            self.accepted_by_input[what] += 1
        return result

    def reject(self, what: str, payload_bytes: int, exc: BaseException) -> None:
        """Count one rejected input; log it unless a line was logged less than log_every_secs ago."""
        reason = f"{what}: {type(exc).__name__}"
        now = self._clock()
        text = str(exc).replace("\n", " ")
        if len(text) > self.max_chars:
            text = text[: self.max_chars] + f"... ({len(text)} chars)"
        with self._lock:
            self.rejected[reason] += 1
            self.last_rejected[reason] = f"{text} ({payload_bytes} bytes)"
            total = sum(self.rejected.values())
            if now - self._last_log < self.log_every_secs:
                self._unlogged += 1
                return
            skipped, self._unlogged, self._last_log = self._unlogged, 0, now
        more = f" (+{skipped} not logged)" if skipped else ""
        log.warning(
            "%s rejected %s #%d (%d bytes): %s: %s%s",
            self.service,
            what,
            total,
            payload_bytes,
            type(exc).__name__,
            text,
            more,
        )

    def stats(self) -> dict[str, Any]:
        """accepted (in all and by input), rejected, rejected by reason and the newest rejection's text by
        reason."""
        with self._lock:
            return {
                "service": self.service,
                "accepted": self.accepted,
                "accepted_by_input": dict(self.accepted_by_input),
                "rejected": sum(self.rejected.values()),
                "rejected_by_reason": dict(self.rejected),
                "last_rejected": dict(self.last_rejected),
            }


def _one_robots(declared: str, asked: str) -> str:
    """The reply key of a queryable declared for every robot (`splittag/*/slam/stats`): the asked
    robot's own key when the query names one robot, else the declared key (it intersects the query,
    which reached it, and is the key access control lets this service reply on)."""
    parts, asked_parts = declared.split("/"), asked.split("/")
    if len(asked_parts) == len(parts) and not any(c in asked_parts[1] for c in "*$"):
        concrete = [a if d == "*" else d for d, a in zip(parts, asked_parts, strict=True)]
        if not any(c in "/".join(concrete) for c in "*$"):
            return "/".join(concrete)
    return declared


def serve_stats(
    session: zenoh.Session, key: str, guard: InputGuard, extra: Callable[[], dict[str, Any]] | None = None
) -> zenoh.Queryable[None]:
    """A queryable answering the guard's stats (and the service's own counters, `extra`) as JSON."""

    # Replies carry the service's own key, not the asker's: a wildcard get (`splittag/r1/*/stats`) then
    # gets one reply per service instead of one consolidated away (a fleet slam serving `*`: the asker's).
    concrete = not any(c in key for c in "*$")

    def on_query(query: zenoh.Query) -> None:
        body = {**guard.stats(), **(extra() if extra is not None else {})}
        reply_key = key if concrete else _one_robots(key, str(query.key_expr))
        query.reply(reply_key, json.dumps(body).encode(), encoding=zenoh.Encoding.APPLICATION_JSON)

    return session.declare_queryable(key, on_query)


def service_stats(session: zenoh.Session, robot_id: str, service: str, *, timeout_secs: float = 5.0) -> dict[str, Any]:
    """Ask a running service for its input counters (see serve_stats)."""
    for reply in get_until_answered(session, keys.stats(robot_id, service), timeout_secs):
        if reply.ok is not None:
            parsed: dict[str, Any] = json.loads(reply.ok.payload.to_bytes())
            return parsed
    raise TimeoutError(f"no stats from {service} of {robot_id} within {timeout_secs} s")
