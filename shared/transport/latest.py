"""The newest *valid* message of a key: a latest-only slot that checks each sample as it arrives.

A plain ring of one (zenoh.handlers.RingChannel(1)) lets a malformed sample displace the good frame
that was waiting, and drops bad samples uncounted while the consumer is busy. Here each sample is
decoded on Zenoh's thread as it arrives (header work: arrays stay zero-copy views of the payload), a
bad one is rejected and counted by the service's InputGuard and never touches the slot, and the
consumer takes the newest good message. Decoding is the only work done on Zenoh's thread.
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from typing import Generic, Protocol, TypeVar

import zenoh

T = TypeVar("T")


class Rejecter(Protocol):
    """Counts and logs one rejected input (shared.runtime.guard.InputGuard is one)."""

    def reject(self, what: str, payload_bytes: int, exc: BaseException) -> None: ...


class LatestValid(Generic[T]):
    """Keeps the newest message that `check(payload)` accepted; `take` waits for one."""

    def __init__(self, check: Callable[[bytes], T], guard: Rejecter, what: str) -> None:
        self._check = check
        self._guard = guard
        self._what = what
        self._cond = threading.Condition()
        self._item: T | None = None
        self.received = 0
        self.replaced = 0  # good messages displaced by a newer good one before the consumer took them

    def offer(self, payload: bytes) -> bool:
        """Check one payload; keep it if good (True), count and log it if not (False)."""
        try:
            item = self._check(payload)
        except Exception as exc:  # any bad input: counted by reason, never raised on Zenoh's thread
            self._guard.reject(self._what, len(payload), exc)
            return False
        with self._cond:
            self.received += 1
            if self._item is not None:
                self.replaced += 1
            self._item = item
            self._cond.notify()
        return True

    def on_sample(self, sample: zenoh.Sample) -> None:
        """Zenoh subscriber callback."""
        self.offer(sample.payload.to_bytes())

    def take(
        self, stop: threading.Event, *, poll_secs: float = 0.05, wake: Callable[[], bool] | None = None
    ) -> T | None:
        """The newest good message (removed from the slot), or None once `stop` is set or `wake()` says
        the consumer has other work (checked every poll_secs)."""
        with self._cond:
            while self._item is None:
                if stop.is_set() or (wake is not None and wake()):
                    return None
                self._cond.wait(poll_secs)
            item, self._item = self._item, None
            return item


def declare_latest_valid(session: zenoh.Session, key: str, slot: LatestValid[T]) -> zenoh.Subscriber[None]:
    """Subscribe `slot` to `key` (its callback runs on Zenoh's threads)."""
    return session.declare_subscriber(key, slot.on_sample)
