"""Every Zenoh key expression splittag uses, in one place (documented in the README).

Data topics end in the schema version of the message they carry, so a v2 publisher never feeds a
v1 subscriber (tests/test_transport.py holds each key, its docstring and the README's key table to its
message's version); control keys (split, alive, echo) carry their schema in the Zenoh encoding instead.
"""

from __future__ import annotations

import re
from typing import Final

ROOT: Final[str] = "splittag"
_ID = re.compile(r"^[A-Za-z0-9_\-]{1,64}$")


def _check(segment: str, what: str) -> str:
    if not _ID.match(segment):
        raise ValueError(f"{what} {segment!r} must match {_ID.pattern} (no '/', '*', '$' or spaces)")
    return segment


def is_wildcard(key: str) -> bool:
    """Whether a key expression names keys by a wildcard (`*`, `**` or `$*`), not one key."""
    return "*" in key or "$" in key


def frames(robot_id: str) -> str:
    """Frame v1: camera -> robot_infer."""
    return f"{ROOT}/{_check(robot_id, 'robot id')}/frame/v1"


def ground_truth(robot_id: str) -> str:
    """CameraPose v3 (status ground_truth): camera -> evaluators, when the source knows it."""
    return f"{ROOT}/{_check(robot_id, 'robot id')}/ground_truth/v3"


def frame_stamp(robot_id: str) -> str:
    """FrameStamp v1: camera -> slam, a data set's own time for a frame (folder source with rgb.txt)."""
    return f"{ROOT}/{_check(robot_id, 'robot id')}/frame_stamp/v1"


def features(robot_id: str) -> str:
    """Features v4: robot_infer -> edge_infer (the split tensor crosses the link here)."""
    return f"{ROOT}/{_check(robot_id, 'robot id')}/features/v4"


def tag_poses(robot_id: str) -> str:
    """TagPoses v4: edge_infer -> slam, controller, robot_infer (credits)."""
    return f"{ROOT}/{_check(robot_id, 'robot id')}/tag_poses/v4"


def frame_sent(robot_id: str) -> str:
    """FrameSent v1: robot_infer -> controller (robot-local), one per Features put on the uplink."""
    return f"{ROOT}/{_check(robot_id, 'robot id')}/frame_sent/v1"


def camera_pose(robot_id: str) -> str:
    """CameraPose v3: slam -> anyone."""
    return f"{ROOT}/{_check(robot_id, 'robot id')}/camera_pose/v3"


def tag_map(robot_id: str) -> str:
    """TagMap v3: slam publishes on change and answers gets (queryable) on the same key."""
    return f"{ROOT}/{_check(robot_id, 'robot id')}/map/v3"


def split(robot_id: str) -> str:
    """Queryable of robot_infer: get -> current SplitConfig; get with `k=<n>` sets it."""
    return f"{ROOT}/{_check(robot_id, 'robot id')}/split"


def split_auto(robot_id: str) -> str:
    """The same queryable for a controller: every set here is a controller's (refused while a person's
    setting is pinned), so access control can let a controller steer without letting it pin."""
    return f"{split(robot_id)}/auto"


def compute(robot_id: str, side: str) -> str:
    """ComputeProfile v2: robot_infer (side robot) and edge_infer (side edge) -> controller, ~1 Hz."""
    if side not in ("robot", "edge"):
        raise ValueError(f"side must be robot or edge, not {side!r}")
    return f"{ROOT}/{_check(robot_id, 'robot id')}/compute/{side}/v2"


def controller(robot_id: str) -> str:
    """ControllerState v2: the adaptive split controller's estimates, predictions and decision."""
    return f"{ROOT}/{_check(robot_id, 'robot id')}/controller/v2"


def echo(robot_id: str) -> str:
    """Queryable on the edge that answers link probes with a tiny reply."""
    return f"{ROOT}/{_check(robot_id, 'robot id')}/echo"


def alive(robot_id: str, service: str) -> str:
    """Liveliness token of one service of one robot."""
    return f"{ROOT}/{_check(robot_id, 'robot id')}/alive/{_check(service, 'service')}"


def robot_of(key: str) -> str:
    """The robot id of a per-robot key (`splittag/<robot_id>/...`); ValueError for any other key, and
    for a key with a wildcard anywhere: a put on `splittag/r1/**` reaches every subscriber of r1, and
    must not count as a message of whichever topic received it."""
    text = str(key)
    parts = text.split("/")
    if len(parts) < 3 or parts[0] != ROOT:
        raise ValueError(f"{key!r} is not a splittag/<robot_id>/... key")
    if "*" in text or "$" in text:
        raise ValueError(f"{key!r} is a wildcard, not one robot's key")
    return _check(parts[1], "robot id")


# Keys of the edge tier as a whole (not of one robot). '@fleet' is a verbatim chunk: no robot id can
# spell it and no `splittag/*/...` wildcard of a per-robot key matches it.
FLEET: Final[str] = f"{ROOT}/@fleet"


def for_every_robot(key: str) -> str:
    """A per-robot key with its robot id replaced by `*`: the same key of every robot."""
    parts = key.split("/")
    robot_of(key)
    return "/".join([parts[0], "*", *parts[2:]])


def fleet_service(service: str) -> str:
    """Liveliness token of a service that serves the whole fleet (slam with `robots`)."""
    return f"{FLEET}/{_check(service, 'service')}"


def edge_worker(tier: str, worker_id: str) -> str:
    """Liveliness token of one edge_infer worker of an edge tier (discovery and robot assignment):
    workers share robots only with the workers of their own tier."""
    return f"{FLEET}/{_check(tier, 'edge tier')}/edge_worker/{_check(worker_id, 'worker id')}"


def edge_workers(tier: str) -> str:
    """Every worker's liveliness token of one edge tier."""
    return f"{FLEET}/{_check(tier, 'edge tier')}/edge_worker/*"


def worker_of(key: str) -> str:
    """The worker id of an `edge_worker` token key."""
    parts = str(key).split("/")
    if len(parts) != 5 or f"{parts[0]}/{parts[1]}" != FLEET or parts[3] != "edge_worker":
        raise ValueError(f"{key!r} is not a {FLEET}/<tier>/edge_worker/<id> key")
    return _check(parts[4], "worker id")


def stats(robot_id: str, service: str) -> str:
    """Queryable of every service: its input counters (accepted, rejected by reason) as JSON."""
    return f"{ROOT}/{_check(robot_id, 'robot id')}/{_check(service, 'service')}/stats"
