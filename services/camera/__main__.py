"""`python -m services.camera --config deploy/local.toml`"""

import threading

import zenoh

from services.camera.service import check_source, run
from services.camera.settings import CameraSettings
from shared.runtime.service_main import SOURCE_ENDED, service_main
from shared.runtime.sources import FrameSource

checked: list[FrameSource | None] = []  # the source check_source made: the loop streams that one


def _run(settings: CameraSettings, session: zenoh.Session, stop: threading.Event) -> object:
    run(settings, session=session, stop=stop, source=checked[0] if checked else None)
    return SOURCE_ENDED  # (service_main: unless the stop ended it)


raise SystemExit(service_main("camera", CameraSettings, _run, check=lambda s: checked.append(check_source(s))))
