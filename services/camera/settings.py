"""Settings of the camera service."""

from __future__ import annotations

from pathlib import Path
from typing import ClassVar, Literal

from pydantic import Field
from pydantic_settings import SettingsConfigDict

from shared.runtime.settings import ServiceSettings


class CameraSettings(ServiceSettings):
    """Where frames come from and how fast they go out."""

    SERVICE: ClassVar[str] = "camera"
    model_config = SettingsConfigDict(**{**ServiceSettings.model_config, "env_prefix": "SPLITTAG_CAMERA_"})

    source: Literal["demo", "folder", "video", "v4l2"] = "demo"  # demo scene, image folder, video file or V4L2 device
    path: str = ""  # folder, video file, or V4L2 device index/path
    camera_info: Path | None = None  # ROS camera_info YAML (required for folder, video, v4l2)
    groundtruth: Path | None = None  # optional TUM file for a folder or a video file (in the video's time)
    fps: float = Field(default=15.0, gt=0)  # publishing rate (a folder or video is paced to it)
    # "fps": frames go out at `fps` whatever the pipeline takes (a robot slower than the camera skips
    # frames, as a live camera's would); "poses": each frame waits, also, for the previous frame's
    # TagPoses, so a data set is played frame by frame and none is skipped (`fps` stays the upper bound),
    # or for `poses_timeout_secs` when they do not come (a frame refused on the way: said, counted).
    pace: Literal["fps", "poses"] = "fps"
    poses_timeout_secs: float = Field(default=10.0, gt=0)  # pace = "poses": the longest wait for a frame's TagPoses
    # None (default): loop the demo scene, play any other source once (a data set replayed in a loop
    # would fold its trajectory onto itself). A looped source that has data-set stamps (rgb.txt, a video
    # file's own time) is stamped forward on every new pass (pass n: + n x its span), so time never runs
    # backwards.
    loop: bool | None = None
    max_frames: int = Field(default=0, ge=0)  # 0 = unlimited
    # skip this many frames of the source's first pass (a folder or video camera restarted by the run's
    # launcher goes on from where it was instead)
    start_frame: int = Field(default=0, ge=0)
    demo_frames: int = Field(default=150, ge=2)  # length of the demo scene's loop

    @property
    def loops(self) -> bool:
        """Whether the source restarts when it ends (`loop`, or its default for the source)."""
        return self.source == "demo" if self.loop is None else self.loop

    cache_dir: Path = Path("runs/cache")  # where the demo scene's renders are cached
    wait_for: list[str] = Field(default_factory=lambda: ["robot_infer"])  # services to await before streaming
