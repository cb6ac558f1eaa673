"""`python -m services.edge_infer --config deploy/local.toml`"""

from services.edge_infer.service import run
from services.edge_infer.settings import EdgeInferSettings
from shared.runtime.service_main import service_main

raise SystemExit(service_main("edge_infer", EdgeInferSettings, lambda s, z, stop: run(s, session=z, stop=stop)))
