"""A packet-level simulation of the robot -> edge uplink with the pipeline's flow control, for the
link estimator's tests. Written independently of `shared.control.linkmodel`: messages are cut into MTU-sized
packets that cross a FIFO delay line with per-packet jitter and then a token-bucket rate limiter (the
emulated link's order), the robot keeps up to `window` frames in flight and takes the newest camera
frame when a credit returns, the edge serves frames one at a time, and probes share the same link.
The edge stamps every arrival; each message yields (payload bytes, sent ms, received ms, previous
received ms), the evidence the controller gets from TagPoses and probe acks.
"""

from __future__ import annotations

import heapq
import itertools
from dataclasses import dataclass, field

import numpy as np

MTU_BYTES = 1448


@dataclass(frozen=True)
class Crossing:
    """One message on the uplink as the edge saw it (edge clock = true time + clock_offset_ms)."""

    payload_bytes: int
    sent_ms: float
    received_ms: float
    previous_received_ms: float | None
    kind: str  # "frame" or "probe"


@dataclass
class UplinkSim:
    """Delay line (floor + jitter, order kept) followed by a token bucket of one packet's burst."""

    floor_ms: float
    rate_bytes_per_ms: float
    jitter_ms: float = 1.0
    rng: np.random.Generator = field(default_factory=lambda: np.random.default_rng(0))
    _delay_out_ms: float = 0.0
    _bucket_free_ms: float = 0.0

    def send(self, now_ms: float, payload_bytes: int) -> float:
        """Push a message whose bytes all leave the sender at now_ms; return when its last byte arrives."""
        arrival = now_ms
        for size in [MTU_BYTES] * (payload_bytes // MTU_BYTES) + [payload_bytes % MTU_BYTES or 0]:
            if size == 0:
                continue
            out = max(self._delay_out_ms, now_ms + self.floor_ms + self.rng.uniform(0, self.jitter_ms))
            self._delay_out_ms = out
            self._bucket_free_ms = max(self._bucket_free_ms, out) + size / self.rate_bytes_per_ms
            arrival = self._bucket_free_ms
        return arrival


def simulate(
    *,
    floor_ms: float,
    beta_ms_per_kB: float,
    window: int,
    frame_bytes: list[int],
    fps: float = 10.0,
    robot_ms: float = 15.0,
    edge_ms: float = 30.0,
    downlink_ms: float = 0.5,
    probe_every_ms: float | None = 250.0,
    probe_bytes: tuple[int, ...] = (16 * 1024, 64 * 1024),
    duration_ms: float = 20_000.0,
    clock_offset_ms: float = 0.0,
    seed: int = 0,
) -> list[Crossing]:
    """Run the pipeline for duration_ms; frame n carries frame_bytes[n % len(frame_bytes)] bytes."""
    rng = np.random.default_rng(seed)
    link = UplinkSim(floor_ms, 1024.0 / beta_ms_per_kB, rng=rng)
    events: list[tuple[float, int, str, int]] = []
    order = itertools.count()

    def at(t: float, what: str, arg: int = 0) -> None:
        heapq.heappush(events, (t, next(order), what, arg))

    sent: dict[int, tuple[float, int, str]] = {}  # message id -> (sent ms, bytes, kind)
    out: list[Crossing] = []
    ids = itertools.count()
    in_flight = 0
    robot_busy = False
    newest_frame: int | None = None
    edge_free_ms = 0.0
    last_arrival: float | None = None
    frames_sent = 0

    def robot_try(now: float) -> None:
        nonlocal robot_busy, newest_frame
        if robot_busy or newest_frame is None or in_flight >= window:
            return
        robot_busy, newest_frame = True, None
        at(now + robot_ms * rng.uniform(0.9, 1.1), "robot_done")

    def transmit(now: float, size: int, kind: str) -> None:
        mid = next(ids)
        sent[mid] = (now, size, kind)
        at(link.send(now, size), "arrive", mid)

    for i in range(int(duration_ms * fps / 1e3)):
        at(i * 1e3 / fps, "camera", i)
    if probe_every_ms:
        for j in range(int(duration_ms / probe_every_ms)):
            at(j * probe_every_ms + 7.0, "probe", probe_bytes[j % len(probe_bytes)])
    while events:
        now, _, what, arg = heapq.heappop(events)
        if what == "camera":
            newest_frame = arg
            robot_try(now)
        elif what == "robot_done":
            robot_busy = False
            in_flight += 1
            transmit(now, frame_bytes[frames_sent % len(frame_bytes)], "frame")
            frames_sent += 1
            robot_try(now)
        elif what == "probe":
            transmit(now, arg, "probe")
        elif what == "arrive":
            t_sent, size, kind = sent.pop(arg)
            stamp = now + clock_offset_ms
            out.append(Crossing(size, t_sent, stamp, last_arrival, kind))
            last_arrival = stamp
            if kind == "frame":
                edge_free_ms = max(edge_free_ms, now) + edge_ms * rng.uniform(0.9, 1.1)
                at(edge_free_ms + downlink_ms, "credit")
        elif what == "credit":
            in_flight -= 1
            robot_try(now)
    return out


def late_stamps(crossings: list[Crossing], *, fraction: float, mean_ms: float, seed: int = 0) -> list[Crossing]:
    """The receiver under CPU load: every stamp is late by an exponential 0.3 ms, and `fraction` of them
    by an exponential `mean_ms` more (the scheduler ran something else first). A process stamps in
    order, so a stamp is never before the one ahead of it; each message's previous stamp follows."""
    rng = np.random.default_rng(seed)
    out: list[Crossing] = []
    previous: float | None = None
    for c in crossings:
        late = rng.exponential(0.3) + (rng.exponential(mean_ms) if rng.random() < fraction else 0.0)
        stamp = c.received_ms + late if previous is None else max(c.received_ms + late, previous + 0.02)
        out.append(Crossing(c.payload_bytes, c.sent_ms, stamp, previous, c.kind))
        previous = stamp
    return out
