"""Round-trip time of splittag messages through codec + Zenoh vs a raw TCP ping-pong, one run.

Both servers run in their own process on 127.0.0.1, both replies are tiny (the payload loads only
the "uplink"), shared memory is off. Zenoh timing includes encoding the Features message, the
query, the server's full decode + validation, and decoding the ack.

    .venv/bin/python -m bench.transport [--repetitions 200]
"""

from __future__ import annotations

import argparse
import signal
import socket
import struct
import subprocess
import sys
import time

import numpy as np
import zenoh

from bench.machine import cpu_label
from shared.transport.probe import Prober
from shared.transport.session import ZenohSettings, free_tcp_port, open_session, wait_for_liveliness
from shared.wire import keys
from shared.wire.messages import encode
from shared.wire.sizing import probe_features

SIZES = [64, 256, 1024, 4096, 16384, 65536, 262144, 1 << 20, 2 << 20]
_LEN = struct.Struct("!Q")


def tcp_echo_server(port: int) -> None:
    """Serve one client: read a length-prefixed payload, answer 8 bytes; until EOF."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as srv:
        srv.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        srv.bind(("127.0.0.1", port))
        srv.listen(1)
        conn, _ = srv.accept()
        conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        buf = bytearray(4 << 20)
        view = memoryview(buf)
        while True:
            head = conn.recv(8, socket.MSG_WAITALL)
            if len(head) < 8:
                return
            (n,) = _LEN.unpack(head)
            got = 0
            while got < n:
                r = conn.recv_into(view[got:n], n - got)
                if r == 0:
                    return
                got += r
            conn.sendall(_LEN.pack(n))


def _connect(port: int) -> socket.socket:
    deadline = time.monotonic() + 10
    while True:
        try:
            s = socket.create_connection(("127.0.0.1", port))
            s.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            return s
        except ConnectionRefusedError:
            if time.monotonic() > deadline:
                raise
            time.sleep(0.05)


def bench_tcp(port: int, size: int, reps: int) -> list[float]:
    """RTTs (ms) of the raw TCP ping-pong at one size."""
    payload = bytes(size)
    out = []
    with _connect(port) as s:
        for _ in range(reps + 5):
            t0 = time.perf_counter()
            s.sendall(_LEN.pack(size) + payload)
            s.recv(8, socket.MSG_WAITALL)
            out.append((time.perf_counter() - t0) * 1e3)
    return out[5:]


def main() -> None:
    """Run both benchmarks and print the table."""
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--repetitions", type=int, default=200)
    args = ap.parse_args()
    print(f"CPU: {cpu_label()}", flush=True)
    robot = "bench"
    endpoint = f"tcp/127.0.0.1:{free_tcp_port()}"
    echo = subprocess.Popen(
        [sys.executable, "-m", "shared.tools.cli", "echo", "--listen", endpoint, "--robot-id", robot],
        start_new_session=True,
        stderr=subprocess.DEVNULL,
    )
    rows = []
    try:
        session = open_session(ZenohSettings(mode="client", connect=[endpoint]))
        wait_for_liveliness(session, [keys.alive(robot, "echo")])
        prober = Prober(session, keys.echo(robot))
        raw_querier = session.declare_querier(
            keys.echo(robot) + "/raw", congestion_control=zenoh.CongestionControl.BLOCK
        )
        for size in SIZES:
            msg = probe_features(size, robot_id=robot)
            zen = []
            for i in range(args.repetitions + 5):
                t0 = time.perf_counter()
                prober.round_trip(encode(msg))
                if i >= 5:
                    zen.append((time.perf_counter() - t0) * 1e3)
            raw_payload = bytes(len(encode(msg)))
            raw = []
            for i in range(args.repetitions + 5):
                t0 = time.perf_counter()
                for reply in raw_querier.get(payload=raw_payload):
                    assert reply.ok is not None
                if i >= 5:
                    raw.append((time.perf_counter() - t0) * 1e3)
            port = free_tcp_port()
            server = subprocess.Popen(
                [
                    sys.executable,
                    "-c",
                    f"from bench.transport import tcp_echo_server as f; f({port})",
                ]
            )
            try:
                tcp = bench_tcp(port, len(encode(msg)), args.repetitions)
            finally:
                server.wait(timeout=10)
            rows.append((size, len(encode(msg)), float(np.median(zen)), float(np.median(raw)), float(np.median(tcp))))
        prober.close()
        session.close()
    finally:
        echo.send_signal(signal.SIGINT)
        echo.wait(timeout=10)
    print(f"median of {args.repetitions} round trips, 127.0.0.1, zenoh shared memory off")
    print(
        f"{'tensor B':>9} {'message B':>10} {'codec+zenoh ms':>15} {'zenoh only ms':>14} {'raw TCP ms':>11} "
        f"{'ratio':>6} {'zenoh/TCP':>10}"
    )
    for size, wire, z, r, t in rows:
        print(f"{size:>9} {wire:>10} {z:>15.3f} {r:>14.3f} {t:>11.3f} {z / t:>6.2f} {r / t:>10.2f}")


if __name__ == "__main__":
    main()
