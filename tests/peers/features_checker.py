"""Test peer: receives one Features message, checks its tensor bit for bit, reports via a queryable."""

from __future__ import annotations

import argparse
import threading

import msgpack
import numpy as np
import zenoh

from shared.runtime.signals import SignalStop
from shared.transport.session import ZenohSettings, declare_fifo_subscriber, open_session
from shared.wire import keys
from shared.wire.codec import WireError
from shared.wire.messages import Features, decode


def expected_tensor(seed: int, nbytes: int) -> np.ndarray:
    """The tensor the test publishes (regenerated here from the same seed)."""
    rng = np.random.default_rng(seed)
    return rng.standard_normal(nbytes // 2).astype(np.float16).reshape(-1, 64, 64)


def verdict_key(robot_id: str) -> str:
    """Where the verdict queryable lives."""
    return f"splittag/{robot_id}/test/verdict"


def main() -> None:
    """Serve until SIGINT."""
    ap = argparse.ArgumentParser()
    ap.add_argument("--listen", required=True)
    ap.add_argument("--robot-id", required=True)
    ap.add_argument("--seed", type=int, required=True)
    ap.add_argument("--nbytes", type=int, required=True)
    args = ap.parse_args()
    stop = threading.Event()
    SignalStop(stop)
    want = expected_tensor(args.seed, args.nbytes)
    state: dict[str, object] = {"received": 0, "bit_exact": False, "errors": []}
    lock = threading.Lock()

    session = open_session(ZenohSettings(mode="router", listen=[args.listen]))
    sub = declare_fifo_subscriber(session, keys.features(args.robot_id))

    def on_query(query: zenoh.Query) -> None:
        with lock:
            query.reply(query.key_expr, msgpack.packb(state))

    # Keep references: a dropped token or queryable is undeclared.
    queryable = session.declare_queryable(verdict_key(args.robot_id), on_query)
    token = session.liveliness().declare_token(keys.alive(args.robot_id, "checker"))
    print("checker ready", flush=True)
    while not stop.is_set():
        sample = sub.try_recv()
        if sample is None:
            stop.wait(0.005)
            continue
        try:
            msg = decode(sample.payload.to_bytes(), Features)
            got = msg.tags[0].tensor
            exact = got.dtype == want.dtype and got.shape == want.shape and (got.tobytes() == want.tobytes())
            with lock:
                state["received"] = int(state["received"]) + 1  # type: ignore[call-overload]
                state["bit_exact"] = bool(exact)
        except WireError as exc:
            with lock:
                state["errors"].append(str(exc))  # type: ignore[attr-defined]
    token.undeclare()
    queryable.undeclare()
    session.close()


if __name__ == "__main__":
    main()
