"""Settings of the adaptive split controller."""

from __future__ import annotations

from typing import ClassVar

from pydantic import Field
from pydantic_settings import SettingsConfigDict

from shared.control.controller import ControllerTuning
from shared.runtime.settings import ServiceSettings


class ControllerSettings(ServiceSettings, ControllerTuning):
    """How often to decide and probe; how reluctant to switch comes from ControllerTuning (the core's)."""

    SERVICE: ClassVar[str] = "controller"
    model_config = SettingsConfigDict(**{**ServiceSettings.model_config, "env_prefix": "SPLITTAG_CONTROLLER_"})

    enabled: bool = True  # False: estimate and publish state, never change k (an observer)
    decide_period_secs: float = Field(default=0.1, gt=0)  # one decision (and ControllerState) per period
    probe_period_secs: float = Field(default=0.15, gt=0)  # at most one routine probe per period ...
    probe_max_age_secs: float = Field(default=0.3, gt=0)  # ... at a size not seen for this long
    probe_busy_max_wait_secs: float = Field(default=2.0, gt=0)  # probe a link busy this long anyway
    # Two sizes pin both t0 and beta even while frames carry almost nothing (k = 7); small enough
    # to occupy the 14.2 Mbit/s uplink for at most ~37 ms.
    probe_sizes_bytes: list[int] = Field(default_factory=lambda: [16 * 1024, 64 * 1024])
    # Probes use at most this share of the uplink's estimated rate (1 / beta), in one burst of every size
    # at most: on a 4 Mbit/s uplink at k = 7 a trial saw 40 % of it in probes (ProbeBudget). At 0.1 the
    # 5g-pre-tdd link's routine probes were held back and bench.controller's reach back to k = 0 on 5g
    # went 0.7 -> 1.1 s; at 0.25 they are not (0.70-0.73 s) and a 4 Mbit/s link carries 1 Mbit/s of them
    probe_budget_share: float = Field(default=0.25, gt=0, le=1)
    # A probe not answered within this long failed (said once a run of failures); the controller waits for
    # one in flight at exit
    probe_timeout_secs: float = Field(default=5.0, gt=0, le=60)
