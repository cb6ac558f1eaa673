"""`splittag demo`: real split-sized tensors crossing Zenoh between two processes on loopback.

The edge side (a child process) runs the echo queryable in a router session; this process joins
as a client, waits for the edge's liveliness token, then sends a Features message per split point
with that cut's tensor (the per-cut sizes of the paper's table) and prints round-trip times.
"""

from __future__ import annotations

import signal
import socket
import subprocess
import sys
import time

import numpy as np

from shared import keys
from shared.messages import encode
from shared.model import CUTS
from shared.probe import Prober, probe_features
from shared.transport import ZenohSettings, open_session, wait_for_liveliness


def free_tcp_port() -> int:
    """A TCP port on 127.0.0.1 that was free a moment ago."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        port: int = s.getsockname()[1]
        return port


def run_demo(*, robot_id: str = "demo", repetitions: int = 20) -> int:
    """Run the two-process exchange and print one line per split point; returns an exit code."""
    endpoint = f"tcp/127.0.0.1:{free_tcp_port()}"
    edge = subprocess.Popen(
        [sys.executable, "-m", "shared.cli", "echo", "--listen", endpoint, "--robot-id", robot_id],
        start_new_session=True,
    )
    try:
        session = open_session(ZenohSettings(mode="client", connect=[endpoint]))
        wait_for_liveliness(session, [keys.alive(robot_id, "echo")], timeout_secs=30)
        prober = Prober(session, keys.echo(robot_id))
        print(f"edge echo alive at {endpoint}; {repetitions} round trips per split point")
        print(f"{'k':>2} {'cut':<10} {'tensor':<16} {'message B':>10} {'RTT p50 ms':>11} {'p90 ms':>8}")
        for cut in CUTS:
            payload = encode(probe_features(cut.payload_bytes, robot_id=robot_id))
            rtts = [prober.round_trip(payload).rtt_secs * 1e3 for _ in range(repetitions)]
            p50, p90 = np.percentile(rtts, [50, 90])
            shape = "x".join(map(str, cut.shape))
            print(f"{cut.k:>2} {cut.name:<10} {shape:<16} {len(payload):>10} {p50:>11.3f} {p90:>8.3f}")
        prober.close()
        session.close()
        return 0
    finally:
        edge.send_signal(signal.SIGINT)
        try:
            edge.wait(timeout=10)
        except subprocess.TimeoutExpired:
            edge.kill()
            edge.wait()
        time.sleep(0)  # let the child's log lines flush before the shell prompt returns
