"""Zenoh transport options for the split tensor on the paper's link, measured side by side in one run.

Robot and edge each in their own network namespace, joined by the emulated 5G uplink
(shared/tools/linkemu: t0 39.9 ms, beta 0.18 ms/kB), and the same on loopback. What varies is what
`ZenohSettings` and the publishers/queriers can set:

- **batch size** (`transport/link/tx/batch_size`, negotiated as the smaller of the two ends; zenoh's
  default and maximum 65535): a message larger than a batch travels in fragments;
- **express** (a per-publisher/querier flag: never wait to share a batch);
- **priority** of a small message while large ones stream (zenoh keeps one queue per priority).

Payloads are raw bytes of the sizes the cuts send for 3.5 tags at fp16 (codec cost is
bench/transport.py's subject), through a querier to a queryable that reads them and answers 8 bytes,
as the link probe does: round-trip time = t0 + S beta on the emulated link. Under load, a publisher
(congestion control BLOCK, priority DATA, as the Features publisher) streams 230 kB messages (k = 0)
back to back while the small probe measures its round trip at each priority.

    .venv/bin/python -m bench.zenoh_options [--repetitions 15]   # needs root (network namespaces)
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
import zenoh

from bench.machine import cpu_label
from shared.runtime.signals import SignalStop
from shared.transport.session import ZenohSettings, build_config, free_tcp_port, wait_for_liveliness
from shared.wire.cuts import tensor_bytes

KEY_ECHO = "bench/options/echo"
KEY_SINK = "bench/options/sink"
KEY_ALIVE = "bench/options/alive"
BATCH_SIZES = [8192, 16384, 32768, 65535]
TAGS = 3.5
HEADER_BYTES = 1500  # a Features header for 3.5 tags, about
SIZES = {k: int(tensor_bytes(k) * TAGS) + HEADER_BYTES for k in (7, 6, 5, 0, 3)}
LOAD_BYTES = SIZES[0]
PROBE_BYTES = 1024
PRIORITIES = {"data": zenoh.Priority.DATA, "interactive_high": zenoh.Priority.INTERACTIVE_HIGH}


def _config(settings: ZenohSettings, batch_size: int) -> zenoh.Config:
    return build_config(settings.model_copy(update={"batch_size_bytes": batch_size}))


def serve(listen: str, batch_size: int) -> None:
    """The edge end: an echo queryable (reads the payload, answers 8 bytes) and a sink subscriber."""
    stop = threading.Event()
    SignalStop(stop, [signal.SIGTERM])
    session = zenoh.open(_config(ZenohSettings(mode="router", listen=[listen]), batch_size))

    def echo(query: zenoh.Query) -> None:
        n = len(query.payload.to_bytes()) if query.payload is not None else 0
        query.reply(query.key_expr, n.to_bytes(8, "little"))

    def sink(sample: zenoh.Sample) -> None:
        sample.payload.to_bytes()

    queryable = session.declare_queryable(KEY_ECHO, echo)
    subscriber = session.declare_subscriber(KEY_SINK, sink)
    token = session.liveliness().declare_token(KEY_ALIVE)
    stop.wait()
    token.undeclare()
    subscriber.undeclare()
    queryable.undeclare()
    session.close()


def _round_trips(querier: zenoh.Querier, size: int, repetitions: int, *, warmup: int = 2) -> list[float]:
    payload = bytes(size)
    out = []
    for i in range(repetitions + warmup):
        t0 = time.perf_counter()
        for reply in querier.get(payload=payload):
            if reply.ok is None:
                raise RuntimeError("the echo replied an error")
            reply.ok.payload.to_bytes()
            break
        if i >= warmup:  # the first ones open TCP windows
            out.append((time.perf_counter() - t0) * 1e3)
    return out


def measure(connect: str, batch_size: int, repetitions: int, *, load: bool) -> dict[str, Any]:
    """The robot end: RTT per size (express off and on), and with `load` the probe under a stream."""
    session = zenoh.open(_config(ZenohSettings(mode="client", connect=[connect]), batch_size))
    try:
        wait_for_liveliness(session, [KEY_ALIVE], timeout_secs=60)
        out: dict[str, Any] = {"batch_size": batch_size, "rtt_ms": {}}
        for express in (False, True):
            querier = session.declare_querier(
                KEY_ECHO,
                timeout=30.0,
                congestion_control=zenoh.CongestionControl.BLOCK,
                express=express,
                target=zenoh.QueryTarget.ALL,
            )
            out["rtt_ms"]["express" if express else "batched"] = {
                str(k): _round_trips(querier, size, repetitions) for k, size in SIZES.items()
            }
            querier.undeclare()
        if load:
            out["under_load"] = _under_load(session, repetitions)
        return out
    finally:
        session.close()


def _under_load(session: zenoh.Session, repetitions: int) -> dict[str, Any]:
    """Probe RTTs at each priority while a BLOCK publisher streams k = 0 frames back to back."""
    stop = threading.Event()
    sent = [0]
    pub = session.declare_publisher(
        KEY_SINK, congestion_control=zenoh.CongestionControl.BLOCK, priority=zenoh.Priority.DATA
    )
    payload = bytes(LOAD_BYTES)

    def stream() -> None:
        while not stop.is_set():
            pub.put(payload)
            sent[0] += 1

    thread = threading.Thread(target=stream, daemon=True)
    thread.start()
    time.sleep(2.0)  # the stream fills the link and the queues
    out: dict[str, Any] = {}
    t0, n0 = time.monotonic(), sent[0]
    queriers = {
        name: session.declare_querier(
            KEY_ECHO, timeout=30.0, congestion_control=zenoh.CongestionControl.BLOCK, priority=priority
        )
        for name, priority in PRIORITIES.items()
    }
    for name in PRIORITIES:
        out[name] = []
    for querier in queriers.values():
        _round_trips(querier, PROBE_BYTES, 0, warmup=1)
    for _ in range(repetitions):  # interleaved, so a drift of the queues is not read as a priority's effect
        for name, querier in queriers.items():
            out[name] += _round_trips(querier, PROBE_BYTES, 1, warmup=0)
    for querier in queriers.values():
        querier.undeclare()
    out["stream_mbit_s"] = (sent[0] - n0) * LOAD_BYTES * 8 / 1e6 / (time.monotonic() - t0)
    stop.set()
    thread.join(timeout=30)
    pub.undeclare()
    return out


def _run_pair(
    batch_size: int, repetitions: int, *, load: bool, edge_wrap: list[str], robot_wrap: list[str], listen: str
) -> dict[str, Any]:
    server = subprocess.Popen(
        [*edge_wrap, sys.executable, "-m", "bench.zenoh_options", "--serve", listen, "--batch-size", str(batch_size)],
        start_new_session=True,
    )
    try:
        argv = [sys.executable, "-m", "bench.zenoh_options", "--measure", listen, "--batch-size", str(batch_size)]
        argv += ["--repetitions", str(repetitions), *(["--load"] if load else [])]
        done = subprocess.run([*robot_wrap, *argv], capture_output=True, text=True, timeout=900)
        if done.returncode != 0:
            raise RuntimeError(f"the robot end failed ({done.returncode}):\n{done.stderr[-4000:]}")
        return dict(json.loads(done.stdout.strip().splitlines()[-1]))
    finally:
        server.send_signal(signal.SIGTERM)
        try:
            server.wait(timeout=30)
        except subprocess.TimeoutExpired:
            os.killpg(server.pid, signal.SIGKILL)  # never leave it in a namespace about to go
            server.wait(timeout=30)


def _p50(values: list[float]) -> float:
    return float(np.median(values))


def print_tables(link: str, results: list[dict[str, Any]]) -> None:
    """RTT medians per batch size and size, express off / on; the probe under load per priority."""
    print(f"\n{link}: median round trip ms (express off / on), {len(results[0]['rtt_ms']['batched']['7'])} each")
    print(f"{'batch size':>10} " + " ".join(f"{f'k={k} {s / 1024:.0f} kB':>18}" for k, s in SIZES.items()))
    for r in results:
        cells = [
            f"{_p50(r['rtt_ms']['batched'][str(k)]):8.2f} / {_p50(r['rtt_ms']['express'][str(k)]):7.2f}" for k in SIZES
        ]
        print(f"{r['batch_size']:>10} " + " ".join(f"{c:>18}" for c in cells))
    loaded = [r for r in results if "under_load" in r]
    for r in loaded:
        u = r["under_load"]
        parts = ", ".join(
            f"{name} p50 {_p50(u[name]):.1f} p90 {float(np.percentile(u[name], 90)):.1f} ms" for name in PRIORITIES
        )
        print(
            f"{link}, batch {r['batch_size']}: 1 kB probe while k = 0 frames stream ({u['stream_mbit_s']:.1f} Mbit/s): "
            + parts
        )


def main() -> None:
    """Run every configuration on the emulated 5G link and on loopback; print the tables."""
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--repetitions", type=int, default=15)
    ap.add_argument("--serve", help=argparse.SUPPRESS)
    ap.add_argument("--measure", help=argparse.SUPPRESS)
    ap.add_argument("--batch-size", type=int, default=65535, help=argparse.SUPPRESS)
    ap.add_argument("--load", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.serve:
        serve(args.serve, args.batch_size)
        return
    if args.measure:
        print(json.dumps(measure(args.measure, args.batch_size, args.repetitions, load=args.load)))
        return

    from shared.tools.linkemu import PROFILES, LinkEmulator, LinkEmulatorSettings, in_netns, unavailable_reason

    print(f"CPU: {cpu_label()}", flush=True)
    port = free_tcp_port()
    loop = [
        _run_pair(b, args.repetitions, load=b == 65535, edge_wrap=[], robot_wrap=[], listen=f"tcp/127.0.0.1:{port}")
        for b in BATCH_SIZES
    ]
    print_tables("loopback", loop)
    reason = unavailable_reason()
    if reason is not None:
        print(f"\nemulated 5G link: not measured ({reason})")
        return
    with tempfile.TemporaryDirectory() as tmp, LinkEmulator(LinkEmulatorSettings(), log_dir=Path(tmp)) as emu:
        emu.up(PROFILES["5g"])
        s = emu.settings
        five_g = [
            _run_pair(
                b,
                args.repetitions,
                load=b in (16384, 65535),
                edge_wrap=in_netns(s.edge_ns, []),
                robot_wrap=in_netns(s.robot_ns, []),
                listen=f"tcp/{s.edge_addr}:{port}",
            )
            for b in BATCH_SIZES
        ]
    print_tables(f"emulated 5G uplink ({PROFILES['5g'].description})", five_g)


if __name__ == "__main__":
    main()
