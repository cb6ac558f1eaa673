"""The newest *valid* message of a key: a latest-only slot that checks each sample as it arrives.

A plain ring of one (zenoh.handlers.RingChannel(1)) lets a malformed sample displace the good frame
that was waiting, and drops bad samples uncounted while the consumer is busy. Here each sample is
decoded on Zenoh's thread as it arrives (header work: arrays stay zero-copy views of the payload), a
bad one is rejected and counted by the service's InputGuard and never touches the slot, and the
consumer takes the newest good message. Decoding is the only work done on Zenoh's thread.
"""

from __future__ import annotations

import statistics
import threading
import time
from collections import deque
from collections.abc import Callable
from typing import Generic, Protocol, TypeVar

import zenoh

T = TypeVar("T")


class Rejecter(Protocol):
    """Counts and logs one rejected input (shared.runtime.guard.InputGuard is one)."""

    def reject(self, what: str, payload_bytes: int, exc: BaseException) -> None: ...


def fresh_wait_secs(*, age_secs: float, interval_secs: float | None, fraction: float) -> float:
    """How long a consumer about to take a message `age_secs` old should wait for the next one instead,
    when messages come every `interval_secs` (None: not known yet): the time until the next is due when
    that is within `fraction` of the interval, else 0 (take this one now).

    Waiting w for a message that is then fresh trades w of the consumer's time for the age it would
    have carried (interval - w): worth it when w is the smaller part. With the wait allowed for the
    last `fraction` f of each interval, a consumer that takes messages at random phases waits f^2/2 of
    an interval on average, and the median age drops from 1/2 of one to 1/2 - f (f <= 1/2; f = 1/3:
    1/6; f = 1/2: none)."""
    if fraction <= 0 or interval_secs is None or interval_secs <= 0:
        return 0.0
    due = interval_secs - age_secs
    return due if 0 < due <= fraction * interval_secs else 0.0


class LatestValid(Generic[T]):
    """Keeps the newest message that `check(payload)` accepted; `take` waits for one (and, with
    `fresh_fraction`, for the next one when it is due so soon that waiting beats taking an aged one)."""

    def __init__(
        self,
        check: Callable[[bytes], T],
        guard: Rejecter,
        what: str,
        *,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self._check = check
        self._guard = guard
        self._what = what
        self._clock = clock
        self._cond = threading.Condition()
        self._item: T | None = None
        self._arrived = 0.0  # when the newest good message came (clock)
        self._gaps: deque[float] = deque(maxlen=15)  # seconds between the last good messages
        self.received = 0
        self.replaced = 0  # good messages displaced by a newer good one before the consumer took them
        self.fresh_waits = 0  # takes that waited for the next message (fresh_fraction)
        self.fresh_wait_secs = 0.0  # their total wait

    def offer(self, payload: bytes) -> bool:
        """Check one payload; keep it if good (True), count and log it if not (False)."""
        try:
            item = self._check(payload)
        except Exception as exc:  # any bad input: counted by reason, never raised on Zenoh's thread
            self._guard.reject(self._what, len(payload), exc)
            return False
        with self._cond:
            now = self._clock()
            if self.received:
                self._gaps.append(now - self._arrived)
            self._arrived = now
            self.received += 1
            if self._item is not None:
                self.replaced += 1
            self._item = item
            self._cond.notify_all()
        return True

    def interval_secs(self) -> float | None:
        """The median of the last gaps between good messages (None before three of them)."""
        with self._cond:
            return statistics.median(self._gaps) if len(self._gaps) >= 2 else None

    def on_sample(self, sample: zenoh.Sample) -> None:
        """Zenoh subscriber callback."""
        self.offer(sample.payload.to_bytes())

    def take(
        self,
        stop: threading.Event,
        *,
        poll_secs: float = 0.05,
        wake: Callable[[], bool] | None = None,
        fresh_fraction: float = 0.0,
    ) -> T | None:
        """The newest good message (removed from the slot), or None once `stop` is set or `wake()` says
        the consumer has other work (checked every poll_secs). With `fresh_fraction` > 0, when the next
        message is due within that fraction of the interval between messages (`fresh_wait_secs`), wait
        for it first, at most until half that fraction of an interval after it was due (a late or
        missing one: the waiting one is taken)."""
        with self._cond:
            if self._item is not None and fresh_fraction > 0:
                interval = self.interval_secs()  # the condition's lock is reentrant
                wait = fresh_wait_secs(
                    age_secs=self._clock() - self._arrived, interval_secs=interval, fraction=fresh_fraction
                )
                if wait > 0 and interval is not None:
                    start, received = self._clock(), self.received
                    deadline = start + wait + 0.5 * fresh_fraction * interval
                    while self.received == received and not stop.is_set() and not (wake is not None and wake()):
                        left = deadline - self._clock()
                        if left <= 0:
                            break
                        self._cond.wait(min(poll_secs, left))
                    self.fresh_waits += 1
                    self.fresh_wait_secs += self._clock() - start
            while self._item is None:
                if stop.is_set() or (wake is not None and wake()):
                    return None
                self._cond.wait(poll_secs)
            item, self._item = self._item, None
            return item


def declare_latest_valid(session: zenoh.Session, key: str, slot: LatestValid[T]) -> zenoh.Subscriber[None]:
    """Subscribe `slot` to `key` (its callback runs on Zenoh's threads)."""
    return session.declare_subscriber(key, slot.on_sample)
