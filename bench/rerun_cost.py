"""What Rerun logging costs the pipeline (goal: at most 5 % of its throughput).

Two measurements in one run:
1. CPU per frame of every logging call the services make (camera image + ground-truth keypoints,
   edge keypoints/quads/timings, SLAM pose/trajectory/map), timed in-process with process_time
   (Rerun's encoder and file-sink threads included), against the CPU the pipeline itself spends on a
   frame (robot + edge compute, median, measured in the A/B runs).
2. Throughput A/B: the whole pipeline (camera, robot_infer, edge_infer, slam) with Rerun off and on,
   interleaved off/on/off/on... so drift hits both arms alike; median fps per arm and their ratio.

    .venv/bin/python -m bench.rerun_cost [--pairs 3] [--window-secs 15] [--k 7]
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np

from bench.machine import cpu_label
from shared.runtime.sources import DemoSource
from shared.tools.launch import Monitor, attach_monitor, demo_tag_map, loopback_config, start_service, stop_services
from shared.transport.session import ZenohSettings, open_session, wait_for_liveliness
from shared.transport.split_client import query_split
from shared.vision.geometry import default_camera, make_pose
from shared.viz.recording import RerunSettings, RerunViz
from shared.wire import keys
from shared.wire.messages import HopTimings, LinkStamps, TagPose, TagPoses

ROBOT = "rrcost"
SERVICES = ("edge_infer", "robot_infer", "slam", "camera")


def logging_cpu_ms_per_frame(frames: int, image_every: int) -> dict[str, float]:
    """CPU ms per frame of each service's logging, on demo frames and 4-tag TagPoses."""
    cam = default_camera()
    source = DemoSource(n_frames=150, cache_dir=Path("runs/cache"))
    images = [f.image for _, f in zip(range(30), source.frames(), strict=False)]
    rng = np.random.default_rng(0)
    tags = [
        TagPose(
            tag_id=i,
            tag_size_m=0.16,
            keypoints_px=rng.uniform(0, 700, (16, 2)).astype(np.float32),
            corners_px=rng.uniform(0, 700, (4, 2)).astype(np.float32),
            camera_from_tag=make_pose(np.eye(3), [0.1 * i, 0, 1.5]),
            reprojection_error_px=0.3,
            alt_camera_from_tag=make_pose(np.eye(3), [0.1 * i, 0, 1.5]),
            alt_reprojection_error_px=2.0,
            tracked=False,
        )
        for i in range(4)
    ]
    out: dict[str, float] = {}
    with tempfile.TemporaryDirectory() as tmp:
        settings = RerunSettings(enabled=True, recording_id="cost", image_every=image_every)
        vizs = {s: RerunViz(settings, service=s, run_dir=Path(tmp)) for s in ("camera", "edge_infer", "slam")}
        positions = np.zeros((0, 3))
        cpu = {s: 0.0 for s in vizs}
        t_ns = time.time_ns()
        for i in range(frames):
            t_ns += 66_666_667
            c0 = time.process_time()
            vizs["camera"].image(t_ns, images[i % len(images)], cam, i)
            vizs["camera"].keypoints_gt(t_ns, [t.keypoints_px.astype(np.float64) for t in tags])
            c1 = time.process_time()
            msg = TagPoses(
                robot_id=ROBOT,
                seq=i,
                capture_nanos=t_ns,
                split_k=7,
                payload_bytes=1400,
                intrinsics=cam,
                link=LinkStamps(sent_nanos=t_ns, received_nanos=t_ns + 1_000_000, previous_received_nanos=0),
                timings=HopTimings(
                    robot_compute_secs=0.09, transport_secs=0.001, edge_compute_secs=0.002, capture_to_pose_secs=0.1
                ),
                tags=tags,
            )
            vizs["edge_infer"].tag_poses(msg)
            c2 = time.process_time()
            pose = make_pose(np.eye(3), [0.01 * i, 0.0, 0.0])
            positions = np.vstack([positions, pose[:3, 3]])
            vizs["slam"].camera_pose(t_ns, pose, cam)
            vizs["slam"].trajectory(t_ns, "world/trajectory", positions)
            if i % 30 == 0:
                vizs["slam"].tag_map(t_ns, {t.tag_id: (0.16, t.camera_from_tag) for t in tags})
            c3 = time.process_time()
            cpu["camera"] += c1 - c0
            cpu["edge_infer"] += c2 - c1
            cpu["slam"] += c3 - c2
        c0 = time.process_time()
        for v in vizs.values():
            v.close()  # flushing is part of the cost
        flush = time.process_time() - c0
    for s, total in cpu.items():
        out[s] = 1e3 * total / frames
    out["flush"] = 1e3 * flush / frames
    out["total"] = sum(out.values())
    return out


def throughput(args: argparse.Namespace, rerun: bool, tmp: Path) -> tuple[float, float, float]:
    """(fps, e2e p50 ms, robot+edge compute ms per frame) of one run with Rerun on or off."""
    cfg, topology = loopback_config(
        tmp, robot_id=ROBOT, rerun=rerun, image_every=args.image_every, fps=args.fps, split_k=args.k
    )
    services = [start_service(n, cfg, tmp) for n in SERVICES]
    try:
        session = open_session(ZenohSettings(mode="client", connect=[topology.robot_router]))
        monitor = Monitor(demo_tag_map())
        subs = attach_monitor(session, ROBOT, monitor)
        wait_for_liveliness(session, [keys.alive(ROBOT, s) for s in SERVICES], timeout_secs=120)
        query_split(session, ROBOT)
        time.sleep(args.settle_secs)
        start, t0 = len(monitor.records), time.monotonic()
        time.sleep(args.window_secs)
        recs = monitor.records[start:]
        elapsed = time.monotonic() - t0
        for s in subs:
            s.undeclare()
        session.close()
    finally:
        stop_services(services)
    e2e = [r["e2e_ms"] for r in recs]
    work = [r["robot_ms"] + r["edge_ms"] for r in recs]
    return len(recs) / elapsed, float(np.percentile(e2e, 50)), float(np.median(work))


def main() -> None:
    """Print both measurements."""
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--pairs", type=int, default=3)
    ap.add_argument("--window-secs", type=float, default=15.0)
    ap.add_argument("--settle-secs", type=float, default=3.0)
    ap.add_argument("--fps", type=float, default=15.0)
    ap.add_argument("--k", type=int, default=7)
    ap.add_argument("--image-every", type=int, default=5)
    ap.add_argument("--frames", type=int, default=300)
    args = ap.parse_args()
    print(f"CPU: {cpu_label()}", flush=True)

    cost = logging_cpu_ms_per_frame(args.frames, args.image_every)
    print(f"logging CPU per frame (image_every={args.image_every}, {args.frames} frames, ms):")
    print("  " + "  ".join(f"{k} {v:.3f}" for k, v in cost.items()))

    arms: dict[bool, list[tuple[float, float, float]]] = {False: [], True: []}
    with tempfile.TemporaryDirectory() as tmp:
        for i in range(args.pairs):
            for rerun in (False, True) if i % 2 == 0 else (True, False):
                run_dir = Path(tmp) / f"{i}-{int(rerun)}"
                run_dir.mkdir()
                result = throughput(args, rerun, run_dir)
                arms[rerun].append(result)
                print(f"  pair {i} rerun {'on ' if rerun else 'off'}: {result[0]:.2f} fps, e2e p50 {result[1]:.1f} ms")
    off = np.median([r[0] for r in arms[False]])
    on = np.median([r[0] for r in arms[True]])
    work = np.median([r[2] for r in arms[False]])
    print(
        f"k={args.k}, camera {args.fps} fps, {args.pairs} interleaved pairs x {args.window_secs} s: "
        f"median {off:.2f} fps off, {on:.2f} fps on -> throughput ratio {on / off:.3f}; "
        f"e2e p50 {np.median([r[1] for r in arms[False]]):.1f} / {np.median([r[1] for r in arms[True]]):.1f} ms"
    )
    print(
        f"logging {cost['total']:.2f} ms CPU per frame vs {work:.1f} ms of robot + edge compute per frame "
        f"= {100 * cost['total'] / work:.1f} %"
    )


if __name__ == "__main__":
    main()
