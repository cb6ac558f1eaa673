"""Many robots, one edge tier: which edge worker serves which robot, decided by every worker alike.

Each edge_infer worker declares a liveliness token (`keys.edge_worker`); each robot_infer declares
its own (`keys.alive(robot, "robot_infer")`). From the set of live workers every worker computes the
same assignment with rendezvous (highest-random-weight) hashing with bounded loads: a robot goes to
the worker with the highest hash of (robot, worker) that still has room for its share. No broker, no
election, no messages beyond the tokens: when a worker disappears its robots move, and (almost) all
others stay where they are. The hash is
blake2b, so the answer is the same in every process and on every host (Python's own hash is salted).

`FleetView` is the thread-safe bookkeeping of the tokens (Zenoh calls it on its threads); it tells
its owner which robots it serves after each change. No Zenoh here: the service wires it.
"""

from __future__ import annotations

import hashlib
import threading
from collections.abc import Callable, Iterable


def weight(robot_id: str, worker_id: str) -> int:
    """The rendezvous weight of one (robot, worker) pair: the same in every process."""
    digest = hashlib.blake2b(f"{robot_id}\x00{worker_id}".encode(), digest_size=8).digest()
    return int.from_bytes(digest, "big")


def assign(robots: Iterable[str], workers: Iterable[str]) -> dict[str, str]:
    """robot -> the worker that serves it (no workers: empty): rendezvous hashing with bounded loads.
    Robots are placed in id order, each with the highest-weight worker that has fewer than
    ceil(robots / workers) robots, so no worker carries more than its share (plain rendezvous hashing
    put all 4 robots of a 2-worker bench on one worker). The same sets give the same answer in every
    process; a worker that leaves hands on all of its robots, and the others keep theirs unless the
    bound makes room for a newcomer ahead of them (rarely: tests/test_fleet.py measures it)."""
    pool = sorted(set(workers))
    if not pool:
        return {}
    order = sorted(set(robots))
    cap = -(-len(order) // len(pool))
    load = dict.fromkeys(pool, 0)
    out: dict[str, str] = {}
    for r in order:
        ranked = sorted(pool, key=lambda w: (weight(r, w), w), reverse=True)
        chosen = next(w for w in ranked if load[w] < cap)
        load[chosen] += 1
        out[r] = chosen
    return out


class FleetView:
    """What one worker knows of the edge tier: the live workers, the robots to serve, and from them the
    robots that are its own. `on_change(robots)` is called with its new set whenever that set changes
    (outside the view's lock, on the caller's thread).

    `robots`: a fixed set to serve (None: every robot whose robot_infer token is alive)."""

    def __init__(
        self,
        worker_id: str,
        *,
        robots: Iterable[str] | None,
        on_change: Callable[[frozenset[str]], None],
    ) -> None:
        self.worker_id = worker_id
        self._fixed = frozenset(robots) if robots is not None else None
        self._on_change = on_change
        self._workers: set[str] = {worker_id}  # a worker always counts itself
        self._alive_robots: set[str] = set()
        self._mine: frozenset[str] = frozenset()
        self._lock = threading.Lock()
        self._notify_lock = threading.Lock()  # changes are reported in order
        self.reassignments = 0

    @property
    def workers(self) -> frozenset[str]:
        """The live workers (this one included)."""
        with self._lock:
            return frozenset(self._workers)

    @property
    def mine(self) -> frozenset[str]:
        """The robots this worker serves now."""
        with self._lock:
            return self._mine

    def _robots(self) -> set[str]:
        return set(self._fixed) if self._fixed is not None else set(self._alive_robots)

    def worker_up(self, worker_id: str) -> None:
        """A worker's token appeared (or was there when this one started)."""
        self._update(lambda: self._workers.add(worker_id))

    def worker_down(self, worker_id: str) -> None:
        """A worker's token disappeared (its robots move to the others)."""
        if worker_id != self.worker_id:
            self._update(lambda: self._workers.discard(worker_id))

    def robot_up(self, robot_id: str) -> None:
        """A robot_infer token appeared."""
        self._update(lambda: self._alive_robots.add(robot_id))

    def robot_down(self, robot_id: str) -> None:
        """A robot_infer token disappeared (a fixed robot set keeps it)."""
        self._update(lambda: self._alive_robots.discard(robot_id))

    def refresh(self) -> None:
        """Report the current set once (at start-up, after the initial tokens are read)."""
        self._update(lambda: None, force=True)

    def _update(self, change: Callable[[], None], *, force: bool = False) -> None:
        with self._notify_lock:
            with self._lock:
                change()
                mine = frozenset(r for r, w in assign(self._robots(), self._workers).items() if w == self.worker_id)
                changed = mine != self._mine
                if changed:
                    self.reassignments += 1
                self._mine = mine
            if changed or force:
                self._on_change(mine)
