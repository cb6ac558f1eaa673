"""The launcher's live monitor stays bounded in a deployment that runs for days."""

from __future__ import annotations

from shared.tools.launch import Monitor
from shared.wire.messages import CameraPose, TagPoses, encode
from tests.examples import example_messages

EXAMPLES = example_messages()


def test_records_and_ground_truth_are_bounded() -> None:
    poses = EXAMPLES[TagPoses.SCHEMA]
    gt = EXAMPLES[CameraPose.SCHEMA]
    assert isinstance(poses, TagPoses) and isinstance(gt, CameraPose)
    monitor = Monitor(None, max_records=10, max_ground_truth=5)
    for seq in range(25):
        monitor.on_gt(encode(gt.model_copy(update={"seq": seq})))
        monitor.on_poses(encode(poses.model_copy(update={"seq": seq})))
    assert len(monitor.records) <= 10 and monitor.frames_total == 25
    assert [r["seq"] for r in monitor.records][-1] == 24  # the newest are kept
    assert sorted(monitor.gt) == [20, 21, 22, 23, 24]
    summary = monitor.summary()
    assert summary["frames_total"] == 25 and summary["frames"] == len(monitor.records)


def test_unbounded_by_default_for_benchmarks() -> None:
    poses = EXAMPLES[TagPoses.SCHEMA]
    assert isinstance(poses, TagPoses)
    monitor = Monitor(None)
    for seq in range(50):
        monitor.on_poses(encode(poses.model_copy(update={"seq": seq})))
    assert len(monitor.records) == 50  # benchmarks slice records by index
