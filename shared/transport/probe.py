"""Link probing: an echo queryable on the edge and a client that times round trips.

A probe is a real `Features` message of the requested size (one tag whose fp16 tensor fills the
payload), so its cost includes the codec; the echo decodes and validates it and replies with a
tiny `ProbeAck`, so only the uplink carries the payload, as in the paper's measurement.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from typing import NamedTuple

import zenoh

from shared.transport.session import encoding_for
from shared.wire import keys
from shared.wire.codec import WireError
from shared.wire.messages import (
    WRITE_FRAMING,
    Features,
    LinkStamps,
    ProbeAck,
    View,
    decode_view,
    encode,
    encode_values,
    framing_of,
)

log = logging.getLogger(__name__)


def serve_echo(
    session: zenoh.Session,
    key: str,
    *,
    max_bytes: int,
    arrivals: ArrivalClock | None = None,
    refused: Callable[[str, int, BaseException], None] | None = None,
) -> zenoh.Queryable[None]:
    """Declare the echo queryable: decode each probe, reply a ProbeAck with the probe's link stamps
    (errors are replied, not raised). `arrivals` is shared with whatever else arrives on the same
    uplink (edge_infer's Features), so a probe's stamps say what was ahead of it. A probe that does not
    decode goes to `refused` (a service's InputGuard.reject: counted, logged at most once a second; a
    trial's 2,000 garbage probes in 1.3 s were 2,000 warnings, counted nowhere), else is logged."""
    enc = encoding_for(ProbeAck.SCHEMA)
    arrivals = arrivals or ArrivalClock()

    def on_query(query: zenoh.Query) -> None:
        if query.payload is None and keys.is_wildcard(str(query.key_expr)):
            # A key discovery (`get splittag/**`), not a probe: no reply, nothing counted (an integrator's
            # read was answered as a refused probe and showed in edge_infer's refusal counters).
            query.drop()
            return
        received, previous = arrivals.stamp()
        payload = query.payload.to_bytes() if query.payload is not None else b""
        error = ""
        link = None
        try:
            # Every check the edge makes of Features, without assembling the model: the echo reads one field.
            link = (decode_view(payload, Features, max_bytes=max_bytes).fields.publish_nanos, received, previous)
        except WireError as exc:
            error = str(exc)
            if refused is not None:
                refused("probe", len(payload), exc)
            else:
                log.warning("echo: rejected probe of %d bytes: %s", len(payload), exc)
        framing = framing_of(payload)  # the asker's
        if framing == WRITE_FRAMING:  # checked as the asker will parse it, no model built for it
            out = encode_values(ProbeAck, len(payload), not error, error, link)
        else:
            stamps = None
            if link is not None:
                stamps = LinkStamps(sent_nanos=link[0], received_nanos=link[1], previous_received_nanos=link[2])
            ack = ProbeAck(received_bytes=len(payload), decoded_ok=not error, error=error, link=stamps)
            out = encode(ack, framing=framing)
        query.reply(key, out, encoding=enc)  # this echo's own key

    return session.declare_queryable(key, on_query)


class ArrivalClock:
    """Receiver side of one link: stamps each arriving message and returns the previous arrival, so
    every message can say what was ahead of it (thread-safe: subscribers and queryables stamp on
    Zenoh's threads). Stamp where the bytes arrive, before any queue of the receiver's own."""

    def __init__(self, clock: Callable[[], int] = time.time_ns) -> None:
        self._clock = clock
        self._last = 0
        self._lock = threading.Lock()

    def stamp(self) -> tuple[int, int]:
        """(received_nanos, previous_received_nanos); the previous is 0 for the first message."""
        with self._lock:
            now = self._clock()
            previous, self._last = self._last, max(self._last, now)
            return now, previous


class ProbeError(RuntimeError):
    """A probe got no reply, an error reply, or an ack saying the payload was rejected."""


class ProbeResult(NamedTuple):
    """One timed round trip (a named tuple: made on every probe's critical path, at a fifth of a
    frozen dataclass's cost)."""

    payload_bytes: int
    rtt_secs: float
    ack: View[ProbeAck]

    @property
    def link(self) -> LinkStamps | None:
        """The probe's one-way stamps (None from an echo that predates them)."""
        return self.ack.model().link


class Prober:
    """Sends probes through one Zenoh querier and times each round trip on one clock."""

    def __init__(self, session: zenoh.Session, key: str, *, timeout_secs: float = 10.0) -> None:
        self._querier = session.declare_querier(
            key,
            timeout=timeout_secs,
            congestion_control=zenoh.CongestionControl.BLOCK,
            target=zenoh.QueryTarget.ALL,
        )
        self._enc = encoding_for(Features.SCHEMA)

    def round_trip(self, payload: bytes) -> ProbeResult:
        """Send `payload` (wire bytes of a Features message) and wait for the echo's ack."""
        start = time.perf_counter()
        replies = self._querier.get(payload=payload, encoding=self._enc)
        view: View[ProbeAck] | None = None
        for reply in replies:
            if reply.ok is None:
                err = reply.err.payload.to_string() if reply.err is not None else "?"
                raise ProbeError(f"echo replied an error: {err}")
            view = decode_view(reply.ok.payload.to_bytes(), ProbeAck)
            break
        rtt = time.perf_counter() - start
        if view is None:
            raise ProbeError("no reply from the echo queryable (is the edge running?)")
        ack = view.fields
        if not ack.decoded_ok or ack.received_bytes != len(payload):
            raise ProbeError(f"echo rejected the probe: {ack.error or ack.received_bytes}")
        return ProbeResult(payload_bytes=len(payload), rtt_secs=rtt, ack=view)

    def close(self) -> None:
        """Undeclare the querier."""
        self._querier.undeclare()
