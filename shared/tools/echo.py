"""The edge-side echo process: a router session with the link-probe queryable and a liveliness token."""

from __future__ import annotations

import logging
import threading

import zenoh

from shared.runtime.signals import SignalStop
from shared.runtime.waiting import until_set
from shared.transport.probe import serve_echo
from shared.transport.session import ZenohSettings, open_session
from shared.wire import keys
from shared.wire.codec import DEFAULT_MAX_BYTES

log = logging.getLogger(__name__)


def run(
    zenoh_settings: ZenohSettings,
    *,
    robot_id: str,
    max_bytes: int = DEFAULT_MAX_BYTES,
    stop: threading.Event | None = None,
) -> None:
    """Serve probes until `stop` is set (or SIGINT/SIGTERM when run as the main thread)."""
    stop = stop or threading.Event()
    signals = SignalStop(stop) if threading.current_thread() is threading.main_thread() else None
    try:
        session = open_session(zenoh_settings)
    except BaseException:
        if signals is not None:
            signals.restore()
        raise
    try:
        queryable = serve_echo(session, keys.echo(robot_id), max_bytes=max_bytes)

        # Raw echo: what an application on Zenoh alone does (reads the payload into bytes, replies its
        # 8-byte length), to separate Zenoh's cost from the codec's.
        def raw_echo(query: zenoh.Query) -> None:
            payload = query.payload.to_bytes() if query.payload is not None else b""
            query.reply(query.key_expr, len(payload).to_bytes(8, "little"))

        raw = session.declare_queryable(keys.echo(robot_id) + "/raw", raw_echo)
        token = session.liveliness().declare_token(keys.alive(robot_id, "echo"))
        log.info("echo serving %s", keys.echo(robot_id))
        until_set(stop)
        token.undeclare()
        raw.undeclare()
        queryable.undeclare()
    finally:
        session.close()
        if signals is not None:
            signals.restore()
        log.info("echo stopped")
