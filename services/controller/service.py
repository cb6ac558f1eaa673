"""The controller loop: evidence from TagPoses, ComputeProfiles and sparse probes; a decision every
decide_period_secs; the split applied through the public split query, on the controller's key
(`splittag/<robot>/split/auto`: every set there is a controller's, refused while a person's pin
holds); state published.

Why its own process (not inside robot_infer): it must never delay a frame (probing blocks for a
round trip, fitting costs CPU at its own pace); it can be stopped, restarted or replaced (e.g. by an
oracle in experiments) without touching inference; and going through the public split query proves
that any client, human or not, can steer the split. It runs on the robot side, next to the split
queryable, so its probes cross the uplink exactly like the features do.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from typing import TypeVar

import zenoh

from services.controller.settings import ControllerSettings
from shared.control.controller import SplitController
from shared.control.linkmodel import ProbeBudget
from shared.runtime.guard import InputGuard, persist_input_counts, serve_stats
from shared.transport.probe import ProbeError, Prober
from shared.transport.session import encoding_for
from shared.transport.split_client import SplitQueryError, query_split
from shared.viz.recording import Viz, make_viz
from shared.wire import keys
from shared.wire.messages import (
    ComputeProfile,
    ControllerState,
    FrameSent,
    Message,
    TagPoses,
    decode_for_robot,
    encode,
)
from shared.wire.sizing import probe_features

log = logging.getLogger(__name__)
M = TypeVar("M", bound=Message)


class ProbeFailures:
    """What the probe loop says about failed probes: the first of a run of failures (a warning once the
    echo has answered before; until then the edge is still starting: info), with why, then nothing
    until a probe is answered again, which is said with how many failed and for how long (not after
    the failures of start-up, before any probe was answered). (A trial's
    controller logged 84 warnings, 6.5 a second, while robot_infer, the robot's router, was down, each
    asking whether the edge was running.)"""

    def __init__(self, reaches_router: Callable[[], bool], clock: Callable[[], float] = time.monotonic) -> None:
        self.reaches_router, self.clock = reaches_router, clock
        self.answered = False
        self.failed = 0
        self.since = 0.0

    def failure(self, size: int, exc: Exception) -> None:
        self.failed += 1
        if self.failed > 1:
            return
        self.since = self.clock()
        why = str(exc)
        if not self.reaches_router():
            why = "this controller reaches no router (robot_infer hosts the robot's router: is it running?)"
        level = logging.WARNING if self.answered else logging.INFO
        log.log(level, "probe of %d bytes failed: %s; further failures are not logged until one is answered", size, why)

    def success(self) -> None:
        if self.failed and self.answered:
            log.warning("probes answered again after %d failed over %.1f s", self.failed, self.clock() - self.since)
        self.answered, self.failed = True, 0


def _probe_loop(
    settings: ControllerSettings,
    core: SplitController,
    lock: threading.Lock,
    prober: Prober,
    stop: threading.Event,
    failures: ProbeFailures,
) -> None:
    """Sparse probes: one per period at a size not seen lately; at once (largest size) when the change
    detector is half-way to firing or its alarm is being judged, to settle it quickly; every size right
    after an alarm (its challenger fit needs more than one size to tell the floor from the slope: with
    64 kB probes alone, a bench.controller run's took over at t0 63 ms, beta 0.19 on a 39.9 ms / 0.577
    ms/kB link) and again after a change. All within `probe_budget_share` of the uplink (ProbeBudget)."""
    burst_from = core.link.changes + core.link.alarms
    budget = ProbeBudget(share=settings.probe_budget_share, depth_bytes=sum(settings.probe_sizes_bytes))
    last_probe = 0.0
    busy_since: float | None = None
    while not stop.wait(0.005):
        now = time.monotonic()
        with lock:
            idle = core.link_idle(time.time_ns())
        # A probe sent into a busy link waits behind frames and delays the ones after it: wait for the
        # link to drain, unless it has been busy so long that t0 would go unobserved.
        busy_since = None if idle else (busy_since if busy_since is not None else now)
        if busy_since is not None and now - busy_since < settings.probe_busy_max_wait_secs:
            continue
        with lock:
            changed = core.link.changes + core.link.alarms != burst_from
            burst_from = core.link.changes + core.link.alarms
            suspicious = core.link.alarm_level >= 0.4
            due = core.probe_size_due(settings.probe_sizes_bytes, settings.probe_max_age_secs)
        if changed:
            sizes = list(settings.probe_sizes_bytes)
        elif suspicious and now - last_probe >= 0.05:
            sizes = [max(settings.probe_sizes_bytes)]
        elif due is not None and now - last_probe >= settings.probe_period_secs:
            sizes = [due]
        else:
            continue
        for size in sizes:
            with lock:
                beta = core.link.beta_ms_per_kB
            if not budget.take(size, beta_ms_per_kB=beta, force=changed):
                break  # the uplink's probe budget is spent: the next when it has refilled
            try:
                r = prober.round_trip(encode(probe_features(size)))
            except ProbeError as exc:
                failures.failure(size, exc)
                continue
            finally:
                last_probe = time.monotonic()
            failures.success()
            with lock:
                if r.link is not None:
                    core.add_crossing(r.payload_bytes, r.link)
                else:
                    core.add_link_sample(r.payload_bytes, r.rtt_secs * 1e3)


def _decide(
    settings: ControllerSettings, session: zenoh.Session, core: SplitController, lock: threading.Lock
) -> tuple[ControllerState, bool] | None:
    """One decision: read robot_infer's split, choose k, apply it when enabled. None: no split state.
    Returns the state to publish and whether the split was switched."""
    rid = settings.robot_id
    try:
        split = query_split(session, rid, timeout_secs=2.0, auto=True, ask_again=False)
    except SplitQueryError as exc:
        log.debug("no split state: %s", exc)
        return None
    with lock:
        state = core.decide(robot_id=rid, current_k=split.k, pinned=split.pinned)
    if not settings.enabled or state.chosen_k == split.k:
        return state, False
    try:
        applied = query_split(session, rid, params=f"k={state.chosen_k}", auto=True, ask_again=False)
    except SplitQueryError as exc:  # pinned meanwhile, or robot_infer restarting
        return state.model_copy(update={"reason": f"{state.reason}; refused: {exc}"}), False
    log.info("split k=%d -> %d: %s", split.k, state.chosen_k, state.reason)
    if applied.k == state.chosen_k:
        with lock:
            core.switched(split.k, applied.k)
    return state.model_copy(update={"applied": applied.k == state.chosen_k}), True


def _log_state(viz: Viz, state: ControllerState) -> None:
    # Only what is known: no link estimate before the first sample, no T(k) before both compute
    # profiles (the state carries zeros there, which a plot would show as T = 0).
    link = (
        {"controller/t0_ms": state.t0_ms, "controller/beta_ms_per_kB": state.beta_ms_per_kB}
        if state.link_samples or state.has_prediction
        else {}
    )
    predicted = (
        {f"controller/predicted_ms/k{k}": v for k, v in enumerate(state.predicted_ms_by_k)}
        if state.has_prediction
        else {}
    )
    throughput: dict[str, float] = {}
    if state.has_prediction and state.period_ms_by_k is not None:
        throughput = {f"controller/period_ms/k{k}": v for k, v in enumerate(state.period_ms_by_k)}
    for k, ms in enumerate(state.achieved_ms_by_k or []):
        if ms is not None:
            throughput[f"controller/achieved_ms/k{k}"] = ms
    if state.frame_share_by_k is not None and state.min_frame_share is not None:
        throughput |= {f"controller/frame_share/k{k}": v for k, v in enumerate(state.frame_share_by_k)}
        throughput["controller/min_frame_share"] = state.min_frame_share
    if state.frame_interval_ms is not None:
        throughput["controller/frame_interval_ms"] = state.frame_interval_ms
    chosen = {"controller/chosen_k": float(state.chosen_k), "controller/best_k": float(state.best_k)}
    viz.scalars(state.stamp_nanos, {**link, **chosen, **predicted, **throughput})


def run(settings: ControllerSettings, *, session: zenoh.Session, stop: threading.Event) -> None:
    """Decide until `stop` is set."""
    rid = settings.robot_id
    core = SplitController(settings)
    lock = threading.Lock()
    guard = InputGuard("controller")
    persist_input_counts(guard, settings.run_dir, label=settings.robot_id)
    stats = serve_stats(session, keys.stats(rid, "controller"), guard)

    def subscribe(key: str, schema: type[M], handle: Callable[[M], None]) -> zenoh.Subscriber[None]:
        """A callback subscriber that decodes, counts and logs bad messages, and fuses good ones."""

        def fuse(payload: bytes) -> None:
            msg = decode_for_robot(payload, schema, rid)
            with lock:
                handle(msg)

        def on_sample(sample: zenoh.Sample) -> None:
            payload = sample.payload.to_bytes()
            guard.run(schema.__name__, len(payload), lambda: fuse(payload))

        return session.declare_subscriber(key, on_sample)

    # edge_infer's liveliness token (as robot_infer watches it): frames posed on board while it is there
    # were late at the cut in use, not a pause
    edge_alive = threading.Event()

    def on_edge(sample: zenoh.Sample) -> None:
        if sample.kind == zenoh.SampleKind.PUT:
            edge_alive.set()
        else:
            edge_alive.clear()
            with lock:
                core.edge_gone()

    def on_poses(m: TagPoses) -> None:
        if m.payload_bytes == 0:  # computed on board: nothing crossed the link
            core.add_on_board(edge_alive=edge_alive.is_set())
            return
        core.add_posed(m.split_k, m.capture_nanos)  # what the cut achieves between frames
        if m.link is not None:
            core.add_crossing(m.payload_bytes, m.link)
        else:  # from an edge that predates link stamps: right only on an idle link
            core.add_link_sample(m.payload_bytes, m.timings.transport_secs * 1e3)
        h = m.timings  # what the frame took where T(k) predicts it: the model's check (measured_window_secs)
        core.add_measured(m.split_k, (h.robot_compute_secs + h.transport_secs + h.edge_compute_secs) * 1e3, len(m.tags))

    subs = [
        subscribe(keys.tag_poses(rid), TagPoses, on_poses),
        subscribe(keys.frame_sent(rid), FrameSent, core.frame_sent),
        subscribe(keys.compute(rid, "robot"), ComputeProfile, core.add_compute),
        subscribe(keys.compute(rid, "edge"), ComputeProfile, core.add_compute),
    ]
    edge_token = session.liveliness().declare_subscriber(keys.alive(rid, "edge_infer"), on_edge, history=True)
    pub = session.declare_publisher(keys.controller(rid), encoding=encoding_for(ControllerState.SCHEMA))
    prober = Prober(session, keys.echo(rid), timeout_secs=settings.probe_timeout_secs)
    failures = ProbeFailures(lambda: any(True for _ in session.info.routers_zid()))
    prober_thread = threading.Thread(
        target=_probe_loop, args=(settings, core, lock, prober, stop, failures), daemon=True
    )
    prober_thread.start()
    token = session.liveliness().declare_token(keys.alive(rid, "controller"))
    viz = make_viz(settings.rerun, service="controller", run_dir=settings.run_dir)
    switches = 0
    unread_since: float | None = None  # since when the split has not been readable (None: it is)
    warned = False
    log.info("controller ready (enabled=%s)", settings.enabled)
    try:
        while not stop.wait(settings.decide_period_secs):
            decided = _decide(settings, session, core, lock)
            if decided is None:
                unread_since = unread_since or time.monotonic()
                if not warned and time.monotonic() - unread_since > 10.0:
                    # An old robot_infer without the controller's key, or access control that denies it,
                    # looked exactly like a robot not yet up (a reviewer): say so once.
                    log.warning(
                        "no answer on %s for 10 s: is robot_infer running (a version that serves it), and may "
                        "this identity ask it?",
                        keys.split_auto(rid),
                    )
                    warned = True
                continue
            unread_since, warned = None, False
            state, switched = decided
            switches += switched
            pub.put(encode(state))
            _log_state(viz, state)
    finally:
        token.undeclare()
        edge_token.undeclare()
        for s in subs:
            s.undeclare()
        prober_thread.join(timeout=settings.probe_timeout_secs + 5.0)  # a probe in flight ends first
        prober.close()
        viz.close()
        stats.undeclare()
        guard.close()  # the last interval's rejections said, the counts written
        log.info(
            "controller: %d switches, %d vetoed by the frames measured at both cuts, %d held as ping-pong; "
            "%d link alarms: %d changes taken, %d dismissed (a fresh fit did not predict the link better); "
            "%d link samples left out as stamped at once after a stall of this process or the edge's; inputs %s",
            switches,
            core.vetoed,
            core.held,
            core.link.alarms,
            core.link.changes,
            core.link.dismissed,
            core.link.bunched,
            guard.stats(),
        )
