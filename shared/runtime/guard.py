"""One guarded place per service for its inputs: whatever handling one message raises (bad bytes, a
geometry the maths cannot take, a state the core refuses) is counted by reason, logged at most once
per interval with the text truncated, and the service goes on with the next message. The counts are
served on `splittag/<robot_id>/<service>/stats` (JSON), so a test or an operator can see them."""

from __future__ import annotations

import json
import logging
import os
import threading
import time
from collections import Counter
from collections.abc import Callable
from pathlib import Path
from typing import Any, TypeVar

import zenoh

from shared.transport.query import get_until_answered
from shared.vision.files import atomic_write_text
from shared.wire import keys

T = TypeVar("T")
log = logging.getLogger(__name__)


def _daemon_timer(delay_secs: float, call: Callable[[], None]) -> None:
    timer = threading.Timer(delay_secs, call)
    timer.daemon = True
    timer.start()


class InputGuard:
    """Counts accepted and rejected inputs of one service; thread-safe (Zenoh callbacks use it too).

    Rejections are logged one line per `log_every_secs`; those in between are summed up, by reason, in
    a line once the interval has passed (`schedule` runs `flush` then) and at shutdown (`flush`): a trial's
    burst of 10 bad frames showed as "rejected frame #1" and nothing more."""

    def __init__(
        self,
        service: str,
        *,
        log_every_secs: float = 1.0,
        max_chars: int = 300,
        clock: Callable[[], float] = time.monotonic,
        schedule: Callable[[float, Callable[[], None]], None] = _daemon_timer,
    ) -> None:
        self.service = service
        self.log_every_secs = log_every_secs
        self.max_chars = max_chars
        self._clock = clock
        self._schedule = schedule
        self._pending: Counter[str] = Counter()  # rejected since the last line and not logged, by reason
        self._flush_due = False
        self._persist_path: Path | None = None
        self._write_failing = False  # the last write of the counts failed: tried again every period
        self._label: str | None = None
        self._persist_stop: threading.Event | None = None
        self._persist_thread: threading.Thread | None = None
        self._write_lock = threading.Lock()
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
            flush_in: float | None = None
            logged = now - self._last_log >= self.log_every_secs
            if logged:
                skipped, self._unlogged, self._last_log = self._unlogged, 0, now
                self._pending.clear()
            else:
                self._unlogged += 1
                self._pending[reason] += 1
                if not self._flush_due:  # the interval's tail is said when it ends
                    self._flush_due = True
                    flush_in = max(self._last_log + self.log_every_secs - now, 0.0)
        if flush_in is not None:
            self._schedule(flush_in, self.flush)
        if not logged:
            return
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

    def flush(self) -> None:
        """Log, in one line, the rejections since the last line that were not logged one by one (by
        reason, with the newest text); nothing when there are none. At shutdown, and `schedule`d."""
        with self._lock:
            self._flush_due = False
            if not self._unlogged:
                return
            count, pending = self._unlogged, dict(self._pending)
            self._unlogged, self._last_log = 0, self._clock()
            self._pending.clear()
            total = sum(self.rejected.values())
            newest = {reason: self.last_rejected[reason] for reason in pending}
        by_reason = ", ".join(f"{reason} x{n}" for reason, n in pending.items())
        log.warning(
            "%s rejected %d more inputs not logged one by one (%d in all): %s; the newest of each: %s",
            self.service,
            count,
            total,
            by_reason,
            "; ".join(f"{reason}: {text}" for reason, text in newest.items()),
        )

    def persist(self, path: Path, *, label: str | None = None, every_secs: float = 2.0) -> None:
        """Keep this process's counts in `path` (JSON, replaced whole): now, every `every_secs` while they
        change, and at `close`. The launcher's summary adds up every process's file per service (and
        `label`: a fleet's robot or edge worker), so the counts of a process that was killed and
        restarted are not lost (a trial: the end-of-run lines said 0 rejected after the restarts, of 19
        and 10 refused). Nothing without a run folder (`path`'s grandparent)."""
        if not path.parent.parent.is_dir():
            return
        self._persist_path, self._label = path, label
        written = self._change_count()
        self._write_counts()
        stop = self._persist_stop = threading.Event()

        def keep() -> None:
            last = written
            while not stop.wait(every_secs):
                if ((now := self._change_count()) != last or self._write_failing) and self._write_counts():
                    last = now

        self._persist_thread = threading.Thread(target=keep, name=f"{self.service}-counts", daemon=True)
        self._persist_thread.start()

    def close(self) -> None:
        """At shutdown: the last interval's rejections said (`flush`), the counts written a last time,
        after the periodic writer has stopped (its older counts never replace these)."""
        self.flush()
        if self._persist_stop is not None and self._persist_thread is not None:
            self._persist_stop.set()
            self._persist_thread.join()
            self._write_counts()

    def _change_count(self) -> int:
        with self._lock:
            return self.accepted + sum(self.rejected.values())

    def _write_counts(self) -> bool:
        """Whether the counts are in the file now. A failed write (a full disk, a folder made read-only)
        is said once and tried again every period until it succeeds, which is said too: the first
        failure used to stop every later write, at exit included (a soak trial's summary said 0 refused)."""
        with self._write_lock:  # (the periodic writer and close share the file and its temporary)
            path = self._persist_path
            if path is None:
                return True
            doc = {**self.stats(), "label": self._label, "pid": os.getpid(), "unix_nanos": time.time_ns()}
            try:
                path.parent.mkdir(exist_ok=True)
                atomic_write_text(path, json.dumps(doc))
            except OSError as exc:  # (the counts stay served on the stats key meanwhile)
                if not self._write_failing:
                    log.warning("%s: cannot write its input counts to %s (trying again): %s", self.service, path, exc)
                self._write_failing = True
                return False
            if self._write_failing:
                log.warning("%s: input counts written to %s again", self.service, path)
            self._write_failing = False
            return True

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
    if len(asked_parts) == len(parts) and not keys.is_wildcard(asked_parts[1]):
        concrete = [a if d == "*" else d for d, a in zip(parts, asked_parts, strict=True)]
        if not keys.is_wildcard("/".join(concrete)):
            return "/".join(concrete)
    return declared


def serve_stats(
    session: zenoh.Session, key: str, guard: InputGuard, extra: Callable[[], dict[str, Any]] | None = None
) -> zenoh.Queryable[None]:
    """A queryable answering the guard's stats (and the service's own counters, `extra`) as JSON."""

    # Replies carry the service's own key, not the asker's: a wildcard get (`splittag/r1/*/stats`) then
    # gets one reply per service instead of one consolidated away (a fleet slam serving `*`: the asker's).
    concrete = not keys.is_wildcard(key)

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


def persist_input_counts(guard: InputGuard, run_dir: Path, *, label: str | None = None) -> None:
    """`guard.persist` into the run folder (`inputs/<service>.<pid>.json`) when the run's launcher started
    this process; a service started by hand keeps its counts to itself (its default run_dir,
    runs/current, may be another run's, whose summary would count them)."""
    from shared.runtime.service_main import started_by_run_launcher

    if started_by_run_launcher(run_dir):
        guard.persist(run_dir / "inputs" / f"{guard.service}.{os.getpid()}.json", label=label)


def input_counts_summary(run_dir: Path) -> dict[str, dict[str, Any]]:
    """Every process's input counts in a run folder added up per service (restarted ones included):
    processes, accepted (in all and by input), rejected (in all and by reason). A service whose
    processes name several labels (a fleet's robots, edge workers) has one entry per label,
    `<service>@<label>`; a file cut short is skipped."""
    docs: list[dict[str, Any]] = []
    for path in sorted((run_dir / "inputs").glob("*.json")):
        try:
            doc = json.loads(path.read_text())
            docs.append(
                {
                    "service": str(doc["service"]),
                    "label": None if doc.get("label") is None else str(doc["label"]),
                    "accepted": int(doc["accepted"]),
                    "accepted_by_input": {str(k): int(v) for k, v in doc["accepted_by_input"].items()},
                    "rejected": int(doc["rejected"]),
                    "rejected_by_reason": {str(k): int(v) for k, v in doc["rejected_by_reason"].items()},
                }
            )
        except (OSError, ValueError, KeyError, TypeError, AttributeError):
            continue
    labels: dict[str, set[str | None]] = {}
    for doc in docs:
        labels.setdefault(doc["service"], set()).add(doc["label"])
    out: dict[str, dict[str, Any]] = {}
    for doc in docs:
        service = doc["service"]
        key = service if len(labels[service]) == 1 else f"{service}@{doc['label']}"
        entry = out.setdefault(
            key, {"processes": 0, "accepted": 0, "accepted_by_input": {}, "rejected": 0, "rejected_by_reason": {}}
        )
        entry["processes"] += 1
        for total in ("accepted", "rejected"):
            entry[total] += doc[total]
        for counts in ("accepted_by_input", "rejected_by_reason"):
            for name, n in doc[counts].items():
                entry[counts][name] = entry[counts].get(name, 0) + n
    return out
