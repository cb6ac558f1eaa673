"""`python -m services.camera --config deploy/local.toml`"""

from services.camera.service import run
from services.camera.settings import CameraSettings
from shared.runtime.service_main import service_main

raise SystemExit(service_main("camera", CameraSettings, lambda s, z, stop: run(s, session=z, stop=stop)))
