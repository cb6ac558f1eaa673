"""A user-space delay line on a TUN device: every packet read from the device is written back into it
`delay_ms` later, in order. The kernel has tbf and htb but no netem, so this adds the 5G link's
latency floor; tbf on the veth shapes the rate (see shared/tools/linkemu.py for the routing that sends
the robot's uplink packets through the TUN device and forwards them onto the veth after the delay).

Run inside the robot's network namespace (it attaches to an existing persistent TUN device):
    ip netns exec st-robot python -m shared.tools.delayline --tun sttun --delay-ms 39.9 --control /run/x.sock
The control socket (a Unix stream socket; path names cross network namespaces) takes one line of
JSON per connection, {"delay_ms": 12.5}, applies it to packets arriving from then on, and answers
with the state as JSON. With `--events FILE` (the launcher gives its run folder's link_events.jsonl) a
request's `event` (the link profile being applied, stamped by the applier) is appended to that file:
whoever applies a profile, the launcher or `splittag link set` from another shell, it is recorded by the
one process that owns the emulation, in the run folder it was started for.
"""

from __future__ import annotations

import argparse
import contextlib
import fcntl
import json
import logging
import os
import select
import signal
import socket
import struct
import time
from collections import deque
from collections.abc import Sequence
from pathlib import Path

log = logging.getLogger(__name__)

TUNSETIFF = 0x400454CA
IFF_TUN = 0x0001
IFF_NO_PI = 0x1000
MAX_PACKET = 65536
MAX_QUEUED = 100_000  # packets; beyond this the line drops (and counts) like a full router buffer


def open_tun(name: str) -> int:
    """Attach to the TUN device `name` (created by `ip tuntap add ... mode tun`), non-blocking."""
    fd = os.open("/dev/net/tun", os.O_RDWR | os.O_NONBLOCK)
    try:
        fcntl.ioctl(fd, TUNSETIFF, struct.pack("16sH", name.encode(), IFF_TUN | IFF_NO_PI))
    except OSError:
        os.close(fd)
        raise
    return fd


class DelayLine:
    """FIFO of (due time, packet). Pure bookkeeping; the loop in `serve` does the I/O."""

    def __init__(self, delay_ms: float) -> None:
        self.delay_secs = self._check(delay_ms) / 1e3
        self.queue: deque[tuple[float, bytes]] = deque()
        self.forwarded = self.dropped = 0

    @staticmethod
    def _check(delay_ms: float) -> float:
        if not 0.0 <= delay_ms <= 10_000.0:
            raise ValueError(f"delay_ms must be in [0, 10000], not {delay_ms}")
        return float(delay_ms)

    def set_delay_ms(self, delay_ms: float) -> None:
        """Packets arriving from now on wait this long (those queued keep their due time)."""
        self.delay_secs = self._check(delay_ms) / 1e3

    def push(self, now: float, packet: bytes) -> None:
        """A packet arrived at `now`."""
        if len(self.queue) >= MAX_QUEUED:
            self.dropped += 1
            return
        # FIFO: a packet never overtakes one queued before it, even when the delay just shrank.
        due = now + self.delay_secs
        if self.queue and self.queue[-1][0] > due:
            due = self.queue[-1][0]
        self.queue.append((due, packet))

    def pop_due(self, now: float) -> list[bytes]:
        """Packets whose time has come."""
        out = []
        while self.queue and self.queue[0][0] <= now:
            out.append(self.queue.popleft()[1])
        self.forwarded += len(out)
        return out

    def timeout(self, now: float) -> float | None:
        """Seconds until the next packet is due (None when empty)."""
        return max(0.0, self.queue[0][0] - now) if self.queue else None

    def state(self) -> dict[str, float | int]:
        """What the control socket reports."""
        return {
            "delay_ms": self.delay_secs * 1e3,
            "queued": len(self.queue),
            "forwarded": self.forwarded,
            "dropped": self.dropped,
        }


EVENT_FIELDS: dict[str, tuple[type, ...]] = {
    "unix_nanos": (int,),
    "profile": (str,),
    "rate_mbit": (int, float, type(None)),
    "delay_ms": (int, float),
    "beta_ms_per_kB": (int, float),
}


def record_event(events: Path, event: object) -> None:
    """Append one link event (checked: exactly EVENT_FIELDS, each of its type) to `events`; never through
    a symbolic link (the file is the run folder's, opened without following one)."""
    if not isinstance(event, dict) or set(event) != set(EVENT_FIELDS):
        raise ValueError(f"an event has exactly the fields {sorted(EVENT_FIELDS)}")
    for name, types in EVENT_FIELDS.items():
        if not isinstance(event[name], types) or isinstance(event[name], bool):
            raise ValueError(f"event field {name} has the wrong type")
    fd = os.open(events, os.O_WRONLY | os.O_APPEND | os.O_CREAT | os.O_NOFOLLOW, 0o644)
    with os.fdopen(fd, "a") as f:
        f.write(json.dumps(event) + "\n")


def _handle_control(conn: socket.socket, line: DelayLine, events: Path | None = None) -> None:
    with conn:
        conn.settimeout(2.0)
        try:
            raw = conn.recv(4096)
            request = json.loads(raw or b"{}")
            if "delay_ms" in request:
                line.set_delay_ms(float(request["delay_ms"]))
                log.info("delay set to %.2f ms", line.delay_secs * 1e3)
            recorded = False
            if "event" in request and events is not None:
                try:
                    record_event(events, request["event"])
                    recorded = True
                except OSError as exc:  # the run folder is gone or full: the link change still holds
                    log.warning("link event not recorded in %s: %s", events, exc)
            conn.sendall(json.dumps({"ok": True, "recorded": recorded, **line.state()}).encode())
        except (OSError, ValueError, TypeError) as exc:
            log.warning("control request rejected: %s", exc)
            with contextlib.suppress(OSError):
                conn.sendall(json.dumps({"ok": False, "error": str(exc)}).encode())


def serve(tun: str, delay_ms: float, control: Path, events: Path | None = None) -> int:
    """Run the delay line until SIGINT/SIGTERM (`events`: where the link events of requests go)."""
    fd = open_tun(tun)
    line = DelayLine(delay_ms)
    control.unlink(missing_ok=True)
    ctl = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    ctl.bind(str(control))
    ctl.listen(8)
    running = True

    def stop(*_: object) -> None:
        nonlocal running
        running = False

    signal.signal(signal.SIGINT, stop)
    signal.signal(signal.SIGTERM, stop)
    log.info("delay line on %s: %.2f ms, control %s", tun, delay_ms, control)
    try:
        while running:
            try:
                wait = line.timeout(time.monotonic())  # 0.0 means "due now": not the idle timeout
                readable, _, _ = select.select([fd, ctl.fileno()], [], [], 0.5 if wait is None else wait)
            except InterruptedError:
                continue
            now = time.monotonic()
            if fd in readable:
                for _ in range(256):
                    try:
                        line.push(now, os.read(fd, MAX_PACKET))
                    except BlockingIOError:
                        break
            if ctl.fileno() in readable:
                conn, _ = ctl.accept()
                _handle_control(conn, line, events)
            for packet in line.pop_due(time.monotonic()):
                try:
                    os.write(fd, packet)
                except OSError as exc:  # e.g. the device went down; drop like a link would
                    line.dropped += 1
                    log.debug("write failed: %s", exc)
    finally:
        os.close(fd)
        ctl.close()
        control.unlink(missing_ok=True)
        log.info("delay line stopped: %s", line.state())
    return 0


def control_request(control: Path, request: dict[str, object], timeout_secs: float = 5.0) -> dict[str, object]:
    """Send one request to a running delay line and return its JSON answer."""
    with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as s:
        s.settimeout(timeout_secs)
        s.connect(str(control))
        s.sendall(json.dumps(request).encode())
        answer: dict[str, object] = json.loads(s.recv(4096))
    if not answer.get("ok"):
        raise RuntimeError(f"delay line refused {request}: {answer.get('error')}")
    return answer


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point: python -m shared.tools.delayline --tun NAME --delay-ms MS --control PATH."""
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--tun", required=True)
    ap.add_argument("--delay-ms", type=float, required=True)
    ap.add_argument("--control", type=Path, required=True)
    ap.add_argument("--events", type=Path, default=None, help="append the requests' link events to this file")
    # the process that started it (`link up`, a launcher): while it runs, the link is in use, not a leftover
    ap.add_argument("--owner-pid", type=int, default=None)
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s delayline %(levelname)s %(message)s")
    return serve(args.tun, args.delay_ms, args.control, args.events)


if __name__ == "__main__":
    raise SystemExit(main())
