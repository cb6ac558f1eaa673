"""Camera sources other than the demo scene: an image folder (+ TUM ground truth), a video file, V4L2;
and the camera service streaming them over a real Zenoh session, looping or stopping at the end."""

from __future__ import annotations

import itertools
import threading
from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np
import pytest

from services.camera.service import run as run_camera
from services.camera.settings import CameraSettings
from shared.runtime.sources import CaptureSource, FolderSource, SourceSizeError, VideoSource
from shared.transport.session import ZenohSettings, free_tcp_port, open_session
from shared.vision.camera import CameraIntrinsics
from shared.vision.geometry import GeometryError, camera_to_yaml, default_camera, make_pose
from shared.vision.tags import render_tag, to_uint8
from shared.vision.trajectory import read_tum, write_tum
from shared.wire import keys
from shared.wire.messages import CameraPose, Frame, FrameStamp, decode, encode

CAM = default_camera()


def _tag_image(i: int) -> np.ndarray:
    """A grey frame with tag i at a known pose (its id encodes the frame index)."""
    pose = make_pose(np.eye(3), [0.05 * i, -0.05, 1.5])
    canvas = np.full((CAM.height, CAM.width), 0.55, np.float32)
    h = CAM.matrix() @ np.column_stack([pose[:3, 0], pose[:3, 1], pose[:3, 3]])
    render_tag(canvas, tag_id=i, tag_size_m=0.2, tag_plane_to_image=h)
    return to_uint8(canvas)


def _folder(tmp: Path, n: int = 3) -> tuple[Path, Path, Path]:
    folder = tmp / "images"
    folder.mkdir()
    for i in range(n):
        cv2.imwrite(str(folder / f"{i:04d}.png"), _tag_image(i))
    info = tmp / "camera_info.yaml"
    info.write_text(camera_to_yaml(CAM))
    gt = tmp / "groundtruth.tum"
    write_tum(gt, [(float(i), make_pose(np.eye(3), [i, 0.0, 0.0])) for i in range(n)])
    return folder, info, gt


def test_folder_source_images_and_groundtruth(tmp_path: Path) -> None:
    folder, info, gt = _folder(tmp_path)
    frames = list(FolderSource(folder, info, gt).frames())
    assert [f.image.shape for f in frames] == [(CAM.height, CAM.width)] * 3
    assert np.array_equal(frames[1].image, _tag_image(1))
    assert [f.world_from_camera[0, 3] for f in frames if f.world_from_camera is not None] == [0.0, 1.0, 2.0]
    assert len(read_tum(gt)) == 3


def test_folder_source_skips_bad_images_and_checks_groundtruth(tmp_path: Path) -> None:
    folder, info, gt = _folder(tmp_path)
    cv2.imwrite(str(folder / "0005_small.png"), np.zeros((10, 10), np.uint8))
    with pytest.raises(GeometryError, match="4 images"):
        FolderSource(folder, info, gt)  # 3 poses for 4 images
    frames = list(FolderSource(folder, info).frames())
    assert len(frames) == 3  # the wrong-size image is skipped with a warning, the rest stream
    with pytest.raises(FileNotFoundError, match="no images"):
        FolderSource(tmp_path / "empty_does_not_exist", info)


def _video(tmp: Path, n: int, *, size: tuple[int, int] = (CAM.width, CAM.height), name: str = "clip.avi") -> Path:
    """An MJPG video of _tag_image(0..n-1) in colour at 15 fps (scaled to `size`)."""
    video = tmp / name
    writer = cv2.VideoWriter(str(video), cv2.VideoWriter.fourcc(*"MJPG"), 15.0, size)
    assert writer.isOpened(), "OpenCV cannot write MJPG here"
    for i in range(n):
        image = cv2.resize(_tag_image(i), size, interpolation=cv2.INTER_AREA)
        writer.write(cv2.cvtColor(image, cv2.COLOR_GRAY2BGR))
    writer.release()
    return video


def test_a_video_file_streams_grey_frames_in_its_own_time_with_ground_truth_matched_by_it(tmp_path: Path) -> None:
    """A video is a data set: each frame carries its own time (seconds from the video's first frame) and
    its place, ground truth in that time is matched within 20 ms, and a restarted camera seeks to its
    place instead of replaying the video (a trial's groundtruth was ignored, its restart replayed 0-49)."""
    info = tmp_path / "camera_info.yaml"
    info.write_text(camera_to_yaml(CAM))
    video = _video(tmp_path, 6)
    gt = tmp_path / "groundtruth.txt"  # every frame's pose but frame 4's, in the video's time
    write_tum(gt, [(i / 15.0, make_pose(np.eye(3), [float(i), 0.0, 0.0])) for i in range(6) if i != 4])
    source = VideoSource(video, info, gt)
    frames = list(source.frames())
    assert len(frames) == 6 and [f.index for f in frames] == list(range(6))
    assert all(f.image.shape == (CAM.height, CAM.width) and f.image.dtype == np.uint8 for f in frames)
    assert [f.stamp_nanos for f in frames] == [round(i * 1e9 / 15) for i in range(6)]
    assert [None if f.world_from_camera is None else f.world_from_camera[0, 3] for f in frames] == [0, 1, 2, 3, None, 5]
    assert source.span_nanos == 400_000_000 and source.identity == {"images": 6, "first": str(video)}
    later = list(source.frames(3))
    assert [f.index for f in later] == [3, 4, 5]
    assert [f.stamp_nanos for f in later] == [f.stamp_nanos for f in frames[3:]]
    assert all(np.array_equal(a.image, b.image) for a, b in zip(later, frames[3:], strict=True))
    assert VideoSource(video, info).frames().__next__().world_from_camera is None  # no ground truth given


def test_a_video_that_cannot_be_used_is_refused_at_once_saying_why(tmp_path: Path) -> None:
    """Refused when the source is made (before any Zenoh session: exit 2, no restart loop): frames of
    another size than the camera_info's (a trial's 640x480 video with a 1280x720 camera_info was resized
    silently and posed metres off), a file OpenCV cannot open (a trial's cut-short mp4 restarted the
    camera for the whole run), a folder, a missing file, ground truth in another clock."""
    from services.camera.service import check_source
    from shared.runtime.settings import ConfigurationError

    info = tmp_path / "camera_info.yaml"
    info.write_text(camera_to_yaml(CAM))
    small = _video(tmp_path, 2, size=(CAM.width // 2, CAM.height // 2), name="small.avi")
    with pytest.raises(GeometryError, match=f"are {CAM.width // 2}x{CAM.height // 2} but the camera_info says"):
        VideoSource(small, info)
    garbage = tmp_path / "cut.mp4"
    garbage.write_bytes(np.random.default_rng(0).integers(0, 256, 100_000, dtype=np.uint8).tobytes())
    with pytest.raises(GeometryError, match="not a video OpenCV can open"):
        VideoSource(garbage, info)
    with pytest.raises(FileNotFoundError, match="is a folder, not a video file"):
        VideoSource(tmp_path, info)
    with pytest.raises(FileNotFoundError, match="no such file"):
        VideoSource(tmp_path / "absent.avi", info)
    video = _video(tmp_path, 3)
    epoch = tmp_path / "epoch.txt"
    write_tum(epoch, [(1_700_000_000.0 + i / 15, np.eye(4)) for i in range(3)])
    with pytest.raises(GeometryError, match="in the video's time"):
        VideoSource(video, info, epoch)
    for path in (small, garbage, tmp_path, tmp_path / "absent.avi"):
        with pytest.raises(ConfigurationError, match="source video"):
            check_source(CameraSettings(source="video", path=str(path), camera_info=info))
    assert isinstance(check_source(CameraSettings(source="video", path=str(video), camera_info=info)), VideoSource)
    with pytest.raises(ConfigurationError, match="groundtruth: a v4l2 source"):
        check_source(CameraSettings(source="v4l2", path="0", camera_info=info, groundtruth=epoch))


def test_v4l2_source_when_a_device_exists(tmp_path: Path) -> None:
    devices = sorted(Path("/dev").glob("video*"))
    if not devices:
        pytest.skip("no V4L2 device (/dev/video*) on this machine")
    probe = cv2.VideoCapture(str(devices[0]))
    probe.set(cv2.CAP_PROP_FRAME_WIDTH, CAM.width)
    probe.set(cv2.CAP_PROP_FRAME_HEIGHT, CAM.height)
    ok, first = probe.read()
    probe.release()
    if not ok:
        pytest.skip(f"{devices[0]} gives no frame")
    height, width = first.shape[:2]  # (a device that cannot give CAM's size: at its own, which it is asked for)
    camera = CAM.model_copy(update={"width": width, "height": height})
    info = tmp_path / "camera_info.yaml"
    info.write_text(camera_to_yaml(camera))
    frame = next(iter(CaptureSource(str(devices[0]), info).frames()))
    assert frame.image.shape == (height, width)


def test_a_live_source_of_another_size_is_refused_at_its_first_frame(tmp_path: Path) -> None:
    """A device or stream is asked for the camera_info's size; one that gives another is refused, not
    resized (the intrinsics would no longer hold), and the camera service makes that a configuration
    error (exit 2, no restart loop). A local file given as a stream stands in for the device."""
    from services.camera.service import _frames_from
    from shared.runtime.settings import ConfigurationError

    info = tmp_path / "camera_info.yaml"
    info.write_text(camera_to_yaml(CAM))
    small = _video(tmp_path, 2, size=(CAM.width // 2, CAM.height // 2))
    with pytest.raises(SourceSizeError, match=f"gives {CAM.width // 2}x{CAM.height // 2} frames but the camera_info"):
        next(iter(CaptureSource(str(small), info).frames()))
    with pytest.raises(ConfigurationError, match=r"source: .* gives"):
        next(iter(_frames_from(CaptureSource(str(small), info), 0)))
    right = _video(tmp_path, 2, name="right.avi")
    assert len(list(CaptureSource(str(right), info).frames())) == 2


def _stream(
    settings: CameraSettings,
    key_prefix: str,
    expect: int,
    stamps: list[FrameStamp] | None = None,
    *,
    expect_gts: int = 0,
) -> tuple[list[Frame], list[CameraPose], int]:
    """Run the camera service into a hub session; collect its frames, ground truth (and FrameStamps
    into `stamps`, waiting for `expect` of them too, when given), waiting for `expect` frames and
    `expect_gts` ground-truth poses (the last pose can arrive after the last frame)."""
    port = free_tcp_port()
    hub = open_session(ZenohSettings(mode="peer", listen=[f"tcp/127.0.0.1:{port}"]))
    frames: list[Frame] = []
    gts: list[CameraPose] = []
    got = threading.Event()
    got_stamps = threading.Event()
    got_gts = threading.Event()
    if stamps is None:
        got_stamps.set()
    if expect_gts == 0:
        got_gts.set()

    def on_gt(sample: object) -> None:
        gts.append(decode(sample.payload.to_bytes(), CameraPose))  # type: ignore[attr-defined]
        if len(gts) >= expect_gts:
            got_gts.set()

    def on_stamp(sample: object) -> None:
        assert stamps is not None
        stamps.append(decode(sample.payload.to_bytes(), FrameStamp))  # type: ignore[attr-defined]
        if len(stamps) >= expect:
            got_stamps.set()

    def on_frame(sample: object) -> None:
        frames.append(decode(sample.payload.to_bytes(), Frame))  # type: ignore[attr-defined]
        if len(frames) >= expect:
            got.set()

    subs = [
        hub.declare_subscriber(keys.frames(key_prefix), on_frame),
        hub.declare_subscriber(keys.ground_truth(key_prefix), on_gt),
        hub.declare_subscriber(keys.frame_stamp(key_prefix), on_stamp),
    ]
    cam_session = open_session(ZenohSettings(mode="client", connect=[f"tcp/127.0.0.1:{port}"]))
    try:
        published = run_camera(
            settings.model_copy(update={"wait_for": []}), session=cam_session, stop=threading.Event()
        )
        assert got.wait(10), f"received {len(frames)} of {expect} frames"
        assert got_stamps.wait(10), f"received {len(stamps or [])} of {expect} frame stamps"
        assert got_gts.wait(10), f"received {len(gts)} of {expect_gts} ground-truth poses"
    finally:
        cam_session.close()
        for s in subs:
            s.undeclare()
        hub.close()
    return frames, gts, published


def _looping_folder(tmp_path: Path, robot_id: str, *, max_frames: int, start_frame: int = 0) -> CameraSettings:
    """Camera settings streaming _folder's three frames in a loop at 50 fps."""
    folder, info, gt = _folder(tmp_path)
    return CameraSettings(
        robot_id=robot_id,
        source="folder",
        path=str(folder),
        camera_info=info,
        groundtruth=gt,
        fps=50.0,
        loop=True,
        max_frames=max_frames,
        start_frame=start_frame,
        run_dir=tmp_path,
    )


def test_camera_service_streams_a_folder_and_loops(tmp_path: Path) -> None:
    settings = _looping_folder(tmp_path, "src1", max_frames=7)
    frames, gts, published = _stream(settings, "src1", 7, expect_gts=7)
    assert published == 7
    # each pass is a camera session of its own: seq starts again (slam does not carry its motion prior
    # across the wrap, which a data-set trial found bending the poses around every wrap)
    assert [f.seq for f in frames] == [0, 1, 2, 0, 1, 2, 0]
    assert all(a.capture_nanos < b.capture_nanos for a, b in itertools.pairwise(frames))
    assert np.array_equal(frames[4].image, _tag_image(1))  # 0 1 2 0 1 2 0: looped
    assert [g.world_from_camera[0, 3] for g in gts] == [0, 1, 2, 0, 1, 2, 0]
    assert frames[0].intrinsics == CAM


def test_only_the_demo_scenes_closed_loop_goes_on_as_one_camera_session() -> None:
    """The demo path is a closed loop (frame 149 -> 0 is an ordinary step): its passes keep counting seq,
    which slam's motion prior and robot_infer's tracker then carry across (review). A folder or video
    jumps back to its start: a new session each pass (the test above)."""
    from shared.runtime.sources import DemoSource, demo_trajectory

    assert DemoSource.continuous_loop and not getattr(FolderSource, "continuous_loop", False)
    path = demo_trajectory(150)
    step = np.linalg.norm(path[0][:3, 3] - path[-1][:3, 3])
    assert step < 2 * np.median([np.linalg.norm(a[:3, 3] - b[:3, 3]) for a, b in itertools.pairwise(path)])


def test_camera_service_starts_later_in_the_source_and_refuses_a_start_past_its_end(tmp_path: Path) -> None:
    """`start_frame` (a fleet's robots at different places of one source) skips the first pass's first
    frames only; a start past the source's end is an error, not a camera that loops publishing nothing."""
    settings = _looping_folder(tmp_path, "src3", max_frames=4, start_frame=2)
    frames, gts, published = _stream(settings, "src3", 4, expect_gts=4)
    assert published == 4 and [f.seq for f in frames] == [0, 0, 1, 2]
    assert [g.world_from_camera[0, 3] for g in gts] == [2, 0, 1, 2]  # 2, then the whole source again
    session = open_session(ZenohSettings(mode="peer", listen=[], multicast_scouting=False))
    try:
        with pytest.raises(ValueError, match="start_frame 3 is past the source's last frame"):
            run_camera(
                settings.model_copy(update={"start_frame": 3, "wait_for": []}), session=session, stop=threading.Event()
            )
    finally:
        session.close()


def test_camera_service_stops_at_the_end_of_a_video(tmp_path: Path) -> None:
    info = tmp_path / "camera_info.yaml"
    info.write_text(camera_to_yaml(CAM))
    video = tmp_path / "clip.avi"
    writer = cv2.VideoWriter(str(video), cv2.VideoWriter.fourcc(*"MJPG"), 15.0, (CAM.width, CAM.height))
    for i in range(4):
        writer.write(cv2.cvtColor(_tag_image(i), cv2.COLOR_GRAY2BGR))
    writer.release()
    settings = CameraSettings(
        robot_id="src2", source="video", path=str(video), camera_info=info, fps=50.0, loop=False, run_dir=tmp_path
    )
    frames, gts, published = _stream(settings, "src2", 4)
    assert published == 4 and len(frames) == 4 and not gts


def test_camera_settings_need_camera_info_for_files(tmp_path: Path) -> None:
    from services.camera.service import make_source

    with pytest.raises(ValueError, match="camera_info"):
        make_source(CameraSettings(source="folder", path=str(tmp_path)))


def test_folder_source_reads_rgb_txt_stamps_and_associates_ground_truth_by_time(tmp_path: Path) -> None:
    """A TUM data set: rgb.txt beside rgb/ lists the images (its order, not the file names'), each frame
    carries its time; ground truth at another rate is matched to the nearest stamp within 20 ms."""
    root = tmp_path / "dataset"
    (root / "rgb").mkdir(parents=True)
    for i in range(3):
        cv2.imwrite(str(root / "rgb" / f"{i}.png"), _tag_image(i))
    (root / "rgb.txt").write_text(
        "# color images\n# timestamp filename\n1305031102.175304 rgb/2.png\n1305031102.211214 rgb/0.png\n"
        "1305031102.243211 rgb/1.png\n"
    )
    info = tmp_path / "camera_info.yaml"
    info.write_text(camera_to_yaml(CAM))
    gt = tmp_path / "groundtruth.txt"  # 100 Hz, and nothing near the last image
    write_tum(gt, [(1305031102.17 + 0.01 * j, make_pose(np.eye(3), [float(j), 0.0, 0.0])) for j in range(6)])
    frames = list(FolderSource(root / "rgb", info, gt).frames())
    assert [f.stamp_nanos for f in frames] == [
        1_305_031_102_175_304_000,
        1_305_031_102_211_214_000,
        1_305_031_102_243_211_000,
    ]
    assert np.array_equal(frames[0].image, _tag_image(2))
    assert [None if f.world_from_camera is None else f.world_from_camera[0, 3] for f in frames] == [1.0, 4.0, None]
    assert all(f.stamp_nanos is None for f in FolderSource(_folder(tmp_path)[0], info).frames())


def test_folder_source_refuses_a_bad_rgb_txt_with_the_line(tmp_path: Path) -> None:
    info = tmp_path / "camera_info.yaml"
    info.write_text(camera_to_yaml(CAM))
    folder = tmp_path / "imgs"
    folder.mkdir()
    cv2.imwrite(str(folder / "a.png"), _tag_image(0))
    for text, why in (
        ("1.0 a.png extra\n", "rgb.txt:1: expected 'timestamp filename'"),
        ("# c\nnan a.png\n", "rgb.txt:2: timestamp 'nan' must be"),
        ("t a.png\n", "timestamp 't' is not a number"),
        ("1e400 a.png\n", "timestamp '1e400' must be"),
    ):
        (folder / "rgb.txt").write_text(text)
        with pytest.raises(GeometryError, match=why):
            FolderSource(folder, info)
    (folder / "rgb.txt").write_text("1.0 a.png\n2.0 missing.png\n")
    with pytest.raises(FileNotFoundError, match=r"1 missing image, e\.g\."):
        FolderSource(folder, info)


def test_camera_service_sends_each_frames_data_set_time(tmp_path: Path) -> None:
    """The camera publishes a FrameStamp per frame of a folder with rgb.txt: the same seq and capture
    time as the Frame (so slam can pair them), and the data set's time."""
    folder, info, _ = _folder(tmp_path)
    listed = [1_305_031_102_175_304_000, 1_305_031_102_211_214_000, 1_305_031_102_243_211_000]
    (folder / "rgb.txt").write_text(
        "".join(f"{t // 10**9}.{t % 10**9:09d} {i:04d}.png\n" for i, t in enumerate(listed))
    )
    stamps: list[FrameStamp] = []
    settings = CameraSettings(
        robot_id="src3", source="folder", path=str(folder), camera_info=info, fps=50.0, loop=False, run_dir=tmp_path
    )
    frames, _, published = _stream(settings, "src3", 3, stamps)
    assert published == 3
    by_seq = {s.seq: s for s in stamps}
    assert [(by_seq[f.seq].capture_nanos, by_seq[f.seq].source_stamp_nanos) for f in frames] == [
        (f.capture_nanos, t) for f, t in zip(frames, listed, strict=True)
    ]


def test_a_folder_whose_images_are_not_the_camera_infos_size_is_a_configuration_error(tmp_path: Path) -> None:
    """A camera_info of another size than the images: one line at start-up (the service would skip every
    image and crash-loop on 'no frames'); a folder whose first image is no image likewise."""
    from services.camera.service import check_source
    from shared.runtime.settings import ConfigurationError

    folder, _, _ = _folder(tmp_path)
    big = tmp_path / "camera_info_1080p.yaml"
    big.write_text(camera_to_yaml(CAM.model_copy(update={"width": 1920, "height": 1080})))
    with pytest.raises(ConfigurationError, match=r"0000.png is 1280x720 but the camera_info says 1920x1080"):
        check_source(CameraSettings(source="folder", path=str(folder), camera_info=big))
    (folder / "0000.png").write_bytes(b"not a png")
    with pytest.raises(ConfigurationError, match="not an image OpenCV can read"):
        check_source(CameraSettings(source="folder", path=str(folder), camera_info=tmp_path / "camera_info.yaml"))


def test_ground_truth_from_another_clock_is_refused_and_a_partial_match_is_warned(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """Ground truth whose stamps meet no image of rgb.txt (another recording, or shifted by 0.5 s) is
    an error naming both spans, not a run that silently writes no groundtruth.tum; a partial match
    says how many images go without truth."""
    root = tmp_path / "dataset"
    (root / "rgb").mkdir(parents=True)
    for i in range(3):
        cv2.imwrite(str(root / "rgb" / f"{i}.png"), _tag_image(i))
    (root / "rgb.txt").write_text("".join(f"{100 + i / 10:.6f} rgb/{i}.png\n" for i in range(3)))
    info = tmp_path / "camera_info.yaml"
    info.write_text(camera_to_yaml(CAM))
    gt = tmp_path / "groundtruth.txt"
    write_tum(gt, [(100.5 + i / 10, make_pose(np.eye(3), [float(i), 0.0, 0.0])) for i in range(3)])
    with pytest.raises(GeometryError, match=r"none of its 3 poses is within 20 ms .*images 100\.000000-100\.200000"):
        FolderSource(root / "rgb", info, gt)
    write_tum(gt, [(100.0 + i / 10, make_pose(np.eye(3), [float(i), 0.0, 0.0])) for i in range(2)])
    with caplog.at_level("WARNING"):
        frames = list(FolderSource(root / "rgb", info, gt).frames())
    assert [f.world_from_camera is not None for f in frames] == [True, True, False]
    assert "1 of 3 images have no ground-truth pose" in caplog.text


def test_a_folder_plays_once_by_default_and_a_looped_one_keeps_its_time_going_forward(tmp_path: Path) -> None:
    """`loop` unset loops only the demo scene: a data set replayed in a loop folds its trajectory onto
    itself. Looped on purpose, each new pass of a stamped folder is shifted by the pass's span (last -
    first + one frame period), so the data-set time slam writes never runs backwards."""
    assert CameraSettings().loops and not CameraSettings(source="folder").loops
    assert CameraSettings(source="folder", loop=True).loops and not CameraSettings(loop=False).loops
    folder, info, _ = _folder(tmp_path)
    listed = [1_000_000_000, 1_100_000_000, 1_200_000_000]
    (folder / "rgb.txt").write_text("".join(f"{t / 1e9:.6f} {i:04d}.png\n" for i, t in enumerate(listed)))
    once = CameraSettings(robot_id="src4", source="folder", path=str(folder), camera_info=info, fps=50.0)
    _, _, published = _stream(once.model_copy(update={"run_dir": tmp_path}), "src4", 3)
    assert published == 3  # ended with the folder
    stamps: list[FrameStamp] = []
    looped = once.model_copy(update={"loop": True, "max_frames": 7, "run_dir": tmp_path})
    _, _, published = _stream(looped, "src4", 7, stamps)
    assert published == 7
    span = 300_000_000  # 0.2 s of stamps + one 0.1 s period
    assert [s.source_stamp_nanos for s in sorted(stamps, key=lambda s: s.capture_nanos)] == [
        *listed,
        *(t + span for t in listed),
        listed[0] + 2 * span,
    ]


def test_a_looped_folders_span_is_its_time_span_whatever_rgb_txts_order() -> None:
    """rgb.txt lists images in its own order; a pass's span is latest - earliest stamp + one period."""
    source = FolderSource.__new__(FolderSource)
    source.stamps_nanos = [1_200, 1_000, 1_100]
    assert source.span_nanos == 300
    source.stamps_nanos = None
    assert source.span_nanos is None


def _demo_source(cache_dir: str, camera_json: str) -> int:
    from shared.runtime.sources import DemoSource

    DemoSource(n_frames=3, cache_dir=Path(cache_dir), camera=CameraIntrinsics.model_validate_json(camera_json))
    return 0


def test_demo_cameras_starting_together_render_the_cache_once(tmp_path: Path) -> None:
    """A fleet's cameras start together on a fresh clone: one renders the demo scene's cache while the
    other waits for it (a lock file), so neither trips over the other's files (one camera exited when
    both wrote the same temporary file: found by a fresh-clone trial). Here the test holds the lock:
    nothing renders until it lets go; then two cameras at once both get every frame."""
    import fcntl
    import multiprocessing

    from shared.runtime.sources import DemoSource

    small = type(CAM).model_validate(
        CAM.model_dump() | {"width": 160, "height": 120, "fx": 130.0, "fy": 130.0, "cx": 79.5, "cy": 59.5}
    )
    folder = DemoSource.cache_folder(tmp_path, n_frames=3, camera=small)
    folder.mkdir(parents=True)
    ctx = multiprocessing.get_context("spawn")
    with ctx.Pool(2) as pool, open(folder / ".render.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        jobs = [pool.apply_async(_demo_source, (str(tmp_path), small.model_dump_json())) for _ in range(2)]
        jobs[0].wait(8)
        assert not jobs[0].ready() and not list(folder.glob("*.png")), "a camera rendered past the lock"
        fcntl.flock(lock, fcntl.LOCK_UN)
        assert [j.get(120) for j in jobs] == [0, 0]
    assert sorted(p.name for p in folder.glob("*.png")) == ["00000.png", "00001.png", "00002.png"]
    assert not list(folder.glob("*tmp*")) and (folder / "scene.json").is_file()


def test_the_demo_source_serves_its_renders_decoded_once(tmp_path: Path) -> None:
    """The demo's renders are decoded once into a raw file that every later run reads: each frame is the
    PNG's pixels exactly, read-only (the camera only encodes it), without a decode per frame; a decoded
    file of the wrong size (a copy cut short) or older than a render is rebuilt, not read, and what a
    camera killed while writing it left is removed."""
    import cv2

    from shared.runtime.sources import DemoSource

    small = type(CAM).model_validate(
        CAM.model_dump() | {"width": 160, "height": 120, "fx": 130.0, "fy": 130.0, "cx": 79.5, "cy": 59.5}
    )
    source = DemoSource(n_frames=3, cache_dir=tmp_path, camera=small)
    decoded = source.cache / "decoded-3x120x160.u8"
    assert decoded.stat().st_size == 3 * 120 * 160
    frames = list(source.frames())
    for i, frame in enumerate(frames):
        png = cv2.imread(str(source.cache / f"{i:05d}.png"), cv2.IMREAD_GRAYSCALE)
        assert png is not None
        assert type(frame.image) is np.ndarray and frame.image.flags.c_contiguous and not frame.image.flags.writeable
        assert frame.image.shape == (120, 160) and np.array_equal(frame.image, png)
    assert len({f.image.tobytes() for f in frames}) == 3  # three different views, not one frame thrice
    decoded.write_bytes(decoded.read_bytes()[:30000])  # cut short: a running camera says so, a new one rebuilds
    with pytest.raises(OSError, match="cut short"):
        list(source.frames())
    again = DemoSource(n_frames=3, cache_dir=tmp_path, camera=small)
    assert decoded.stat().st_size == 3 * 120 * 160
    assert all(np.array_equal(a.image, b.image) for a, b in zip(frames, again.frames(), strict=True))
    # a render made again (here: another picture) after the decoded file: the file follows it
    import os

    flipped = np.ascontiguousarray(frames[1].image[::-1])
    cv2.imwrite(str(source.cache / "00001.png"), flipped)
    made = decoded.stat().st_mtime_ns
    os.utime(source.cache / "00001.png", ns=(made + 10**9, made + 10**9))
    (source.cache / "decoded-3x120x160.u8.tmp.99999").write_bytes(b"left by a killed camera")
    redone = list(DemoSource(n_frames=3, cache_dir=tmp_path, camera=small).frames())
    assert np.array_equal(redone[1].image, flipped) and np.array_equal(redone[0].image, frames[0].image)
    assert not list(source.cache.glob("*tmp*"))


def test_a_damaged_demo_render_is_named_not_sent(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    """A render that no longer reads (a disk error, a file cut short) or is not the camera's size: no
    decoded file is made from it (said once), and the frame is refused by name, never sent as garbage."""
    from shared.runtime.sources import DemoSource

    small = type(CAM).model_validate(
        CAM.model_dump() | {"width": 160, "height": 120, "fx": 130.0, "fy": 130.0, "cx": 79.5, "cy": 59.5}
    )
    cache = DemoSource.cache_folder(tmp_path, n_frames=3, camera=small)
    DemoSource(n_frames=3, cache_dir=tmp_path, camera=small)
    for damage, error, what in (
        (b"not a png", OSError, "demo cache frame 1 unreadable"),
        (cv2.imencode(".png", np.zeros((60, 80), np.uint8))[1].tobytes(), ValueError, "demo cache frame 1 is 80x60"),
    ):
        (cache / "decoded-3x120x160.u8").unlink(missing_ok=True)
        (cache / "00001.png").write_bytes(damage)
        caplog.clear()
        source = DemoSource(n_frames=3, cache_dir=tmp_path, camera=small)
        assert "decoded per frame" in caplog.text and what in caplog.text
        assert not (cache / "decoded-3x120x160.u8").exists() and not list(cache.glob("*tmp*"))
        frames = source.frames()
        assert next(frames).image.shape == (120, 160)
        with pytest.raises(error, match=what):
            next(frames)


def test_the_camera_says_by_its_exit_code_whether_its_source_ended(tmp_path: Path) -> None:
    """A source that ended (the run is complete) exits SOURCE_ENDED_EXIT; a camera stopped by a signal
    exits 0, which the launcher, had it not asked, restarts: a trial's SIGTERM to the demo camera was
    read as a source that ended and stopped the whole run."""
    import os
    import signal
    import subprocess
    import sys

    from shared.runtime.settings import SOURCE_ENDED_EXIT
    from shared.transport.session import wait_for_liveliness
    from tests.procs import REPO

    folder, info, _ = _folder(tmp_path)
    port = free_tcp_port()
    hub = open_session(ZenohSettings(mode="peer", listen=[f"tcp/127.0.0.1:{port}"]))
    env = {
        **os.environ,
        "SPLITTAG_CAMERA_ROBOT_ID": "exit1",
        "SPLITTAG_CAMERA_SOURCE": "folder",
        "SPLITTAG_CAMERA_PATH": str(folder),
        "SPLITTAG_CAMERA_CAMERA_INFO": str(info),
        "SPLITTAG_CAMERA_FPS": "20",
        "SPLITTAG_CAMERA_WAIT_FOR": "[]",
        "SPLITTAG_CAMERA_RUN_DIR": str(tmp_path),
        "SPLITTAG_CAMERA_ZENOH__MODE": "client",
        "SPLITTAG_CAMERA_ZENOH__CONNECT": f'["tcp/127.0.0.1:{port}"]',
    }
    camera = [sys.executable, "-m", "services.camera"]
    try:
        ended = subprocess.run(camera, cwd=REPO, env=env, capture_output=True, text=True, timeout=120)
        assert ended.returncode == SOURCE_ENDED_EXIT, ended.stderr
        looping = subprocess.Popen(
            camera, cwd=REPO, env={**env, "SPLITTAG_CAMERA_LOOP": "true"}, stderr=subprocess.PIPE
        )
        try:
            wait_for_liveliness(hub, [keys.alive("exit1", "camera")], timeout_secs=60)  # streaming
            looping.send_signal(signal.SIGTERM)
            _, err = looping.communicate(timeout=60)
            assert looping.returncode == 0, err.decode(errors="replace")
        finally:
            if looping.poll() is None:
                looping.kill()
                looping.wait()
    finally:
        hub.close()


def test_a_restarted_camera_goes_on_with_its_data_set(tmp_path: Path) -> None:
    """A folder camera the run's launcher restarts goes on from the next image of its data set, not from
    the first again (a trial's restart made trajectory.tum jump back in time: 220 rows for 150 stamps).
    The first camera stops after two images (max_frames, as a crash would); the second sends the third."""
    import os

    settings = _looping_folder(tmp_path, "resume1", max_frames=2).model_copy(update={"loop": False})
    (tmp_path / "launcher.pid").write_text(f"{os.getppid()}\n")  # this process plays the run's launcher's child
    first, _, published = _stream(settings, "resume1", 2)
    assert published == 2 and np.array_equal(first[1].image, _tag_image(1))
    again, gts, published = _stream(settings.model_copy(update={"max_frames": 0}), "resume1", 1, expect_gts=1)
    assert published == 3 and np.array_equal(again[0].image, _tag_image(2))  # the run's count
    assert gts[0].world_from_camera[0, 3] == 2.0  # its own ground truth
    assert again[0].seq == 0  # a new camera session for slam, as any camera restart
    (tmp_path / "launcher.pid").unlink()  # a camera started by hand beside the run plays it all
    alone, _, published = _stream(settings.model_copy(update={"max_frames": 0}), "resume1", 3)
    assert published == 3 and np.array_equal(alone[0].image, _tag_image(0))


def test_a_restarted_video_camera_goes_on_from_its_place_in_the_video(tmp_path: Path) -> None:
    """As a folder's: the run's restarted video camera seeks to the next frame (a trial's killed camera
    replayed frames 0-49, so trajectory.tum went back in time), its frames stamped in the video's time."""
    import os

    info = tmp_path / "camera_info.yaml"
    info.write_text(camera_to_yaml(CAM))
    video = _video(tmp_path, 4)
    settings = CameraSettings(
        robot_id="resume4", source="video", path=str(video), camera_info=info, fps=50.0, loop=False,
        run_dir=tmp_path, max_frames=2,
    )  # fmt: skip
    (tmp_path / "launcher.pid").write_text(f"{os.getppid()}\n")  # this process plays the run's launcher's child
    first, _, published = _stream(settings, "resume4", 2)
    assert published == 2
    stamps: list[FrameStamp] = []
    again, _, published = _stream(settings.model_copy(update={"max_frames": 0}), "resume4", 2, stamps)
    assert published == 4 and [f.seq for f in again] == [0, 1]
    assert [s.source_stamp_nanos for s in stamps] == [round(i * 1e9 / 15) for i in (2, 3)]
    frames = list(VideoSource(video, info).frames())
    assert np.array_equal(again[0].image, frames[2].image) and np.array_equal(first[1].image, frames[1].image)


def test_a_video_camera_restarted_after_its_pass_ends_at_once_and_a_start_past_its_end_is_refused(
    tmp_path: Path,
) -> None:
    """A video camera restarted once its pass was played (killed while waiting for the last poses) ends
    at once, as a folder's does, instead of failing 'the source produced no frames' on every restart
    (review); a start_frame past the video's end says so; a looping video's stamps never go back."""
    import os

    from services.camera.service import SourceProgress

    info = tmp_path / "camera_info.yaml"
    info.write_text(camera_to_yaml(CAM))
    video = _video(tmp_path, 4)
    settings = CameraSettings(
        robot_id="resume5", source="video", path=str(video), camera_info=info, fps=50.0, loop=False,
        run_dir=tmp_path, wait_for=[],
    )  # fmt: skip
    (tmp_path / "launcher.pid").write_text(f"{os.getppid()}\n")
    SourceProgress.of_run(settings, VideoSource(video, info)).write(0, 4, 4)  # the pass was played
    alone = open_session(ZenohSettings(mode="peer", listen=[], multicast_scouting=False))
    try:
        assert run_camera(settings, session=alone, stop=threading.Event()) == 4
        (tmp_path / "launcher.pid").unlink()
        with pytest.raises(ValueError, match="start_frame 4 is past the source's last frame"):
            run_camera(settings.model_copy(update={"start_frame": 4}), session=alone, stop=threading.Event())
    finally:
        alone.close()
    stamps: list[FrameStamp] = []
    looping = CameraSettings(
        robot_id="loop5", source="video", path=str(video), camera_info=info, fps=50.0, loop=True, max_frames=9,
        run_dir=tmp_path,
    )  # fmt: skip
    _stream(looping, "loop5", 9, stamps)
    got = [s.source_stamp_nanos for s in stamps]
    assert all(abs(a - i * 1e9 / 15) <= 2 for i, a in enumerate(got)), got  # 4 frames a pass, 1/15 s apart, on


def test_a_restarted_camera_counts_images_by_their_place_in_the_listing(tmp_path: Path) -> None:
    """A data set with an unreadable image: the progress counts places in the listing, not images read,
    so a camera restarted after the whole pass ends at once instead of skipping everything and failing
    ('start_frame past the end') on every restart (a review); max_frames counts the run's frames."""
    import os

    folder, info, _ = _folder(tmp_path, n=4)
    (folder / "0001.png").write_bytes(b"not an image")  # unreadable: skipped (said in the log)
    (tmp_path / "groundtruth.tum").unlink()
    (tmp_path / "launcher.pid").write_text(f"{os.getppid()}\n")
    settings = CameraSettings(
        robot_id="resume2", source="folder", path=str(folder), camera_info=info, fps=50.0, loop=False, run_dir=tmp_path
    )
    frames, _, published = _stream(settings, "resume2", 3)
    assert published == 3 and np.array_equal(frames[1].image, _tag_image(2))
    alone = open_session(ZenohSettings(mode="peer"))  # nobody listens: the camera ends before sending
    try:
        again = run_camera(settings.model_copy(update={"wait_for": []}), session=alone, stop=threading.Event())
        assert again == 3  # the pass was complete: the source ends at once, the run's count kept
        capped = settings.model_copy(update={"robot_id": "resume3", "max_frames": 2})
        _, _, published = _stream(capped, "resume3", 2)
        assert published == 2
        assert run_camera(capped.model_copy(update={"wait_for": []}), session=alone, stop=threading.Event()) == 2
    finally:
        alone.close()


def test_a_progress_file_that_is_not_this_data_sets_is_ignored(tmp_path: Path) -> None:
    """The progress a restarted camera reads is refused, and the data set played from its start, when it
    is damaged or names another listing (another folder, images added): never a crash, never a skip."""
    from services.camera.service import SourceProgress

    settings = _looping_folder(tmp_path, "prog1", max_frames=0)
    assert settings.camera_info is not None
    source = FolderSource(Path(settings.path), settings.camera_info, settings.groundtruth)
    progress = SourceProgress.of_run(settings, source)
    progress.write(1, 2, 5)
    assert progress.read() == (1, 2, 5)
    for damaged in ("", "{", "[]", '{"images": 3}', progress.path.read_text().replace('"passes": 1', '"passes": "x"')):
        progress.path.write_text(damaged)
        assert progress.read() is None, damaged
    progress.write(1, 2, 5)
    other = SourceProgress(progress.path, {"images": 2, "first": str(source.files[0])})  # a listing of two images
    assert other.read() is None


def _run_paced(
    tmp_path: Path, robot: str, *, n: int, fps: float, timeout_secs: float, delay_secs: Callable[[int], float | None]
) -> tuple[int, list[tuple[int, float]], dict[int, float], float]:
    """Run the camera with `pace = "poses"` on _folder's n frames against a stand-in pipeline that answers
    frame seq with its TagPoses `delay_secs(seq)` after it came (None: never). Returns what the camera
    published, each frame's (seq, arrival), each answer's time by seq, and when the camera ended."""
    import time

    from tests.examples import injected_tag_poses

    folder, info, _ = _folder(tmp_path, n=n)
    settings = CameraSettings(
        robot_id=robot,
        source="folder",
        path=str(folder),
        camera_info=info,
        fps=fps,
        pace="poses",
        poses_timeout_secs=timeout_secs,
        run_dir=tmp_path,
        wait_for=[],
    )
    port = free_tcp_port()
    hub = open_session(ZenohSettings(mode="peer", listen=[f"tcp/127.0.0.1:{port}"]))
    arrived: list[tuple[int, float]] = []
    answered: dict[int, float] = {}
    answers: list[threading.Timer] = []

    def answer(frame: Frame) -> None:
        answered[frame.seq] = time.monotonic()
        hub.put(keys.tag_poses(robot), injected_tag_poses(robot, frame.seq, frame.capture_nanos))

    def on_frame(sample: object) -> None:
        frame = decode(sample.payload.to_bytes(), Frame)  # type: ignore[attr-defined]
        arrived.append((frame.seq, time.monotonic()))
        delay = delay_secs(frame.seq)
        if delay is not None:
            timer = threading.Timer(delay, answer, (frame,))
            timer.start()  # (then listed: only started timers are joined)
            answers.append(timer)

    sub = hub.declare_subscriber(keys.frames(robot), on_frame)
    cam_session = open_session(ZenohSettings(mode="client", connect=[f"tcp/127.0.0.1:{port}"]))
    try:
        time.sleep(0.5)  # (the hub's subscriber is known to the camera's session)
        published = run_camera(settings, session=cam_session, stop=threading.Event())
        ended = time.monotonic()
        deadline = time.monotonic() + 5
        while len(arrived) < published and time.monotonic() < deadline:
            time.sleep(0.01)
    finally:
        for timer in answers:
            timer.join()
        cam_session.close()
        sub.undeclare()
        hub.close()
    return published, arrived, answered, ended


def test_a_data_set_paced_by_its_poses_is_played_frame_by_frame(tmp_path: Path) -> None:
    """A trial could not make the pipeline process every frame of its data set: at 5 fps the robot skipped
    27 of 200, at 3 fps 7, and it had to guess. `pace = "poses"`: each frame goes out once the previous
    frame's TagPoses came back; a frame whose TagPoses never come is waited for `poses_timeout_secs`,
    said, and the data set goes on. The stand-in pipeline answers every frame but the third (refused on
    the way), 50 ms after it came."""
    published, arrived, answered, _ = _run_paced(
        tmp_path, "paced1", n=6, fps=1000.0, timeout_secs=0.6, delay_secs=lambda seq: None if seq == 2 else 0.05
    )
    assert published == 6 and [s for s, _ in arrived] == list(range(6)), arrived
    when = dict(arrived)
    for seq in (1, 2, 4, 5):  # each went out after the previous frame's poses, never before
        assert when[seq] >= answered[seq - 1], (seq, when, answered)
    assert when[3] - when[2] >= 0.6  # the unanswered frame's timeout, then on


def test_a_data_set_paced_by_its_poses_never_goes_faster_than_its_fps(tmp_path: Path) -> None:
    """A review: after a long wait for poses the next frame went out at once and the one after it too
    (the live camera's catch-up slack): at fps 5, gaps of 50 ms. Paced by poses, fps is the upper bound.
    The stand-in pipeline answers slowly (0.3 s) and quickly (0.01 s) in turn; the last frame's poses
    are waited for before the camera ends."""
    fps = 10.0
    published, arrived, answered, ended = _run_paced(
        tmp_path, "paced2", n=5, fps=fps, timeout_secs=5.0, delay_secs=lambda seq: 0.3 if seq % 2 == 0 else 0.01
    )
    gaps = [b - a for (_, a), (_, b) in itertools.pairwise(arrived)]
    assert published == 5 and len(arrived) == 5 and min(gaps) >= 0.9 / fps, gaps  # (10 %: two threads' clocks)
    assert len(answered) == 5 and ended >= max(answered.values())  # it waited for the last frame's poses


def test_poses_that_do_not_decode_are_counted_and_do_not_release_or_stall_the_paced_camera(
    caplog: pytest.LogCaptureFixture,
) -> None:
    """Paced by poses, the camera reads each TagPoses' capture stamp on Zenoh's thread. Bytes that are
    not a TagPoses (a truncated message, another schema on the key) are counted and said once; they
    neither count as the awaited frame's poses nor keep the good answer after them from releasing it."""
    import time

    from services.camera.service import PosesPacer
    from tests.examples import injected_tag_poses

    robot = "pacedbad"
    port = free_tcp_port()
    hub = open_session(ZenohSettings(mode="peer", listen=[f"tcp/127.0.0.1:{port}"]))
    cam_session = open_session(ZenohSettings(mode="client", connect=[f"tcp/127.0.0.1:{port}"]))
    pacer = PosesPacer(cam_session, robot)
    stop = threading.Event()
    try:
        deadline = time.monotonic() + 10
        while pacer.bad == 0 and time.monotonic() < deadline:  # until the camera's subscriber hears the hub:
            hub.put(keys.tag_poses(robot), b"")  # one empty message at a time, each given 0.5 s to come
            wait_until = time.monotonic() + 0.5
            while pacer.bad == 0 and time.monotonic() < wait_until:
                time.sleep(0.01)
        first = pacer.bad
        assert first >= 1
        capture = time.time_ns()
        pacer.sent(0, capture)
        good = injected_tag_poses(robot, 0, capture)
        stamp = encode(FrameStamp(robot_id=robot, seq=0, capture_nanos=capture, source_stamp_nanos=1))
        for bad in (b"", b"\x00" * 7, good[: len(good) // 2], stamp):  # (the last: another schema)
            hub.put(keys.tag_poses(robot), bad)
        deadline = time.monotonic() + 5
        while pacer.bad < first + 4 and time.monotonic() < deadline:
            time.sleep(0.01)
        assert pacer.bad == first + 4
        assert pacer.wait(stop, 0.3)
        assert pacer.timeouts == 1  # the bad bytes did not release the frame: its timeout did

        capture = time.time_ns()
        pacer.sent(1, capture)
        hub.put(keys.tag_poses(robot), b"\xff\xfe")
        hub.put(keys.tag_poses(robot), injected_tag_poses(robot, 1, capture))
        assert pacer.wait(stop, 5.0)
        assert pacer.timeouts == 1 and pacer.bad == first + 5  # released by the good answer behind the bad one
        said = [r for r in caplog.records if "does not decode" in r.getMessage()]
        assert len(said) == 1 and said[0].levelname == "WARNING"  # said once, not five times
    finally:
        pacer.close()
        cam_session.close()
        hub.close()
