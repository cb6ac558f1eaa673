"""Credit-based flow control between robot_infer and edge_infer.

robot_infer may have at most `capacity` frames in flight (sent, no TagPoses back yet). When the edge
(or the link) is the bottleneck, the robot waits for a credit before it takes the next frame from its
latest-only ring, so it always sends the freshest frame and no backlog can build up in transport
buffers: latency stays bounded by about `capacity` edge service times instead of growing without
limit. A frame whose TagPoses never come back (edge restarted, message rejected) expires after
`timeout_secs` and its credit returns. A frame sent with `keep=` holds that object (robot_infer: its
Features) until the answer comes; when the edge is known to be gone (`clear(recover=True)`), the
frames it held become orphans the robot computes itself (`take_orphans`), so a dying edge costs no
frame. Within the window, `EdgePacer` times when the robot starts
each frame so that it reaches the edge just as the edge becomes free (no queueing at the edge)
and, given a link model, reaches the uplink just as the frame ahead has crossed it (no queueing on
the link: on the emulated 5G uplink a split tensor takes longer to cross than the robot takes to make
the next one).
"""

from __future__ import annotations

import itertools
import math
import statistics
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import Final, Generic, TypeVar

from shared.wire.messages import LinkStamps

T = TypeVar("T")


MAX_ANSWER_SECS: Final[float] = 10.0  # the most an answer may say its link, edge or wait took (bounded)


class InFlightWindow(Generic[T]):
    """Thread-safe set of in-flight frames with a capacity, per-entry expiry and, optionally, what each
    frame needs to be recomputed if its answer can no longer come. A frame's key (`seq` below) must be
    unique and increase in send order: robot_infer uses the capture time, since the camera's seq starts
    again with every camera session (a restart, a looped folder's next pass)."""

    def __init__(self, capacity: int, *, timeout_secs: float = 2.0, clock: Callable[[], float] = time.monotonic):
        if capacity < 0:
            raise ValueError("capacity must be >= 0 (0 disables the window)")
        if timeout_secs <= 0:
            raise ValueError("timeout_secs must be > 0")
        self.capacity = capacity
        self.timeout_secs = timeout_secs
        self._clock = clock
        self._sent: dict[int, float] = {}
        self._kept: dict[int, T] = {}
        self._orphans: list[tuple[int, T]] = []  # (seq, what it was sent with)
        self._cond = threading.Condition()
        self.expired = 0
        self._answers: deque[float] = deque(maxlen=20)  # the last answers' times in flight, put -> answer

    def _expire(self) -> None:
        now = self._clock()
        stale = [s for s, t in self._sent.items() if now - t > self.timeout_secs]
        for s in stale:
            del self._sent[s]
            self._kept.pop(s, None)  # unanswered by a live edge (e.g. it refused it): not recomputed
        self.expired += len(stale)

    def _drop_all(self, *, recover: bool) -> None:
        if recover:
            self._orphans.extend((s, self._kept[s]) for s in sorted(self._kept))
        self._sent.clear()
        self._kept.clear()

    def acquire(
        self,
        stop: threading.Event,
        *,
        poll_secs: float = 0.05,
        abandon: Callable[[], bool] | None = None,
        recover: Callable[[], bool] | None = None,
    ) -> bool:
        """Wait for a credit; False once `stop` is set. Expiry is re-checked every poll_secs; when
        `abandon()` says the answers will not come, the frames in flight are forgotten and the credit
        is there at once; they become orphans when `recover()` says so (the edge's token is gone: its
        loss may not have reached `clear(recover=True)` yet), else they are dropped (an answer merely
        overdue)."""
        if self.capacity == 0:
            return not stop.is_set()
        with self._cond:
            while not stop.is_set():
                self._expire()
                if len(self._sent) < self.capacity:
                    return True
                if abandon is not None and abandon():
                    self._drop_all(recover=recover is not None and recover())
                    return True
                self._cond.wait(poll_secs)
        return False

    def oldest_age_secs(self) -> float:
        """How long the oldest unanswered frame has waited (0 when none)."""
        with self._cond:
            return self._clock() - min(self._sent.values()) if self._sent else 0.0

    def clear(self, *, recover: bool = False) -> None:
        """Forget every frame in flight (their answers will not come). `recover`: the edge is gone for
        sure, so what the frames were sent with becomes orphans (`take_orphans`); without it (an answer
        merely overdue, which may still come) they are dropped."""
        with self._cond:
            self._drop_all(recover=recover)
            self._cond.notify_all()

    def take_orphans(self) -> list[T]:
        """What the frames a vanished edge held were sent with, oldest first (emptied)."""
        with self._cond:
            orphans, self._orphans = self._orphans, []
            return [kept for _, kept in orphans]

    @property
    def has_orphans(self) -> bool:
        """Frames wait to be recomputed."""
        with self._cond:
            return bool(self._orphans)

    def sent(self, seq: int, *, keep: T | None = None) -> None:
        """Record that frame `seq` left the robot (with what it would take to recompute it)."""
        if self.capacity == 0:
            return
        with self._cond:
            self._sent[seq] = self._clock()
            if keep is not None:
                self._kept[seq] = keep

    def send(
        self, seq: int, put: Callable[[], None], *, keep: T | None = None, gone: Callable[[], bool] | None = None
    ) -> None:
        """Take frame seq's credit, then put it on the wire. In this order: the answer can arrive (and
        return the credit) before `put` returns; recorded after, it would find nothing to return and the
        credit would be held until it expires. A `put` that raises returns the credit.

        `gone()`: whether the edge's token is gone now. The edge can vanish while the frame is being
        made: its token's loss turned the frames in flight then into orphans, but not this one, sent
        after. Checked once the frame is recorded, so either that check or the loss's own
        `clear(recover=True)` (whichever comes later) makes it an orphan: no frame is lost to the race."""
        self.sent(seq, keep=keep)
        try:
            put()
        except BaseException:
            self.done(seq)
            raise
        if gone is not None and gone():
            self.clear(recover=True)

    def done(self, seq: int) -> None:
        """TagPoses for `seq` arrived: return its credit (unknown seqs are ignored). An orphan of that
        seq not yet taken is answered too (a new edge can answer a frame sent in the instant its token
        was not there yet): it is not recomputed, so no frame gets two TagPoses from that race."""
        with self._cond:
            self._kept.pop(seq, None)
            self._orphans = [(s, kept) for s, kept in self._orphans if s != seq]
            sent = self._sent.pop(seq, None)
            if sent is not None:
                self._answers.append(self._clock() - sent)
                self._cond.notify_all()

    @property
    def typical_answer_secs(self) -> float:
        """The median time in flight of the last 20 answers (0: none yet)."""
        with self._cond:
            return float(statistics.median(self._answers)) if self._answers else 0.0

    def set_capacity(self, capacity: int) -> None:
        """A new number of credits (> 0: a window cannot be switched off once made); a frame waiting
        for a credit takes a new one at once."""
        if capacity < 1 or self.capacity == 0:
            raise ValueError("a window's capacity stays >= 1 (and 0, no window, stays 0)")
        with self._cond:
            self.capacity = capacity
            self._cond.notify_all()

    @property
    def in_flight(self) -> int:
        """Frames currently in flight (expired ones no longer count)."""
        with self._cond:
            self._expire()
            return len(self._sent)


def credits_needed(*, cycle_secs: float, period_secs: float, floor: int, ceiling: int) -> int:
    """Credits that keep a chain of period `period_secs` (its slowest stage, or the camera) busy when
    each credit comes back `cycle_secs` after the robot starts a frame with it (the robot's compute,
    then the frame's time in flight, put -> answer): ceil(cycle / period), within [floor, ceiling]
    (unknown figures: the floor). With fewer the window, not the chain, sets the frame rate: a 40 ms
    uplink floor held k = 0 on the emulated 5G link at 12.4-12.6 fps with a 15 fps camera and an edge
    good for 25."""
    if cycle_secs <= 0 or period_secs <= 0:
        return floor
    return max(floor, min(ceiling, math.ceil(cycle_secs / period_secs - 1e-9)))


def may_run_ahead(*, in_flight: int, capacity: int, pace_delay_secs: float, edge_alive: bool) -> bool:
    """Whether robot_infer may make the next frame's stage 1 now, while the current frame (made, not
    yet sent) is in its network: the next frame would go out as soon as it is made, so making it
    early costs it no freshness. Needs room in the window for it with the current frame counted
    (capacity 0: no window), no pacer delay (the edge keeps up) and the edge there."""
    room = capacity == 0 or in_flight + 1 < capacity
    return room and pace_delay_secs <= 0 and edge_alive


class EdgeWatch:
    """Whether the robot must run the whole chain on board: the edge's liveliness token is gone, or a
    frame sent to it has waited longer than answer_timeout_secs for its answer. Thread-safe (liveliness
    and answer callbacks run on Zenoh's threads).

    An overdue answer is remembered (`overdue`) until the edge answers promptly again (`answered`: a
    frame answered within answer_timeout_secs of its sending) or its token comes back (`edge_up`): a
    stalled edge keeps its token for Zenoh's whole lease, and forgetting the overdue frames used to make
    the next frame look like the first one in flight, so it went to the stalled edge too, and so on: a
    trial's SIGSTOPped edge_infer left the robot without a pose for ~10 s, not 1.5. While overdue, one
    frame per answer_timeout_secs still goes to the edge (`trial_due`) to find out. The late answers of
    the frames a stall held do not end it (an edge that always answers late would flip the robot back
    to it after each, to wait another timeout without poses: review). A single answer lost with nothing
    else in flight (a Features the edge refused) also starts a spell, ended by the next trial's answer
    one timeout later: `stalls` counts both."""

    def __init__(self, *, answer_timeout_secs: float, clock: Callable[[], float] = time.monotonic) -> None:
        self.answer_timeout_secs = answer_timeout_secs
        self._clock = clock
        self._alive = False
        self._overdue = False
        self._trial_at = -math.inf
        self._lock = threading.Lock()
        self.outages = 0  # the token lost
        self.stalls = 0  # an answer overdue while the token was there

    def edge_up(self) -> None:
        """The edge's liveliness token appeared (a new or reconnected edge: trusted again)."""
        with self._lock:
            self._alive = True
            self._overdue = False

    @property
    def alive(self) -> bool:
        """The edge's liveliness token is there."""
        with self._lock:
            return self._alive

    @property
    def overdue(self) -> bool:
        """An answer came later than answer_timeout_secs (or not at), and none since."""
        with self._lock:
            return self._overdue

    @property
    def usable(self) -> bool:
        """Frames may go to the edge: its token is there and no answer is overdue."""
        with self._lock:
            return self._alive and not self._overdue

    def edge_down(self) -> None:
        """The edge's liveliness token disappeared."""
        with self._lock:
            if self._alive:
                self.outages += 1
            self._alive = False

    def answered(self, round_trip_secs: float) -> None:
        """The edge answered a frame `round_trip_secs` after it was sent (on the robot's clock): within
        answer_timeout_secs, it is responsive again."""
        if round_trip_secs <= self.answer_timeout_secs:
            with self._lock:
                self._overdue = False

    def on_board(self, oldest_in_flight_secs: float) -> bool:
        """True when frames must not be sent to the edge now (but see `trial_due`)."""
        with self._lock:
            if self._alive and oldest_in_flight_secs > self.answer_timeout_secs and not self._overdue:
                self._overdue = True
                self.stalls += 1
                self._trial_at = self._clock()  # the first trial one timeout after the spell began
            return not self._alive or self._overdue

    def trial_due(self) -> bool:
        """While overdue with the token there: whether this frame goes to the edge after all, to see if it
        answers again (one per answer_timeout_secs; the frame is dropped if it does not)."""
        with self._lock:
            now = self._clock()
            if self._alive and self._overdue and now - self._trial_at >= self.answer_timeout_secs:
                self._trial_at = now
                return True
            return False


@dataclass
class _Crossing:
    """One answered frame's crossing, as UplinkQueue keeps it: its arrival (receiver clock), size,
    gap after the message ahead (None: unknown), and what that says."""

    received: float
    kB: float
    after_ahead: float | None = None
    held: bool = False  # arrived further apart from the frame before than it was sent
    late: bool = False  # held back by its gap, but the frame right behind it came too soon: a late stamp
    catch_up: bool = False  # right behind a late stamp: its gap is short by the lateness


class UplinkQueue:
    """The uplink as the pacer needs it, from answered frames' link stamps alone: how long a frame of
    S kB occupies the link (x S) and its transit when it finds the link free (t0 + x S).

    The link is a FIFO pipe: a frame sent at s arrives at a = max(s + t0, a_prev) + x S, a_prev being
    the arrival of the message ahead of it (a frame or a probe). A frame therefore bounds both unknowns
    from above, whether or not it waited: x S <= a - a_prev (equal when it waited) and t0 <= a - s - x S
    (equal when it did not). Each is the minimum of its bounds over the last `window` frames, the bound
    on x taken only from frames that visibly waited (below); no estimate of t0 decides which frames
    count (a fit that told them apart with its own t0 locked onto a wrong t0 / beta split after a step
    of the floor or of the edge's clock, holding the link at 40-80 % of its throughput: found in
    review). A step of the floor or of either clock passes out of the window within `window` frames
    whichever way it goes (t0 carries the clocks' offset; only differences on one clock are used for x).
    The sender needs no t0 to keep the pipe free of queues: on its own clock the pipe takes the next
    frame without a wait from F_n = max(s_n, F_(n-1)) + x S_n on, and re-anchoring F on an arrival a
    needs t0 (F = a - t0). A pacer that starts each frame at F reads back what it chose, so an x too
    large would confirm itself: once in every `probe_every` frames one starts `probe_fraction` of a
    frame's link time early, which finds the link free (a smaller bound on x) or waits a little (x
    exactly). Only frames the link held back give bounds on x: frames that arrived more than
    `stretch_fraction` further apart than they were sent (margin over jitter), of at least
    `min_size_kB`, and only once the frame after it has been answered without refuting it: in a FIFO
    every arrival comes at least its own occupancy x S after the message ahead, so where the next frame,
    right behind a held-back one, arrived too soon after it for that bound (its gap a - a_prev, times 1
    + `stretch_fraction`, plus PAIR_ALLOWANCE_SECS, shorter than the bound times its own size S), the
    held-back one's stamp was late, not the link slow. On loopback at k = 0 the edge's callback stamped
    a frame 10 ms late now and then (its Python busy); the frame read as held back, x as 55 ms per 256
    kB, t0 as -54 ms, and the pacer held every frame for that link, leaving the edge idle 13-27 % of the
    time (the next frame arrived 35 ms after the late one: no link took 55 ms). The check is the frame's
    own successor only: a late stamp on a link that does hold frames back drops that one bound, not the
    others (a review found a first version, which took the window's closest pair of arrivals against
    every bound, losing x for 20 frames to one late stamp), and a message between the two (an echo
    probe) leaves the bound unchecked. Where the camera, the robot or the edge is slower, every spacing
    is theirs, a loose bound that made the link look exactly as slow as the camera and held frames until
    the next one was due (a frame dropped from the latest-only ring at 2 fps: found by
    tests/test_pipeline_multiprocess.py); with no held-back frame in the window x is unknown and the
    measured L stands in, as before. t0 is not probed: after the floor falls, frames paced on the old t0
    queue behind each other by the fall until one finds the link idle, which any lateness of a frame
    does (with 2 ms of arrival jitter the simulated chain is back at the new path's latency; on a link
    without any, the latency stays what it was before the fall). Probing late would cost throughput
    wherever x is only a loose bound, as on an edge-bound cut. Pure."""

    PAIR_ALLOWANCE_SECS = 0.005  # the fastest crossing's own wait or jitter, in the bound of x by a pair

    def __init__(
        self,
        *,
        window: int = 20,
        probe_every: int = 8,
        probe_fraction: float = 0.25,
        stretch_fraction: float = 0.1,
        min_size_kB: float = 16.0,
    ) -> None:
        if window < 1 or probe_every < 1 or not 0 <= probe_fraction < 1 or stretch_fraction <= 0:
            raise ValueError("window and probe_every >= 1, probe_fraction in [0, 1), stretch_fraction > 0")
        self.probe_every = probe_every
        self.probe_fraction = probe_fraction
        self.stretch_fraction = stretch_fraction
        self.min_size_kB = min_size_kB
        self.window = window
        self._log: deque[_Crossing] = deque(maxlen=window)  # the answered frames' crossings, oldest first
        self._transits: deque[tuple[float, float]] = deque(maxlen=window)  # (a - s, S): t0's, given x
        self._last: tuple[float, float] | None = None  # the previous frame's (sent, received)
        self._x: float | None = None  # x_secs_per_kB, as of the latest answered frame

    @property
    def x_secs_per_kB(self) -> float | None:
        """The link's time per kB (worked out by `add` once per answered frame: see `_x_from_window`)."""
        return self._x

    def _x_from_window(self) -> float | None:
        """The link's time per kB, from the frames it held back among the last `window` (None: none was;
        an old bound would keep an x the link has since outgrown, and a paced frame would never show it),
        and at most what a larger frame's crossing allows after the fastest one's.

        No frame crosses faster than a free link: t0 + x S <= a - s for each, nearly equal for the
        fastest crossing (it most likely found the link free), so a frame at least twice as large bounds
        x by the difference of the two transits, plus PAIR_ALLOWANCE_SECS, over the difference of their
        sizes (the clocks' offset cancels). This is the one bound on x not taken from held-back frames.
        Without it, spacings stretched by a busy receiver rather than the link (a 2-core box, the
        controller trying cuts of 0.26-4 MB a frame) read as 0.4 ms/kB; a 4 MB frame that crossed in
        10 ms then put t0 at -1.6 s, every re-anchored start 1.6-3 s late, and the robot posed 0.6
        frames a second. x <= 0 is unknown (None), as before any held-back frame.

        Known limit: where every frame of the window queued (a saturated link, nothing paced), the
        fastest crossing waited too, and this bound falls below x by its wait over the size difference
        (a burst of 16-512 kB frames on a 0.6 ms/kB link read 0.11 ms/kB). Paced frames find the link
        nearly free, so the pacer's own chains keep one."""
        # FIFO: every message arrives at least its own occupancy x S after the one ahead, so every gap
        # bounds x (with the held-back margin and a jitter allowance per gap), and a held-back frame took
        # exactly its occupancy. A stamp that came late (a busy receiver) makes one gap too long, which
        # reads as held back, and the next one too short (both marked in `add`, and left out here); the
        # other bounds must agree with every other gap of the window. A bound counts once the frame after
        # it has been answered: a late stamp is only told apart by what follows it.
        log = self._log
        limit = min(
            (self._slack(e.after_ahead) / e.kB for e in log if e.after_ahead is not None and not e.catch_up),
            default=math.inf,
        )
        bounds = [
            e.after_ahead / e.kB
            for e in itertools.islice(log, max(0, len(log) - 1))
            if e.held and not e.late and e.after_ahead is not None and e.after_ahead / e.kB <= limit
        ]
        if not bounds:
            return None
        x = min(bounds)
        fastest, fastest_kB = min(self._transits)
        for transit, kB in self._transits:
            # only a frame at least twice as large, and with PAIR_ALLOWANCE_SECS for the fastest one's own
            # wait or jitter (it need not have found the link quite free): a tighter pair bound would
            # underestimate x, and a pacer with too small an x queues frames on the uplink
            if kB >= 2 * fastest_kB and kB >= self.min_size_kB:
                x = min(x, (transit - fastest + self.PAIR_ALLOWANCE_SECS) / (kB - fastest_kB))
        return x if x > 0 else None

    def _slack(self, after_ahead_secs: float) -> float:
        """The most occupancy a gap between two arrivals allows, with the held-back margin and jitter."""
        return (1 + self.stretch_fraction) * after_ahead_secs + self.PAIR_ALLOWANCE_SECS

    @property
    def t0_secs(self) -> float | None:
        """The link's floor (plus the clocks' offset), None before the first crossing."""
        if not self._transits:
            return None
        x = self.x_secs_per_kB or 0.0
        return min(transit - x * kB for transit, kB in self._transits)

    def transit_secs(self, size_kB: float) -> float | None:
        """A frame's time from send to arrival when it finds the link free."""
        t0 = self.t0_secs
        return None if t0 is None else t0 + (self.x_secs_per_kB or 0.0) * size_kB

    def add(
        self, *, size_kB: float, sent_secs: float, received_secs: float, previous_received_secs: float | None
    ) -> None:
        """One answered frame's crossing: sent on the sender's clock, received and the message ahead
        of it received (None: nothing ahead since the receiver started) on the receiver's."""
        if size_kB <= 0:
            return
        self._transits.append((received_secs - sent_secs, size_kB))
        last, self._last = self._last, (sent_secs, received_secs)
        entry = _Crossing(received_secs, size_kB)
        if last is not None and previous_received_secs is not None and received_secs > previous_received_secs:
            entry.after_ahead = received_secs - previous_received_secs
            sent_apart, arrived_apart = sent_secs - last[0], received_secs - last[1]
            # held back: arrived further apart than sent, by a margin jitter does not reach; a payload of a
            # real size (a per-message cost over 1 kB at k = 7 would read as a link 1000x too slow at k = 3)
            entry.held = size_kB >= self.min_size_kB and arrived_apart > (1 + self.stretch_fraction) * max(
                sent_apart, 0.0
            )
            ahead = self._log[-1] if self._log else None
            if (
                ahead is not None
                and ahead.held
                and ahead.after_ahead is not None
                and abs(previous_received_secs - ahead.received) < 1e-6  # right behind it, nothing between
                and ahead.after_ahead / ahead.kB * size_kB > self._slack(entry.after_ahead)
            ):
                ahead.late = True  # its bound is out: its stamp came late
                entry.catch_up = True  # and this gap is short by as much
        self._log.append(entry)
        self._x = self._x_from_window()

    def reset(self) -> None:
        """Another edge (another receiver clock, another link perhaps): learn afresh."""
        self._log.clear()
        self._transits.clear()
        self._last = None
        self._x = None


class EdgePacer:
    """When the robot should start its next frame so that the frame reaches the edge as the edge
    becomes free: no frame waits in the edge's queue (that wait is pure latency), and the robot takes
    the freshest camera frame at the last useful moment instead of one that would then sit and age.

    Model per frame: the robot computes for R, the link carries it in L, the edge computes E (per tag,
    times the frame's tags) after waiting W behind other robots' frames (an edge tier shared by a
    fleet). Sending frame n at s_n, the edge finishes it at c_n = max(s_n + L, c_(n-1)) + W + E_n;
    starting the next frame before c_n - R - L only makes it wait. R, L, E and W are exponential
    averages of what each answered frame measured (TagPoses timings; W from its stamps on the edge's
    clock: received -> done minus its compute, minus the part spent behind this robot's own previous
    frame, which the max() already models), and each answer re-anchors the prediction of the frames
    still in flight to when it really arrived. Without W an overloaded shared edge looked free to every
    robot's pacer, and each robot kept its whole window queued there: twice the latency for the same
    throughput. Thread-safe: answers arrive on Zenoh's threads. The in-flight window stays the hard cap.

    R is a mean, and a frame whose stage 1 runs longer (more candidates, a core shared with the edge)
    reaches the edge after it has freed: an edge-bound chain then idles by the overrun. With
    `margin_spreads` m each frame starts m mean absolute deviations of the robot's compute earlier than
    R alone says, so that most frames wait a little at the edge instead (k = 0 at 30 fps on a 2-core
    box, six interleaved rounds: m = 0 / 1 kept the edge busy 0.86-0.88 / 0.89-0.91 of the time, at
    1.7-4.0 / 3.8-4.7 ms of edge queue; docs/pipeline.md). On a link-bound chain the same margin is a
    wait on the uplink (the simulated 300 ms link of tests/test_flow.py with 0-20 ms of robot jitter:
    393 -> 397 ms at m = 1), and after a change of cut, while R moves to the new cut's time, the
    spread reads that move as well.

    With an `uplink` (UplinkQueue, fed here with every answered frame's payload and link stamps) the
    link is a server too, not a delay: the pipe takes frame n without a wait from F_n = max(s_n,
    F_(n-1)) + x S_n on (robot clock), the frame arrives at F_n + t0 and L above becomes its transit on
    a free link, t0 + x S. A frame started before F_(n-1) - R waits on the uplink behind the one ahead,
    and the measured L of such a frame includes that wait: it read as a slower link, the next frame
    started earlier still, and on a link-bound cut the robot kept its whole in-flight window queued on
    the uplink (the emulated 5G link at k = 3 measured 1063 ms against a predicted 729). Until the
    uplink has measured x, the measured L stands in."""

    def __init__(
        self,
        *,
        smoothing: float = 0.3,
        clock: Callable[[], float] = time.monotonic,
        uplink: UplinkQueue | None = None,
        stale_secs: float = 2.0,
        margin_spreads: float = 0.0,
    ) -> None:
        if not 0 < smoothing <= 1:
            raise ValueError("smoothing must be in (0, 1]")
        if not 0 <= margin_spreads < math.inf:
            raise ValueError(f"margin_spreads must be finite and >= 0, got {margin_spreads}")
        self._margin_spreads = margin_spreads
        self._stale_secs = stale_secs  # a frame unanswered this long is forgotten (its answer was lost)
        self._alpha = smoothing
        self._clock = clock
        self._lock = threading.Lock()
        self.uplink = uplink
        self.robot_secs = 0.0
        self.robot_spread_secs = 0.0  # mean absolute deviation of the robot's compute from robot_secs
        self.link_secs = 0.0
        self.payload_kB = 0.0
        self.tags = 0.0
        self.edge_secs_per_tag = 0.0
        self.edge_secs_fixed = 0.0
        self.edge_wait_secs = 0.0  # W: waiting at the edge behind other robots' frames
        # keyed as InFlightWindow is (increasing in send order: robot_infer's capture time; older = smaller)
        self._done_at: dict[int, float] = {}  # seq -> predicted edge completion (robot clock)
        self._last_done_at = 0.0
        self._edge_done_nanos = 0  # when the edge finished this robot's latest answered frame (edge clock)
        self._sent: dict[int, tuple[float, float]] = {}  # seq -> (sent, payload kB), robot clock
        self._link_free_at = 0.0  # F of the latest frame sent: the uplink takes the next one from then on
        self._frames_sent = 0

    def _avg(self, old: float, new: float) -> float:
        return new if old == 0.0 else old + self._alpha * (new - old)

    def period_secs(self) -> float:
        """The chain's slowest stage per frame as measured (0 until known): the robot, the uplink's
        occupancy (once measured) or the edge, with its wait behind other robots' frames."""
        with self._lock:
            x = self._x()
            link = 0.0 if x is None else x * self.payload_kB
            edge = self.edge_wait_secs + self.edge_secs_fixed + self.edge_secs_per_tag * self.tags
            return max(self.robot_secs, link, edge)

    def _x(self) -> float | None:
        return None if self.uplink is None else self.uplink.x_secs_per_kB

    def start_delay_secs(self) -> float:
        """How long to wait before taking the next frame (0: start now)."""
        with self._lock:
            x = self._x()
            transit = None if self.uplink is None else self.uplink.transit_secs(self.payload_kB)
            robot = self.robot_secs + self._margin_spreads * self.robot_spread_secs
            if self.uplink is None or x is None or transit is None:
                start = self._last_done_at - robot - self.link_secs
            else:
                link_free = self._link_free_at
                if self._frames_sent % self.uplink.probe_every == self.uplink.probe_every - 1:
                    link_free -= self.uplink.probe_fraction * x * self.payload_kB  # see UplinkQueue
                # on the uplink as the frame ahead has crossed it, at the edge as the edge frees up
                start = max(link_free, self._last_done_at - transit) - robot
            return max(0.0, start - self._clock())

    def sent(
        self, seq: int, *, tags: int, robot_secs: float, payload_bytes: int = 0, sent_at: float | None = None
    ) -> None:
        """Frame `seq` with `tags` tags and `payload_bytes` on the wire left the robot after
        `robot_secs` of robot compute; `sent_at`: when it was put (robot clock; default now: a put
        that blocked would otherwise count as link time)."""
        with self._lock:
            now = self._clock() if sent_at is None else sent_at
            kB = payload_bytes / 1024.0
            self._frames_sent += 1
            if self.robot_secs:
                self.robot_spread_secs += self._alpha * (abs(robot_secs - self.robot_secs) - self.robot_spread_secs)
            self.robot_secs = self._avg(self.robot_secs, robot_secs)
            self.payload_kB = self._avg(self.payload_kB, kB)
            self.tags = self._avg(self.tags, float(tags))
            edge = self.edge_wait_secs + self.edge_secs_fixed + self.edge_secs_per_tag * tags
            for stale in [q for q, (t, _) in self._sent.items() if t < now - self._stale_secs]:  # never answered
                del self._sent[stale]
                self._done_at.pop(stale, None)
            self._sent[seq] = (now, kB)
            x = self._x()
            t0 = None if self.uplink is None else self.uplink.t0_secs
            if x is None or t0 is None:
                arrive = now + self.link_secs
                free = now
            else:
                free = max(now, self._link_free_at) + x * kB
                arrive = free + t0
            self._link_free_at = max(self._link_free_at, free)
            done = max(arrive, self._last_done_at) + edge
            self._done_at[seq] = done
            self._last_done_at = done

    def answered(
        self,
        seq: int,
        *,
        tags: int,
        link_secs: float,
        edge_secs: float,
        edge_received_nanos: int | None = None,
        edge_done_nanos: int | None = None,
        link: LinkStamps | None = None,
    ) -> None:
        """The edge's answer for `seq` arrived now, saying what its link and edge compute took and, with
        both stamps (edge clock), when the edge received the frame and finished it; `link`: how it
        crossed the uplink (for the uplink's model)."""
        # Bounded: one answer with absurd timings (a forged one) must not hold the pacing for minutes.
        link_secs = min(max(link_secs, -MAX_ANSWER_SECS), MAX_ANSWER_SECS)
        edge_secs = min(edge_secs, MAX_ANSWER_SECS)
        with self._lock:
            now = self._clock()
            # (not clamped at 0: with the clocks' offset in it, it can be negative, and that offset must cancel)
            self.link_secs = self._avg(self.link_secs, link_secs)
            if tags:
                self.edge_secs_per_tag = self._avg(self.edge_secs_per_tag, max(0.0, edge_secs) / tags)
            else:
                self.edge_secs_fixed = self._avg(self.edge_secs_fixed, max(0.0, edge_secs))
            if edge_received_nanos is not None and edge_done_nanos is not None:
                waited = (edge_done_nanos - edge_received_nanos) / 1e9 - max(0.0, edge_secs)
                behind_own = (self._edge_done_nanos - edge_received_nanos) / 1e9  # our previous frame, still there
                foreign = min(max(0.0, waited - max(0.0, behind_own)), MAX_ANSWER_SECS)
                self.edge_wait_secs += self._alpha * (foreign - self.edge_wait_secs)  # 0 is a value here
                self._edge_done_nanos = edge_done_nanos  # the latest answer's (a new worker: its clock)
            sent = self._sent.pop(seq, None)
            for stale in [s for s in self._sent if s < seq]:  # older answers that never came
                del self._sent[stale]
            if link is not None and sent is not None and self.uplink is not None:
                prev = link.previous_received_nanos
                self.uplink.add(
                    size_kB=sent[1],
                    sent_secs=link.sent_nanos / 1e9,
                    received_secs=link.received_nanos / 1e9,
                    previous_received_secs=prev / 1e9 if prev else None,
                )
                self._re_anchor_uplink(sent[0] + (link.received_nanos - link.sent_nanos) / 1e9)
            predicted = self._done_at.pop(seq, None)
            for stale in [s for s in self._done_at if s < seq]:
                del self._done_at[stale]
            if predicted is not None:
                # Where it was done, on the clock the predictions are on: this clock plus the edge's
                # offset (the measured link time L and the uplink's t0 carry it), taken from the frame's
                # own stamps. Anchored on the answer's arrival instead, an edge clock behind this one by
                # more than a transit pushed every start later by the offset (a review: 3.33 -> 0.70
                # frames/s at -3 s); with no stamps the answer is the completion (+ a small return trip).
                actual = now
                if sent is not None and link is not None and edge_done_nanos is not None:
                    actual = sent[0] + (edge_done_nanos - link.sent_nanos) / 1e9
                shift = actual - predicted
                self._done_at = {s: t + shift for s, t in self._done_at.items()}
                self._last_done_at = max(self._done_at.values(), default=actual)

    def _re_anchor_uplink(self, arrived: float) -> None:
        """The answered frame arrived at `arrived` (robot clock + the clocks' offset): the pipe took the
        next frame from arrived - t0 on; the frames still in flight follow from there, in order."""
        assert self.uplink is not None
        x, t0 = self.uplink.x_secs_per_kB, self.uplink.t0_secs
        if x is None or t0 is None:
            return
        free = arrived - t0
        for seq in sorted(self._sent):
            sent_at, kB = self._sent[seq]
            free = max(sent_at, free) + x * kB
        self._link_free_at = free

    def forget(self) -> None:
        """The edge restarted or is gone: nothing is in flight any more (and the next edge, perhaps
        another worker with another clock and load, is measured afresh)."""
        with self._lock:
            self._done_at.clear()
            self._last_done_at = 0.0
            self.edge_wait_secs = 0.0
            self._edge_done_nanos = 0
            self._sent.clear()
            self._link_free_at = 0.0
            if self.uplink is not None:
                self.uplink.reset()
