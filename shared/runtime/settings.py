"""Service settings: pydantic-settings with layered sources.

Priority, highest first: explicit keyword arguments, environment variables (prefix
`SPLITTAG_<SERVICE>_`, nested fields with `__`, e.g. `SPLITTAG_EDGE_INFER_ZENOH__MODE=router`),
the service's table in the TOML config file (`[edge_infer]`), the file's `[common]` table,
then defaults. The TOML file comes from `--config` or `SPLITTAG_CONFIG`.
"""

from __future__ import annotations

import logging
import os
import tomllib
from contextvars import ContextVar
from pathlib import Path
from typing import Annotated, Any, ClassVar, Final, Literal, TypeVar

from pydantic import Field
from pydantic_settings import BaseSettings, PydanticBaseSettingsSource, SettingsConfigDict, TomlConfigSettingsSource

from shared.transport.session import ZenohSettings
from shared.viz.recording import RerunSettings
from shared.wire.codec import DEFAULT_MAX_BYTES
from shared.wire.messages import RobotId

# Which robots a fleet service serves: None = its `robot_id` alone; a non-empty list = those robots;
# "*" = every robot whose robot_infer is alive (its liveliness token).
ServedRobots = Annotated[list[RobotId], Field(min_length=1)] | Literal["*"] | None

log = logging.getLogger(__name__)
CONFIG_ENV: Final[str] = "SPLITTAG_CONFIG"  # names the TOML file when --config is not given
CURRENT_RUN: Final[Path] = Path("runs/current")  # the launcher points this at the newest run folder
_CONFIG_FILE: ContextVar[Path | None] = ContextVar("splittag_config_file", default=None)

S = TypeVar("S", bound="ServiceSettings")
CONFIG_EXIT: Final[int] = 2  # a service's exit code for settings it cannot work with: restarting cannot help
# The camera's exit code when its source ended (loop off, max_frames): the run is complete. A camera
# stopped by a signal exits 0 like every service, and a launcher that did not ask restarts it (a trial's
# SIGTERM to the demo camera, whose source never ends, read as a source that ended and stopped the run).
SOURCE_ENDED_EXIT: Final[int] = 3


class ConfigurationError(RuntimeError):
    """Settings, or what they name (a file, a folder, a device), that the service cannot work with: it
    stops with one clear line and exit code CONFIG_EXIT, and the launcher ends the run instead of
    restarting it."""


class ServiceSettings(BaseSettings):
    """Fields every service has."""

    SERVICE: ClassVar[str] = "common"
    model_config = SettingsConfigDict(extra="forbid", env_nested_delimiter="__", env_prefix="SPLITTAG_")

    robot_id: RobotId = "robot1"  # the robot whose keys (splittag/<robot_id>/...) this service uses
    zenoh: ZenohSettings = Field(default_factory=ZenohSettings)
    run_dir: Path = CURRENT_RUN  # logs, recordings and outputs (the launcher gives each run its folder)
    # larger messages are refused unread (counted, logged); above zenoh.max_message_bytes Zenoh drops them unseen
    max_payload_bytes: int = Field(default=DEFAULT_MAX_BYTES, gt=0)
    # start-up wait for the services this one needs (their liveliness tokens)
    liveliness_timeout_secs: float = Field(default=60.0, gt=0)
    rerun: RerunSettings = Field(default_factory=RerunSettings)
    # The CPUs this service runs on (all its threads; shared.runtime.cpus), None: wherever the OS puts
    # it. Where robot and edge services share a host, each side on its own cores keeps its caches warm
    # (docs/wire.md, *Views and CPU placement*).
    cpus: Annotated[list[Annotated[int, Field(ge=0)]], Field(min_length=1)] | None = None

    @classmethod
    def settings_customise_sources(
        cls,
        settings_cls: type[BaseSettings],
        init_settings: PydanticBaseSettingsSource,
        env_settings: PydanticBaseSettingsSource,
        dotenv_settings: PydanticBaseSettingsSource,
        file_secret_settings: PydanticBaseSettingsSource,
    ) -> tuple[PydanticBaseSettingsSource, ...]:
        sources: list[PydanticBaseSettingsSource] = [init_settings, env_settings]
        path = _CONFIG_FILE.get()
        if path is not None:
            # Only the tables the file has: pydantic-settings raises KeyError for a missing one.
            tables = tomllib.loads(path.read_text())
            for header in (cls.SERVICE, "common"):
                if isinstance(tables.get(header), dict):
                    sources.append(TomlConfigSettingsSource(settings_cls, path, toml_table_header=(header,)))
        return tuple(sources)

    @classmethod
    def load(cls: type[S], config_file: Path | None = None, **overrides: Any) -> S:
        """Build the settings from the layered sources (see module docstring); without `config_file`
        the TOML file named by SPLITTAG_CONFIG, if set."""
        if config_file is None and os.environ.get(CONFIG_ENV):
            config_file = Path(os.environ[CONFIG_ENV])
        if config_file is not None and not Path(config_file).is_file():
            raise FileNotFoundError(f"config file {config_file} does not exist")
        token = _CONFIG_FILE.set(Path(config_file) if config_file else None)
        try:
            return cls(**overrides)
        finally:
            _CONFIG_FILE.reset(token)

    def log_resolved(self) -> None:
        """Log the resolved settings once at start-up."""
        log.info("%s settings: %s", self.SERVICE, self.model_dump_json())
