"""`python -m services.camera --config deploy/local.toml`"""

from services.camera.service import check_source, run
from services.camera.settings import CameraSettings
from shared.runtime.service_main import service_main

raise SystemExit(
    service_main("camera", CameraSettings, lambda s, z, stop: run(s, session=z, stop=stop), check=check_source)
)
