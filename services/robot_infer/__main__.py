"""`python -m services.robot_infer --config deploy/local.toml`"""

from services.robot_infer.service import run
from services.robot_infer.settings import RobotInferSettings
from shared.runtime.service_main import service_main

raise SystemExit(service_main("robot_infer", RobotInferSettings, lambda s, z, stop: run(s, session=z, stop=stop)))
