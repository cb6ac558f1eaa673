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
    assert keys.for_every_robot(keys.tag_poses("r1")) == "splittag/*/tag_poses/v4"
    assert keys.robot_of("splittag/r7/features/v4") == "r7"
    assert keys.worker_of(keys.edge_worker("fleet", "edge2")) == "edge2"
    with pytest.raises(ValueError, match="not a"):
        keys.worker_of(keys.alive("r1", "edge_infer"))
    for wildcard in ("splittag/*/features/v4", "splittag/r1/**", "splittag/r1/tag_poses/*", "splittag/r1/$*/v4"):
        with pytest.raises(ValueError, match="wildcard"):  # a put on r1/** is no one topic's message
            keys.robot_of(wildcard)
    import zenoh

    # The fleet's keys can never be taken for a robot's: '@fleet' is a verbatim chunk.
    assert not zenoh.KeyExpr(keys.for_every_robot(keys.alive("any", "edge_infer"))).intersects(
        zenoh.KeyExpr(keys.edge_worker("fleet", "w"))
    )

    # Two robots' own single-robot edges (each a tier of its own) never count each other as workers.
    assert not zenoh.KeyExpr(keys.edge_workers("robot1")).intersects(zenoh.KeyExpr(keys.edge_worker("robot2", "edge1")))


def test_a_batch_of_two_robots_gives_what_each_alone_gives() -> None:
    """One tail pass over two robots' tags (edge_batch) publishes the same poses as one pass each."""
    from shared.model.runtime import load_split_net
    from shared.perception.split import EdgeInput, edge_batch, edge_step
    from shared.vision.tagmap import TagMapFile
    from shared.wire.cuts import FeatureShapeError
    from shared.wire.messages import Features, TagPoses
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
        assert isinstance(b, TagPoses)
        assert a.robot_id == b.robot_id and len(a.tags) == len(b.tags) == len(base.tags)
        for ta, tb in zip(a.tags, b.tags, strict=True):
            np.testing.assert_allclose(tb.keypoints_px, ta.keypoints_px, atol=1e-3)

    # A third robot's tensor carries NaN (the wire does not scan tensor values): refused alone, in the
    # same single pass, and the others' poses are what they were.
    poisoned = messages[0].tags[0].tensor.copy()
    poisoned.flat[0] = np.nan
    bad = messages[0].model_copy(
        update={"robot_id": "r3", "tags": [messages[0].tags[0].model_copy(update={"tensor": poisoned})]}
    )
    mixed = edge_batch([EdgeInput(m, 2, 1, 10, tag_map) for m in (messages[0], bad, messages[1])], net=net)
    assert isinstance(mixed[1], FeatureShapeError) and "r3" in str(mixed[1])
    for a, b in zip(alone, (mixed[0], mixed[2]), strict=True):
        assert isinstance(b, TagPoses)
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
    # One robot's own settings ([robots.robot2.camera]): the shipped fleet's robots see different views
    # (a fleet trial found two copies of one robot, and no place to configure them apart).
    assert docs["robot2_camera"]["camera"]["start_frame"] == 30 and docs["robot2_camera"]["camera"]["fps"] == 10.0
    assert "start_frame" not in docs["robot1_camera"]["camera"] and all("robots" not in d for d in docs.values())
    with pytest.raises(ValueError, match="repeat"):
        FleetPlan(robots=["a", "a"], edge_workers=["w"])
    for extra, said in (
        ("[robots.robot3.camera]\nfps = 5\n", r"names \['robot3'\], not robots of the fleet"),
        ("[robots.robot1.slam]\nx = 1\n", r"may hold only common, robot_infer, camera, controller"),
        ("[robots.robot1]\ncamera = 5\n", r"holds tables .* not values: \['camera'\]"),
    ):
        bad = tmp_path / "bad.toml"
        bad.write_text((REPO / "deploy" / "fleet.toml").read_text() + extra)
        with pytest.raises(ValueError, match=said):
            fleet_configs(plan, tmp_path / "bad", bad)


def test_fleet_settings_refuse_an_empty_robot_list_and_maps_of_robots_not_served(tmp_path: Path) -> None:
    from pydantic import ValidationError

    from services.edge_infer.settings import EdgeInferSettings
    from services.slam.settings import SlamServiceSettings

    for settings in (EdgeInferSettings, SlamServiceSettings):
        with pytest.raises(ValidationError, match="at least 1 item"):
            settings(robot_id="r1", robots=[], run_dir=tmp_path)
    with pytest.raises(ValidationError, match=r"tag_maps for robots this edge does not serve: \['r9'\]"):
        EdgeInferSettings(robot_id="r1", robots=["r1", "r2"], tag_maps={"r9": tmp_path / "m.yaml"}, run_dir=tmp_path)
    assert EdgeInferSettings(robot_id="r1", robots="*", tag_maps={"r9": tmp_path / "m.yaml"}, run_dir=tmp_path)


class _Token:
    """What edge_infer reads of a liveliness sample."""

    def __init__(self, key: str, kind: object) -> None:
        self.key_expr, self.kind = key, kind


def test_a_liveliness_key_that_does_not_parse_is_counted_not_followed() -> None:
    import zenoh

    from services.edge_infer.service import _on_token
    from shared.runtime.guard import InputGuard

    guard, seen = InputGuard("edge_infer", log_every_secs=0.0), list[str]()
    up = down = seen.append
    _on_token(_Token(keys.edge_worker("fleet", "edge2"), zenoh.SampleKind.PUT), keys.worker_of, up, down, guard)  # type: ignore[arg-type]
    _on_token(_Token("splittag/@fleet/fleet/oops", zenoh.SampleKind.PUT), keys.worker_of, up, down, guard)  # type: ignore[arg-type]
    assert seen == ["edge2"]
    assert guard.stats()["rejected_by_reason"] == {"liveliness: ValueError": 1}
    guard.run("tag_poses", 10, lambda: None)
    guard.run("ground_truth", 10, lambda: None)
    guard.run("ground_truth", 10, lambda: None)
    assert guard.stats()["accepted"] == 3  # (slam's stats: what it took, by input)
    assert guard.stats()["accepted_by_input"] == {"tag_poses": 1, "ground_truth": 2}


def test_make_certs_writes_each_host_only_its_own_keys(tmp_path: Path) -> None:
    """`splittag fleet --make-certs`: one certificate per process, and per host a bundle with the CA's
    certificate and that host's identities alone (never ca.key, never another host's key); a host
    that runs its part from the full folder is warned about every key that is not its own."""
    from shared.tools.fleet import FleetPlan, foreign_keys, make_certs

    plan = FleetPlan(robots=["robot1", "robot2"], edge_workers=["edge1"], controller=True, certs=tmp_path / "c")
    names = make_certs(plan)
    assert set(names) == {
        "slam",
        "edge1",
        "robot1",
        "robot1-camera",
        "robot1-controller",
        "robot2",
        "robot2-camera",
        "robot2-controller",
        "operator",
    }
    hosts = tmp_path / "c" / "hosts"
    assert sorted(p.name for p in (hosts / "robot1").iterdir()) == [
        "ca.pem",
        "robot1-camera.key",
        "robot1-camera.pem",
        "robot1-controller.key",
        "robot1-controller.pem",
        "robot1.key",
        "robot1.pem",
    ]
    assert {p.name for p in (hosts / "edge").iterdir()} == {
        "ca.pem",
        *(f"{n}.{s}" for n in ("slam", "edge1", "operator") for s in ("pem", "key")),
    }
    warning = foreign_keys(plan, "robot1")
    assert warning and "ca" in warning[0] and "robot2" in warning[0] and "slam" in warning[0]
    assert foreign_keys(plan.model_copy(update={"certs": hosts / "robot1"}), "robot1") == []


def test_fleet_names_that_would_share_a_certificate_are_refused(tmp_path: Path) -> None:
    """Each process has its own certificate name: a robot called like a worker, slam, the operator or
    another robot's camera is refused, as is a bad name given to make-certs.sh or --make-certs without a
    certs folder."""
    import subprocess
    import sys

    from shared.tools.fleet import FleetPlan

    for robots, workers in (
        (["a", "edge1"], ["edge1"]),
        (["slam"], ["e"]),
        (["a", "a-camera"], ["e"]),
        (["r"], ["operator"]),
    ):
        with pytest.raises(ValueError, match="clash"):
            FleetPlan(robots=robots, edge_workers=workers)
    bad = subprocess.run(
        ["bash", str(Path(__file__).resolve().parents[1] / "deploy" / "make-certs.sh"), str(tmp_path / "c")],
        env={"SPLITTAG_CERT_NAMES": "robot1 ../evil", "PATH": "/usr/bin:/bin"},
        capture_output=True,
        text=True,
    )
    assert bad.returncode == 2 and "../evil is not a certificate name" in bad.stderr, bad.stderr
    config = tmp_path / "fleet.toml"
    config.write_text('[fleet]\nrobots = ["robot1"]\nedge_workers = ["edge1"]\n')
    out = subprocess.run(
        [sys.executable, "-m", "shared.tools.cli", "fleet", "--config", str(config), "--make-certs"],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert out.returncode == 2 and "no [fleet] certs folder" in out.stderr, out.stderr


def test_a_batch_runs_its_tail_in_bounded_chunks_and_a_frame_of_too_many_tags_is_refused() -> None:
    """A trial's three 200-tag Features took the edge to 4.9 GB in one tail pass: the tail now runs on
    at most TAIL_CHUNK_TAGS tags at a time (the same keypoints as one message at a time, chunks
    crossing messages), and a frame of more than MAX_TAGS_PER_FRAME tags is refused before any network."""
    from shared.model.runtime import load_split_net
    from shared.perception.split import (
        MAX_TAGS_PER_FRAME,
        TAIL_CHUNK_TAGS,
        EdgeInput,
        check_features,
        edge_batch,
        edge_step,
    )
    from shared.vision.tagmap import TagMapFile
    from shared.wire.cuts import CUTS, FeatureShapeError
    from shared.wire.messages import Features, TagPoses
    from tests.examples import example_messages

    base = example_messages()[Features.SCHEMA]
    assert isinstance(base, Features)
    rng = np.random.default_rng(1)
    k, per = 6, 7
    messages = []
    for robot in ("r1", "r2", "r3"):  # 21 tags: chunks of 16 cross the messages
        tags = [
            base.tags[0].model_copy(
                update={"tag_id": i, "tensor": np.maximum(rng.normal(0, 1, CUTS[k].shape), 0).astype(np.float16)}
            )
            for i in range(per)
        ]
        messages.append(base.model_copy(update={"robot_id": robot, "split_k": k, "codec": "fp16", "tags": tags}))
    assert 3 * per > TAIL_CHUNK_TAGS
    net = load_split_net(REPO / "models", "fp32")
    tag_map = TagMapFile(default_size_m=0.2)
    together = edge_batch([EdgeInput(m, 2, 1, 10, tag_map) for m in messages], net=net)
    for m, b in zip(messages, together, strict=True):
        a = edge_step(m, net=net, tag_map=tag_map, receive_nanos=2, previous_receive_nanos=1, payload_bytes=10)
        assert isinstance(b, TagPoses) and len(b.tags) == per
        for ta, tb in zip(a.tags, b.tags, strict=True):
            np.testing.assert_allclose(tb.keypoints_px, ta.keypoints_px, atol=1e-3)
    many = base.model_copy(update={"tags": [base.tags[0]] * (MAX_TAGS_PER_FRAME + 1)})
    with pytest.raises(FeatureShapeError, match=f"{MAX_TAGS_PER_FRAME + 1} tags in one frame"):
        check_features(many)
