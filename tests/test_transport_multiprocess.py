"""Two real processes on loopback: a 1 MiB float16 Features message crosses Zenoh bit-exact."""

from __future__ import annotations

import time
from pathlib import Path

import msgpack
import numpy as np
import pytest

from shared.transport.session import (
    ZenohSettings,
    declare_tensor_publisher,
    free_tcp_port,
    open_session,
    wait_for_liveliness,
)
from shared.wire import keys
from shared.wire.messages import Features, TagFeature, encode
from tests.examples import INTRINSICS
from tests.peers.features_checker import expected_tensor, verdict_key
from tests.procs import processes, start_process

pytestmark = pytest.mark.multiprocess

NBYTES = 1 << 20


def test_one_mebibyte_tensor_crosses_bit_exact(tmp_path: Path) -> None:
    robot = "mp1"
    endpoint = f"tcp/127.0.0.1:{free_tcp_port()}"
    with processes(tmp_path) as procs:
        procs.append(
            start_process(
                "checker",
                [
                    "-m",
                    "tests.peers.features_checker",
                    "--listen",
                    endpoint,
                    "--robot-id",
                    robot,
                    "--seed",
                    "11",
                    "--nbytes",
                    str(NBYTES),
                ],
                tmp_path,
            )
        )
        session = open_session(ZenohSettings(mode="client", connect=[endpoint]))
        try:
            wait_for_liveliness(session, [keys.alive(robot, "checker")], timeout_secs=30)
            tensor = expected_tensor(11, NBYTES)
            assert tensor.nbytes == NBYTES
            msg = Features(
                robot_id=robot,
                seq=1,
                capture_nanos=1,
                publish_nanos=2,
                split_k=2,
                codec="fp16",
                intrinsics=INTRINSICS,
                robot_compute_secs=0.0,
                tags=[
                    TagFeature(
                        tag_id=0,
                        decision_margin=1.0,
                        hamming=0,
                        corners_px=np.zeros((4, 2), np.float32),
                        roi_to_image=np.eye(3),
                        tensor=tensor,
                        edge_width_px=1.5,
                        tracked=False,
                    )
                ],
            )
            pub = declare_tensor_publisher(session, keys.features(robot), Features.SCHEMA)
            pub.put(encode(msg))
            verdict: dict = {}
            deadline = time.monotonic() + 20
            while time.monotonic() < deadline:
                for reply in session.get(verdict_key(robot), timeout=5):
                    assert reply.ok is not None
                    verdict = msgpack.unpackb(reply.ok.payload.to_bytes())
                if verdict.get("received"):
                    break
                time.sleep(0.05)
            assert verdict == {"received": 1, "bit_exact": True, "errors": []}
        finally:
            session.close()
