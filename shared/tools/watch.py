"""`splittag watch`, `splittag map` and `splittag stats`: what a running deployment publishes, read from
any shell or process, decoded and checked like the services check it.

- `watch poses|tags|controller|map`: subscribe to one robot's (or, with robot id `*`, every robot's)
  CameraPose, TagPoses, ControllerState or TagMap and print each message as a line (`text`), as a JSON
  object per line (`json`: every field, arrays as nested lists, plus derived fields) or, for poses, as
  TUM trajectory lines (`tum`: `t tx ty tz qx qy qz qw` stamped as trajectory.tum is, in the data set's
  time when the camera sends it, else capture time, exact; lost and bridged poses left out), until
  `count` messages or `duration_secs`.
- `map`: one get on the map queryable (the map as slam holds it now; `save` also writes its files).
- `stats`: one get of every service's input counters (`splittag/<robot>/*/stats`).

A message that does not decode, or that claims another robot than its key, is refused, counted and said
on stderr (rate-limited) and the watch goes on; messages arriving faster than they can be printed are
dropped (counted) instead of queued without bound. Pure formatting below, Zenoh at the edges; nothing
here imports torch, OpenCV, GTSAM or Rerun, so an integrator's process can use it with only zenoh,
msgspec, msgpack, pydantic and numpy installed (README *Reading poses from your own process*).
"""

from __future__ import annotations

import contextlib
import json
import math
import queue
import sys
import time
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field
from functools import partial
from typing import Any, Final, TextIO

import numpy as np
import zenoh
from pydantic import BaseModel

from shared.runtime.guard import InputGuard
from shared.transport.query import get_until_answered
from shared.transport.session import ZenohSettings, open_session
from shared.vision.stamps import format_stamp_nanos
from shared.wire import keys
from shared.wire.messages import (
    CameraPose,
    ControllerState,
    FrameStamp,
    Message,
    TagMap,
    TagPoses,
    decode,
    decode_for_robot,
)

TOPICS: Final[dict[str, tuple[Callable[[str], str], type[Message]]]] = {
    "poses": (keys.camera_pose, CameraPose),
    "tags": (keys.tag_poses, TagPoses),
    "controller": (keys.controller, ControllerState),
    "map": (keys.tag_map, TagMap),
}
# Who publishes each topic, for a watch that hears nothing (a trial's `watch controller` with no controller
# running said only '0 messages')
PUBLISHERS: Final[dict[str, str]] = {
    "poses": "slam publishes it",
    "tags": "edge_infer publishes it, and robot_infer while the edge is away",
    "controller": "the controller publishes it, and runs only when asked: `splittag up --controller` or "
    "`[controller] enabled = true`",
    "map": "slam publishes it when a tag is added and every 30 frames",
}
FORMATS: Final[tuple[str, ...]] = ("text", "json", "tum")
QUEUE_MESSAGES: Final[int] = 1000  # received but not yet printed; beyond it a message is dropped (counted)
QUIET_HINT_SECS: Final[float] = 5.0  # nothing by then: say on stderr what is being waited for
QUIET_MAP_SECS: Final[float] = 60.0  # the same for the map, which a stable run publishes every 30 frames


class ReaderError(RuntimeError):
    """Nothing answered a get, or what answered was refused."""


def key_for(topic: str, robot_id: str) -> str:
    """The key `watch` subscribes to: the topic's key of one robot, or of every robot for `*`."""
    make, _ = TOPICS[topic]
    if robot_id == "*":
        return keys.for_every_robot(make("robot"))
    return make(robot_id)


def quaternion_xyzw(rotation: Any) -> tuple[float, float, float, float]:
    """Unit quaternion (x, y, z, w), w >= 0, of a 3x3 rotation matrix (Shepperd's method: the largest
    of the four squared components is taken first, so no division by a small number)."""
    r = np.asarray(rotation, np.float64).reshape(3, 3)
    trace = float(r[0, 0] + r[1, 1] + r[2, 2])
    diag = (trace, float(r[0, 0]), float(r[1, 1]), float(r[2, 2]))
    i = int(np.argmax(diag))
    if i == 0:
        s = 2.0 * math.sqrt(max(1.0 + trace, 0.0))
        q = ((r[2, 1] - r[1, 2]) / s, (r[0, 2] - r[2, 0]) / s, (r[1, 0] - r[0, 1]) / s, s / 4)
    elif i == 1:
        s = 2.0 * math.sqrt(max(1.0 + r[0, 0] - r[1, 1] - r[2, 2], 0.0))
        q = (s / 4, (r[0, 1] + r[1, 0]) / s, (r[0, 2] + r[2, 0]) / s, (r[2, 1] - r[1, 2]) / s)
    elif i == 2:
        s = 2.0 * math.sqrt(max(1.0 + r[1, 1] - r[0, 0] - r[2, 2], 0.0))
        q = ((r[0, 1] + r[1, 0]) / s, s / 4, (r[1, 2] + r[2, 1]) / s, (r[0, 2] - r[2, 0]) / s)
    else:
        s = 2.0 * math.sqrt(max(1.0 + r[2, 2] - r[0, 0] - r[1, 1], 0.0))
        q = ((r[0, 2] + r[2, 0]) / s, (r[1, 2] + r[2, 1]) / s, s / 4, (r[1, 0] - r[0, 1]) / s)
    v = np.array(q, np.float64)
    v /= np.linalg.norm(v)
    if v[3] < 0:
        v = -v
    return float(v[0]), float(v[1]), float(v[2]), float(v[3])


def position_sigma_m(pose: CameraPose) -> float | None:
    """sqrt of the trace of the pose's position covariance (m): one number for how sure slam is."""
    if pose.covariance_world is None:
        return None
    c = np.asarray(pose.covariance_world, np.float64).reshape(6, 6)
    return float(math.sqrt(max(0.0, float(np.trace(c[:3, :3])))))


def jsonable(value: Any) -> Any:
    """A message (or any part of one) as JSON values: models as objects, arrays as nested lists."""
    if isinstance(value, BaseModel | dict):
        items = value.items() if isinstance(value, dict) else ((k, getattr(value, k)) for k in type(value).model_fields)
        return {str(k): jsonable(v) for k, v in items}
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, list | tuple):
        return [jsonable(v) for v in value]
    if isinstance(value, bytes | bytearray | memoryview):
        return bytes(value).hex()
    return value


def json_line(message: Message) -> str:
    """One JSON object: the schema, every field, and for a pose its position, quaternion and sigma."""
    body: dict[str, Any] = {"schema": message.SCHEMA, **jsonable(message)}
    if isinstance(message, CameraPose):
        m = np.asarray(message.world_from_camera, np.float64)
        body["position_m"] = m[:3, 3].tolist()
        body["quaternion_xyzw"] = list(quaternion_xyzw(m[:3, :3]))
        body["position_sigma_m"] = position_sigma_m(message)
    return json.dumps(body, allow_nan=False)


def tum_line(pose: CameraPose, stamp_nanos: int | None = None) -> str | None:
    """`t tx ty tz qx qy qz qw` at `stamp_nanos` (the frame's data-set time), else its capture time
    (exact decimal seconds); None for a pose that is not in the world frame (lost: the last one
    repeated; bridged: placed by a guess)."""
    if pose.status not in ("tracking", "ground_truth"):
        return None
    m = np.asarray(pose.world_from_camera, np.float64)
    numbers = " ".join(f"{v:.9f}" for v in (*m[:3, 3], *quaternion_xyzw(m[:3, :3])))
    return f"{format_stamp_nanos(pose.capture_nanos if stamp_nanos is None else stamp_nanos)} {numbers}"


# How long after the first pose a TUM watch waits for a data-set stamp before it writes in capture time.
TUM_STAMP_GRACE_SECS = 2.0


class DataSetTime:
    """A data set's time of each frame (the camera's FrameStamps, by capture time), for TUM lines in the
    time trajectory.tum is written in (a trial had to join its live lines through frames.csv). One time
    for the whole output: the first poses wait up to `grace_secs` for a stamp (the stamps' subscription
    reaches the camera's router later than the poses' reaches slam's: review); a stamp by then and the
    lines are in data-set time, a pose without one left out (counted); none, and they are in capture
    time throughout. The grace period starts at the first pose, not at the watch's start: a watch started
    before the run (to catch every pose) waited out its grace before any stamp could come and wrote the
    whole run in capture time (a fresh-clone trial)."""

    def __init__(
        self, *, keep: int = 4096, grace_secs: float = TUM_STAMP_GRACE_SECS, clock: Callable[[], float] = time.monotonic
    ):
        self._by_capture: dict[int, int] = {}
        self.keep, self.grace_secs, self._clock = keep, grace_secs, clock
        self._first_pose: float | None = None  # when the first pose came (the grace period's start)
        self._waiting: list[CameraPose] = []
        self.mode: str | None = None  # "data set" or "capture" once decided
        self.unstamped = 0

    def _grace_over(self) -> bool:
        return self._first_pose is not None and self._clock() - self._first_pose >= self.grace_secs

    def add(self, stamp: FrameStamp) -> None:
        if self.mode is None and self._grace_over():
            self.mode = "capture"  # no stamp in the grace period: capture time it is
        if self.mode == "capture":
            return  # decided: the output stays in one time
        self.mode = "data set"
        self._by_capture[stamp.capture_nanos] = stamp.source_stamp_nanos
        while len(self._by_capture) > self.keep:
            del self._by_capture[next(iter(self._by_capture))]  # the oldest

    def lines(self, pose: CameraPose | None = None, *, final: bool = False) -> list[str]:
        """TUM lines of the poses that can be written now (`final`: every one waiting, whatever the time)."""
        if pose is not None:
            self._waiting.append(pose)
            if self._first_pose is None:
                self._first_pose = self._clock()
        if self.mode is None:
            if not final and not self._grace_over():
                return []
            self.mode = "capture"
        out = []
        for waiting in self._waiting:
            line = self._line(waiting)
            if line is not None:
                out.append(line)
        self._waiting.clear()
        return out

    def _line(self, pose: CameraPose) -> str | None:
        if self.mode == "capture":
            return tum_line(pose)
        stamp = self._by_capture.get(pose.capture_nanos)
        if stamp is None:
            self.unstamped += tum_line(pose) is not None
            return None
        return tum_line(pose, stamp)


def _age(capture_nanos: int, now_nanos: int) -> str:
    """Capture -> now on this host's clock (meaningful when the robot's clock agrees with it)."""
    return f"age {(now_nanos - capture_nanos) / 1e6:.0f} ms"


def pose_text(pose: CameraPose, now_nanos: int) -> str:
    m = np.asarray(pose.world_from_camera, np.float64)
    x, y, z = m[:3, 3]
    qx, qy, qz, qw = quaternion_xyzw(m[:3, :3])
    sigma = position_sigma_m(pose)
    parts = [
        f"{pose.robot_id} #{pose.seq} {pose.status:<8}",
        f"xyz {x:+.3f} {y:+.3f} {z:+.3f} m",
        f"q {qx:+.4f} {qy:+.4f} {qz:+.4f} {qw:+.4f}",
        f"sigma {sigma * 100:.1f} cm" if sigma is not None else "sigma -",
        f"tags {pose.tags_used}",
        _age(pose.capture_nanos, now_nanos),
    ]
    return "  ".join(parts)


def tag_poses_text(msg: TagPoses, now_nanos: int) -> str:
    t = msg.timings
    head = (
        f"{msg.robot_id} #{msg.seq} k={msg.split_k} {msg.payload_bytes} B  "
        f"robot {t.robot_compute_secs * 1e3:.1f} + link {t.transport_secs * 1e3:.1f} + edge "
        f"{t.edge_compute_secs * 1e3:.1f} ms, capture->pose {t.capture_to_pose_secs * 1e3:.1f} ms  "
        f"{_age(msg.capture_nanos, now_nanos)}"
    )
    tags = []
    for tag in msg.tags:
        distance = float(np.linalg.norm(np.asarray(tag.camera_from_tag, np.float64)[:3, 3]))
        how = "tracked" if tag.tracked else (tag.proposer or "detected")
        tags.append(f"{tag.tag_id} ({how}, {distance:.2f} m, {tag.reprojection_error_px:.2f} px)")
    return f"{head}  tags: {', '.join(tags) if tags else 'none'}"


def controller_text(state: ControllerState) -> str:
    if state.has_prediction:
        predicted = " ".join(f"{k}:{ms:.1f}" for k, ms in enumerate(state.predicted_ms_by_k))
        model = f"t0 {state.t0_ms:.1f} ms, beta {state.beta_ms_per_kB:.4f} ms/kB ({state.link_samples} samples)"
    else:
        predicted, model = "-", "no prediction yet"
    pin = "  pinned" if state.pinned else ""
    applied = "  applied" if state.applied else ""
    throughput = ""
    if state.has_prediction and state.frame_share_by_k is not None and state.min_frame_share is not None:
        achieved = state.achieved_ms_by_k or [None] * len(state.frame_share_by_k)
        # a share measured at a cut that ran lately is marked *, the others are the model's
        shares = " ".join(
            f"{k}:{share:.2f}{'' if got is None else '*'}"
            for k, (share, got) in enumerate(zip(state.frame_share_by_k, achieved, strict=True))
        )
        camera = f"camera every {state.frame_interval_ms or 0:.1f} ms"
        throughput = f"  frame share {shares} (keeps up: >= {state.min_frame_share:.2f}, {camera}; * measured)"
    elif state.has_prediction:
        throughput = "  (camera's rate unknown: latency alone)"
    return (
        f"{state.robot_id} k={state.current_k} best={state.best_k} chosen={state.chosen_k}{pin}{applied}  "
        f"T(k) ms {predicted}{throughput}  {model}  ({state.reason})"
    )


def map_text(tag_map: TagMap) -> list[str]:
    """A header line and one line per tag: position, size, observations, how well it is known."""
    lines = [
        f"{tag_map.robot_id} map revision {tag_map.revision}, anchor {tag_map.anchor_tag_id}, {len(tag_map.tags)} tags"
    ]
    for tag in sorted(tag_map.tags, key=lambda t: t.tag_id):
        p = np.asarray(tag.world_from_tag, np.float64)[:3, 3]
        sigma = ""
        if tag.position_sigma_m is not None:
            sigma = f"  sigma {tag.position_sigma_m * 100:.2f} cm / {tag.rotation_sigma_deg or 0.0:.2f} deg"
        bridged = "  bridged" if tag.bridged else ""
        lines.append(
            f"  tag {tag.tag_id:>5}  xyz {p[0]:+.3f} {p[1]:+.3f} {p[2]:+.3f} m  size {tag.size_m:.3f} m  "
            f"{tag.observations} obs{sigma}{bridged}"
        )
    return lines


def render(message: Message, fmt: str, now_nanos: int, data_set_time: DataSetTime | None = None) -> list[str]:
    """The lines one message prints as (none for a pose `tum` leaves out)."""
    if fmt == "json":
        return [json_line(message)]
    if fmt == "tum":
        if not isinstance(message, CameraPose):
            raise ValueError("the tum format is for poses only")
        if data_set_time is not None:
            return data_set_time.lines(message)
        line = tum_line(message)
        return [line] if line is not None else []
    if isinstance(message, CameraPose):
        return [pose_text(message, now_nanos)]
    if isinstance(message, TagPoses):
        return [tag_poses_text(message, now_nanos)]
    if isinstance(message, ControllerState):
        return [controller_text(message)]
    if isinstance(message, TagMap):
        return map_text(message)
    raise TypeError(f"no text form for {type(message).__name__}")


def _decode_checked(payload: bytes, model: type[Message], key: str) -> Message:
    """A message whose robot id is not its key's is refused (as the services refuse it)."""
    message: Message = decode_for_robot(payload, model, keys.robot_of(key))
    return message


@dataclass
class WatchResult:
    """What a watch saw: messages printed, refused (by reason) and dropped because printing fell behind."""

    messages: int = 0
    lines: int = 0
    dropped: int = 0
    unstamped: int = 0  # tum: tracking poses left out for want of their frame's data-set stamp
    dropped_stamps: int = 0  # tum: data-set stamps dropped because printing fell behind
    tum_time: str | None = None  # tum: "data set" or "capture", the time the lines are in (None: no line)
    rejected: dict[str, int] = field(default_factory=dict)
    by_robot: Counter[str] = field(default_factory=Counter)

    def summary(self, key: str) -> str:
        refused = sum(self.rejected.values())
        detail = f" ({', '.join(f'{r}: {n}' for r, n in sorted(self.rejected.items()))})" if refused else ""
        robots = f" from {', '.join(sorted(self.by_robot))}" if len(self.by_robot) > 1 else ""
        unstamped = f", {self.unstamped} left out (no data-set stamp)" if self.unstamped else ""
        if self.dropped_stamps:
            unstamped += f", {self.dropped_stamps} data-set stamps dropped (printing fell behind)"
        if self.tum_time == "data set":
            unstamped += "; TUM lines in the data set's time (its rgb.txt stamps)"
        elif self.tum_time == "capture":
            unstamped += (
                f"; TUM lines in capture time: no data-set stamp came within {TUM_STAMP_GRACE_SECS:g} s of the first "
                "pose (a camera source without rgb.txt stamps, or none reached this watch)"
            )
        return (
            f"{key}: {self.messages} message{'' if self.messages == 1 else 's'}{robots}, {refused} refused{detail}, "
            f"{self.dropped} dropped (printing fell behind){unstamped}"
        )


WAIT_ATTEMPT_SECS: Final[float] = 2.0  # zenoh.open does not return for Ctrl-C: short attempts keep it prompt


def _open_waiting(settings: ZenohSettings, wait_secs: float, who: str, err: TextIO) -> zenoh.Session:
    """A client session, trying again until `wait_secs` have passed while no router answers (said once).
    Tried in attempts of a few seconds: a signal is handled between two (zenoh.open holds on to it)."""
    if wait_secs <= 0:
        return open_session(settings)
    deadline = time.monotonic() + wait_secs
    told = False
    while True:
        left_secs = deadline - time.monotonic()
        attempt = settings.model_copy(update={"connect_timeout_secs": max(0.1, min(WAIT_ATTEMPT_SECS, left_secs))})
        try:
            return open_session(attempt)
        except zenoh.ZError:
            if time.monotonic() >= deadline:
                raise
        if not told:
            told = True
            print(
                f"{who}: no router at {', '.join(settings.connect)} yet; trying for "
                f"{deadline - time.monotonic():.0f} s more (--wait-secs)",
                file=err,
                flush=True,
            )


def watch(
    topic: str,
    robot_id: str,
    settings: ZenohSettings,
    *,
    fmt: str = "text",
    count: int | None = None,
    duration_secs: float | None = None,
    wait_secs: float = 0.0,
    out: TextIO = sys.stdout,
    err: TextIO = sys.stderr,
) -> WatchResult:
    """Subscribe and print until `count` messages, `duration_secs` or Ctrl-C; the callback only enqueues.
    With no router in reach it keeps trying for `wait_secs` (a watch started just before `splittag up`)."""
    if topic not in TOPICS:
        raise ValueError(f"unknown topic {topic!r}: one of {', '.join(TOPICS)}")
    if fmt not in FORMATS or (fmt == "tum" and topic != "poses"):
        raise ValueError(f"format {fmt!r} is not one of {', '.join(FORMATS)} ('tum' is for poses)")
    key = key_for(topic, robot_id)
    model = TOPICS[topic][1]
    inbox: queue.Queue[tuple[str, bytes]] = queue.Queue(maxsize=QUEUE_MESSAGES)
    result = WatchResult()
    dropped = Counter[str]()  # on Zenoh's thread; Counter's update under the GIL, read at the end
    received = 0

    def on_sample(sample: zenoh.Sample) -> None:
        try:
            inbox.put_nowait((str(sample.key_expr), sample.payload.to_bytes()))
        except queue.Full:
            dropped["full"] += 1

    guard = InputGuard(f"splittag watch {topic}")
    stamps: queue.Queue[bytes] = queue.Queue(maxsize=QUEUE_MESSAGES)

    def on_stamp(sample: zenoh.Sample) -> None:
        try:
            stamps.put_nowait(sample.payload.to_bytes())
        except queue.Full:
            dropped["stamps"] += 1

    data_set_time = DataSetTime() if fmt == "tum" else None
    quiet_secs = QUIET_MAP_SECS if topic == "map" else QUIET_HINT_SECS  # a stable map comes every 30 frames

    def emit(lines: list[str]) -> None:
        for line in lines:
            print(line, file=out, flush=True)
            result.lines += 1

    def take_stamps() -> None:  # stamps leave the camera long before their frames' poses
        while data_set_time is not None and not stamps.empty():
            stamp = guard.run("frame_stamp", 0, partial(decode, stamps.get_nowait(), FrameStamp))
            if stamp is not None:
                data_set_time.add(stamp)

    try:
        session = _open_waiting(settings, wait_secs, f"splittag watch {topic}", err)
    except KeyboardInterrupt:
        return result
    start = last_at = time.monotonic()
    hinted = False  # said that nothing came (yet, or since the last message)
    try:
        # the frames' data-set time, when the camera sends it (rgb.txt), subscribed first; both kept (a
        # subscriber that is garbage-collected is undeclared)
        stamp_subscriber = session.declare_subscriber(keys.frame_stamp(robot_id), on_stamp) if data_set_time else None
        subscriber = session.declare_subscriber(key, on_sample)
        while count is None or result.messages < count:
            now = time.monotonic()
            if duration_secs is not None and now - start >= duration_secs:
                break
            if not hinted and now - last_at >= quiet_secs:
                if received == 0:
                    said = f"nothing on {key} yet ({PUBLISHERS[topic]}): is it running, and reachable from here?"
                else:  # a deployment that stopped: say so once instead of waiting in silence
                    said = (
                        f"nothing more on {key} for {now - last_at:.0f} s: has the deployment stopped? (Ctrl-C "
                        "ends the watch)"
                    )
                print(said, file=err, flush=True)
                hinted = True
            try:
                sample_key, payload = inbox.get(timeout=0.2)
            except queue.Empty:
                if data_set_time is not None:  # the grace for stamps may have run out: poses waiting go out
                    take_stamps()
                    emit(data_set_time.lines())
                continue
            received += 1
            last_at, hinted = time.monotonic(), False
            take_stamps()
            message = guard.run(topic, len(payload), partial(_decode_checked, payload, model, sample_key))
            if message is None:
                continue
            result.messages += 1
            result.by_robot[getattr(message, "robot_id", "")] += 1
            emit(render(message, fmt, time.time_ns(), data_set_time))
        take_stamps()
        if data_set_time is not None:
            emit(data_set_time.lines(final=True))
        if received == 0 and not hinted:  # ended (--duration, --count) before the hint: said all the same
            print(f"nothing came on {key} ({PUBLISHERS[topic]}): is it running, and reachable from here?", file=err)
        subscriber.undeclare()
        if stamp_subscriber is not None:
            stamp_subscriber.undeclare()
    except KeyboardInterrupt:
        if data_set_time is not None:
            with contextlib.suppress(BrokenPipeError):
                emit(data_set_time.lines(final=True))
    finally:
        session.close()
    result.rejected = dict(guard.rejected)
    result.dropped = dropped["full"]
    result.dropped_stamps = dropped["stamps"]
    result.unstamped = data_set_time.unstamped if data_set_time is not None else 0
    result.tum_time = data_set_time.mode if data_set_time is not None else None
    return result


def _denied(settings: ZenohSettings, what: str = "ask it") -> str:
    """What else no reply can mean under access control: a denied query gets none (docs/security.md)."""
    return "" if settings.tls is None else f", and may {settings.tls.certificate.stem!r} {what} under access control"


def _refused(selector: str, refused: list[str], err: TextIO) -> None:
    """Replies that could not be trusted: said on `err` beside the good ones (a wildcard get's other
    replies are still shown), or the error when nothing good came."""
    for line in refused:
        print(f"{selector}: {line}", file=err, flush=True)


def get_map(
    robot_id: str, settings: ZenohSettings, *, save: bool = False, timeout_secs: float = 5.0, err: TextIO = sys.stderr
) -> list[TagMap]:
    """One get on the map queryable: the map of each slam that answers (`save`: it also writes its files).
    A reply that does not decode, or is an error, is said and left out; ReaderError if none is left."""
    selector = key_for("map", robot_id) + ("?save=1" if save else "")
    save_what = "save the map (only an operator may)" if save else "ask it"  # a denied query gets no reply
    maps: list[TagMap] = []
    refused: list[str] = []
    session = open_session(settings)
    try:
        for reply in get_until_answered(session, selector, timeout_secs):
            if reply.ok is not None:
                try:
                    tag_map = _decode_checked(reply.ok.payload.to_bytes(), TagMap, str(reply.ok.key_expr))
                    assert isinstance(tag_map, TagMap)
                    maps.append(tag_map)
                except Exception as exc:  # a reply we cannot trust is said, not shown
                    refused.append(f"refused a reply from {reply.ok.key_expr}: {exc}")
            elif reply.err is not None:
                refused.append(reply.err.payload.to_string())
    finally:
        session.close()
    if not maps and refused:
        raise ReaderError(f"{selector}: {'; '.join(refused)}")
    if not maps:
        raise ReaderError(
            f"no reply on {selector} within {timeout_secs:g} s: is slam running{_denied(settings, save_what)}?"
        )
    _refused(selector, refused, err)
    return maps


def get_stats(
    robot_id: str, settings: ZenohSettings, *, timeout_secs: float = 5.0, err: TextIO = sys.stderr
) -> dict[str, dict[str, Any]]:
    """Every service's input counters, by the key that answered (`splittag/<robot>/<service>/stats`); a
    reply that is not JSON is said and left out, ReaderError if none is left."""
    robot = "*" if robot_id == "*" else keys.robot_of(keys.stats(robot_id, "any"))  # checks the id
    selector = f"{keys.ROOT}/{robot}/*/stats"
    found: dict[str, dict[str, Any]] = {}
    refused: list[str] = []
    session = open_session(settings)
    try:
        for reply in get_until_answered(session, selector, timeout_secs):
            if reply.ok is not None:
                try:
                    body = json.loads(reply.ok.payload.to_bytes())
                except ValueError as exc:
                    refused.append(f"{reply.ok.key_expr} answered no JSON: {exc}")
                    continue
                found[str(reply.ok.key_expr)] = body if isinstance(body, dict) else {"reply": body}
    finally:
        session.close()
    if not found and refused:
        raise ReaderError(f"{selector}: {'; '.join(refused)}")
    if not found:
        raise ReaderError(
            f"no reply on {selector} within {timeout_secs:g} s: are the services running{_denied(settings)}?"
        )
    _refused(selector, refused, err)
    return dict(sorted(found.items()))


_GUARD_FIELDS: Final[frozenset[str]] = frozenset(
    {"service", "accepted", "accepted_by_input", "rejected", "rejected_by_reason", "last_rejected"}
)


def _counts(value: Any) -> dict[str, Any]:
    """A stats reply's counter table, or nothing when a reply has something else there."""
    return {str(k): v for k, v in value.items()} if isinstance(value, dict) else {}


def stats_text(stats: dict[str, dict[str, Any]]) -> list[str]:
    """One line per service: accepted (by input) and refused (by reason), then the newest refusal's
    text per reason, indented."""
    lines = []
    for key, body in stats.items():
        name = key.removeprefix(f"{keys.ROOT}/").removesuffix("/stats")
        inputs = ", ".join(f"{k} {v}" for k, v in sorted(_counts(body.get("accepted_by_input")).items()))
        reasons = ", ".join(f"{k}: {v}" for k, v in sorted(_counts(body.get("rejected_by_reason")).items()))
        extra = {k: v for k, v in body.items() if k not in _GUARD_FIELDS}
        more = "  " + " ".join(f"{k}={v}" for k, v in sorted(extra.items())) if extra else ""
        lines.append(
            f"{name:<24} accepted {body.get('accepted', 0)}"
            + (f" ({inputs})" if inputs else "")
            + f"  refused {body.get('rejected', 0)}"
            + (f" ({reasons})" if reasons else "")
            + more
        )
        lines += [f"    last {k}: {v}" for k, v in sorted(_counts(body.get("last_rejected")).items())]
    return lines
