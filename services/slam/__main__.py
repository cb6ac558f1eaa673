"""`python -m services.slam --config deploy/local.toml`"""

from services.slam.service import run
from services.slam.settings import SlamServiceSettings
from shared.runtime.service_main import service_main

raise SystemExit(service_main("slam", SlamServiceSettings, lambda s, z, stop: run(s, session=z, stop=stop)))
