"""Round-trip time of splittag messages through codec + Zenoh vs Zenoh alone vs a raw TCP ping-pong, one run.

Both servers run in their own process on 127.0.0.1, both replies are tiny (the payload loads only
the "uplink"), shared memory is off. codec + Zenoh: encoding the Features message, the query, the
echo's full check of it (decode_view) and its ProbeAck back (in the probe's framing), the client's
check of the ack; in framing 3 (what the services write: positional header checked by msgspec) and, in
the same run, framing 2 (the previous one: named header, pydantic validation). Zenoh alone: the same
querier options and payload size, the echo reading the payload into bytes and replying 8 bytes (what an
application without our codec does at the least). Each framing is timed in turn with Zenoh alone,
round trip by round trip, and its ratio is to that Zenoh-alone median: each path runs as it would alone
(run side by side, a heavier path chills the caches of the lighter one).

    .venv/bin/python -m bench.transport [--repetitions 200] [--framings 3 2]
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
from shared.runtime.cpus import allowed_cpus, pin_cpus
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


# (tensor bytes, message bytes of the first framing, {framing: (codec + Zenoh ms, Zenoh alone ms)}, raw TCP ms)
Row = tuple[int, int, dict[int, tuple[float, float]], float]


def measure(
    repetitions: int,
    *,
    shared_memory: bool,
    framings: tuple[int, ...] = (3, 2),
    split_cpus: tuple[int, int] | None = None,
) -> list[Row]:
    """One table: every size through codec + Zenoh, Zenoh alone and raw TCP. `split_cpus`: (this
    process's CPU, the servers' CPU); None: wherever the OS puts them."""
    robot = "bench"
    endpoint = f"tcp/127.0.0.1:{free_tcp_port()}"
    shm = ["--shared-memory"] if shared_memory else []
    echo_cmd = [sys.executable, "-m", "shared.tools.cli", "echo", "--listen", endpoint, "--robot-id", robot, *shm]
    echo = subprocess.Popen(
        [*echo_cmd, "--cpus", str(split_cpus[1])] if split_cpus else echo_cmd,
        start_new_session=True,
        stderr=subprocess.DEVNULL,
    )
    before = None
    rows: list[Row] = []
    try:
        before = pin_cpus([split_cpus[0]]) if split_cpus else None
        session = open_session(ZenohSettings(mode="client", connect=[endpoint], shared_memory=shared_memory))
        wait_for_liveliness(session, [keys.alive(robot, "echo")])
        prober = Prober(session, keys.echo(robot))
        # The same querier options as the Prober's: only the codec differs between the two columns.
        raw_querier = session.declare_querier(
            keys.echo(robot) + "/raw",
            timeout=10.0,
            congestion_control=zenoh.CongestionControl.BLOCK,
            target=zenoh.QueryTarget.ALL,
        )
        for size in SIZES:
            msg = probe_features(size, robot_id=robot)
            pairs: dict[int, tuple[float, float]] = {}
            for framing in framings:
                # Each framing in turn with Zenoh alone, round trip by round trip (same payload size): each
                # path runs as it would alone, and Zenoh alone under the same conditions.
                payload_bytes = len(encode(msg, framing=framing))
                raw_payload = bytes(payload_bytes)
                zen, raw = [], []
                for i in range(repetitions + 5):
                    t0 = time.perf_counter()
                    prober.round_trip(encode(msg, framing=framing))
                    t1 = time.perf_counter()
                    for reply in raw_querier.get(payload=raw_payload):
                        assert reply.ok is not None
                        reply.ok.payload.to_bytes()
                        break
                    t2 = time.perf_counter()
                    if i >= 5:
                        zen.append((t1 - t0) * 1e3)
                        raw.append((t2 - t1) * 1e3)
                pairs[framing] = (float(np.median(zen)), float(np.median(raw)))
            wire_bytes = len(encode(msg, framing=framings[0]))
            port = free_tcp_port()
            pin = f"from shared.runtime.cpus import pin_cpus; pin_cpus([{split_cpus[1]}]); " if split_cpus else ""
            server = subprocess.Popen(
                [
                    sys.executable,
                    "-c",
                    f"{pin}from bench.transport import tcp_echo_server as f; f({port})",
                ]
            )
            try:
                tcp = bench_tcp(port, wire_bytes, repetitions)
            finally:
                server.wait(timeout=10)
            rows.append((size, wire_bytes, pairs, float(np.median(tcp))))
        prober.close()
        session.close()
    finally:
        echo.send_signal(signal.SIGINT)
        echo.wait(timeout=10)
        if before is not None:
            pin_cpus(before)
    return rows


def print_table(rows: list[Row], *, repetitions: int, shared_memory: bool, split_cpus: tuple[int, int] | None) -> None:
    """The table of one run: per framing, codec + Zenoh, Zenoh alone timed alongside it, their ratio."""
    framings = list(rows[0][2])
    where = f"client on CPU {split_cpus[0]}, servers on CPU {split_cpus[1]}" if split_cpus else "CPUs shared"
    print(
        f"median of {repetitions} round trips, 127.0.0.1, zenoh shared memory {'on' if shared_memory else 'off'}, "
        f"{where}"
    )
    head = "".join(f" {f'framing {f} ms':>13} {'zenoh ms':>9} {f'f{f}/zenoh':>9}" for f in framings)
    print(f"{'tensor B':>9} {'message B':>10}{head} {'raw TCP ms':>11}")
    for size, wire, pairs, tcp in rows:
        cells = "".join(f" {c:>13.3f} {z:>9.3f} {c / z:>9.2f}" for c, z in pairs.values())
        print(f"{size:>9} {wire:>10}{cells} {tcp:>11.3f}")
    for f in framings:
        worst = max(pairs[f][0] / pairs[f][1] for _, _, pairs, _ in rows)
        print(f"worst codec+zenoh / zenoh alone, framing {f}: {worst:.2f}x")


def main() -> None:
    """Run the benchmarks and print the tables."""
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--repetitions", type=int, default=200)
    ap.add_argument(
        "--framings",
        type=int,
        nargs="+",
        choices=(3, 2, 1),
        default=[3, 2],
        help="codec framings to time (the first sets the message size of the Zenoh-alone column)",
    )
    ap.add_argument(
        "--shared-memory",
        choices=("off", "on", "both"),
        default="off",
        help="zenoh shared memory on both ends (same host only: it bypasses any link shaping)",
    )
    ap.add_argument(
        "--placement",
        choices=("shared", "split"),
        nargs="+",
        default=["shared", "split"],
        help="shared: where the OS puts the processes; split: the client on one CPU, the servers on another",
    )
    args = ap.parse_args()
    print(f"CPU: {cpu_label()}", flush=True)
    modes = {"off": [False], "on": [True], "both": [False, True]}[args.shared_memory]
    framings = tuple(dict.fromkeys(args.framings))
    cpus = sorted(allowed_cpus())
    placements: list[tuple[int, int] | None] = []
    for placement in dict.fromkeys(args.placement):
        if placement == "shared":
            placements.append(None)
        elif len(cpus) >= 2:
            placements.append((cpus[0], cpus[1]))
        else:
            print(f"placement split needs two CPUs; this process may use {cpus}: skipped")
    tables = [
        (shm, split, measure(args.repetitions, shared_memory=shm, framings=framings, split_cpus=split))
        for split in placements
        for shm in modes
    ]
    for shm, split, rows in tables:
        print_table(rows, repetitions=args.repetitions, shared_memory=shm, split_cpus=split)


if __name__ == "__main__":
    main()
