"""`python -m services.controller --config deploy/local.toml`"""

from services.controller.service import run
from services.controller.settings import ControllerSettings
from shared.runtime.service_main import service_main

raise SystemExit(service_main("controller", ControllerSettings, lambda s, z, stop: run(s, session=z, stop=stop)))
