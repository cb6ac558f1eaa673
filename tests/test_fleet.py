"""The fleet's pure parts: rendezvous assignment, the worker's view of the tier, fleet keys, the
batched edge step, and the fleet plan's configs."""

from __future__ import annotations

import tomllib
from pathlib import Path

import numpy as np
import pytest

from shared.tools.fleet import FleetPlan, fleet_configs
from shared.transport.fleet import FleetView, assign
from shared.wire import keys

REPO = Path(__file__).resolve().parent.parent


def test_assignment_is_balanced_stable_and_moves_little_beyond_a_dead_workers_robots() -> None:
    robots = [f"robot{i}" for i in range(200)]
    workers = ["edge1", "edge2", "edge3", "edge4"]
    full = assign(robots, workers)
    assert assign(reversed(robots), list(reversed(workers))) == full  # order-free: every process agrees
    counts = {w: sum(v == w for v in full.values()) for w in workers}
    assert max(counts.values()) == 50, counts  # the bound: nobody carries more than its share
    without = assign(robots, [w for w in workers if w != "edge2"])
    dead = {r for r in robots if full[r] == "edge2"}
    moved = {r for r in robots if without[r] != full[r]}
    assert dead <= moved and len(moved - dead) <= 0.1 * len(robots), len(moved - dead)
    assert assign(robots, []) == {}
    for n in range(1, 9):  # small fleets on two workers: never all on one
        small = assign([f"robot{i + 1}" for i in range(n)], ["edge1", "edge2"])
        assert max(sum(w == x for w in small.values()) for x in ("edge1", "edge2")) == -(-n // 2)


def test_fleet_view_reports_its_own_robots_on_every_change() -> None:
    reports: list[frozenset[str]] = []
    robots = ["r1", "r2", "r3", "r4", "r5", "r6"]
    view = FleetView("w1", robots=robots, on_change=reports.append)
    view.refresh()
    assert reports == [frozenset(robots)]  # alone: everything
    view.worker_up("w2")
    mine = {r for r, w in assign(robots, ["w1", "w2"]).items() if w == "w1"}
    assert reports[-1] == frozenset(mine) and view.mine == frozenset(mine)
    n = len(reports)
    view.worker_up("w2")  # a repeated token changes nothing, reports nothing
    assert len(reports) == n
    view.worker_down("w2")
    assert reports[-1] == frozenset(robots)
    view.worker_down("w1")  # a worker never forgets itself
    assert view.workers == frozenset({"w1"})


def test_fleet_view_with_discovered_robots_follows_their_tokens() -> None:
    reports: list[frozenset[str]] = []
    view = FleetView("w1", robots=None, on_change=reports.append)
    view.refresh()
    assert reports == [frozenset()]
    view.robot_up("a")
    view.robot_up("b")
    assert view.mine == {"a", "b"}
    view.robot_down("a")
    assert view.mine == {"b"}


def test_fleet_keys() -> None:
    assert keys.for_every_robot(keys.tag_poses("r1")) == "splittag/*/tag_poses/v3"
    assert keys.robot_of("splittag/r7/features/v3") == "r7"
    assert keys.worker_of(keys.edge_worker("fleet", "edge2")) == "edge2"
    with pytest.raises(ValueError, match="not a"):
        keys.worker_of(keys.alive("r1", "edge_infer"))
    with pytest.raises(ValueError, match="robot id"):
        keys.robot_of("splittag/*/features/v3")
    import zenoh

    # The fleet's keys can never be taken for a robot's: '@fleet' is a verbatim chunk.
    assert not zenoh.KeyExpr(keys.alive_any_robot("edge_infer")).intersects(
        zenoh.KeyExpr(keys.edge_worker("fleet", "w"))
    )

    # Two robots' own single-robot edges (each a tier of its own) never count each other as workers.
    assert not zenoh.KeyExpr(keys.edge_workers("robot1")).intersects(zenoh.KeyExpr(keys.edge_worker("robot2", "edge1")))


def test_a_batch_of_two_robots_gives_what_each_alone_gives() -> None:
    """One tail pass over two robots' tags (edge_batch) publishes the same poses as one pass each."""
    from shared.model.runtime import load_split_net
    from shared.perception.split import EdgeInput, edge_batch, edge_step
    from shared.vision.tagmap import TagMapFile
    from shared.wire.messages import Features
    from tests.examples import example_messages

    base = example_messages()[Features.SCHEMA]
    assert isinstance(base, Features)
    from shared.wire.cuts import CUTS

    rng = np.random.default_rng(0)
    k = 5
    messages = []
    for robot in ("r1", "r2"):
        tags = [
            t.model_copy(update={"tensor": np.maximum(rng.normal(0, 1, CUTS[k].shape), 0).astype(np.float16)})
            for t in base.tags
        ]
        messages.append(base.model_copy(update={"robot_id": robot, "split_k": k, "codec": "fp16", "tags": tags}))
    net = load_split_net(REPO / "models", "fp32")
    tag_map = TagMapFile(default_size_m=0.2)
    alone = [
        edge_step(m, net=net, tag_map=tag_map, receive_nanos=2, previous_receive_nanos=1, payload_bytes=10)
        for m in messages
    ]
    together = edge_batch([EdgeInput(m, 2, 1, 10, tag_map) for m in messages], net=net)
    for a, b in zip(alone, together, strict=True):
        assert a.robot_id == b.robot_id and len(a.tags) == len(b.tags) == len(base.tags)
        for ta, tb in zip(a.tags, b.tags, strict=True):
            np.testing.assert_allclose(tb.keypoints_px, ta.keypoints_px, atol=1e-3)


def test_fleet_configs_give_each_process_its_identity_and_endpoints(tmp_path: Path) -> None:
    plan = FleetPlan.from_config(REPO / "deploy" / "fleet.toml")
    specs = fleet_configs(plan, tmp_path, REPO / "deploy" / "fleet.toml")
    names = [s.name for s in specs]
    assert names == [
        "slam",
        "edge1",
        "edge2",
        "robot1_robot_infer",
        "robot1_camera",
        "robot2_robot_infer",
        "robot2_camera",
    ]
    docs = {s.name: tomllib.loads(s.config.read_text()) for s in specs}
    assert docs["slam"]["slam"]["zenoh"] == {"mode": "router", "listen": ["tcp/127.0.0.1:7447"]}
    assert docs["edge2"]["edge_infer"]["worker_id"] == "edge2"
    assert docs["edge2"]["edge_infer"]["robots"] == ["robot1", "robot2"]
    assert docs["edge2"]["edge_infer"]["tier"] == "fleet"
    assert docs["robot1_camera"]["common"]["rerun"]["entity_prefix"] == "robots/robot1/"
    assert docs["robot2_robot_infer"]["common"]["robot_id"] == "robot2"
    assert docs["robot2_robot_infer"]["robot_infer"]["zenoh"]["listen"] == ["tcp/127.0.0.1:7449"]
    assert docs["robot2_camera"]["camera"]["zenoh"]["connect"] == ["tcp/127.0.0.1:7449"]
    assert "fleet" not in docs["slam"]
    with pytest.raises(ValueError, match="repeat"):
        FleetPlan(robots=["a", "a"], edge_workers=["w"])
