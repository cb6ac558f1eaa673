"""Service settings: layered sources, SPLITTAG_CONFIG, and the run folder shared with the launcher."""

from __future__ import annotations

from pathlib import Path

import pytest

from services.camera.settings import CameraSettings
from shared.runtime.settings import CONFIG_ENV, CURRENT_RUN
from shared.tools.launch import new_run_dir


def test_splittag_config_names_the_toml_when_no_config_is_given(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    cfg = tmp_path / "site.toml"
    cfg.write_text('[common]\nrobot_id = "from_env_file"\n[camera]\nfps = 4.5\n')
    monkeypatch.setenv(CONFIG_ENV, str(cfg))
    s = CameraSettings.load()
    assert (s.robot_id, s.fps) == ("from_env_file", 4.5)
    # --config wins over the environment's file.
    other = tmp_path / "other.toml"
    other.write_text("[camera]\nfps = 2.0\n")
    assert CameraSettings.load(other).fps == 2.0
    monkeypatch.setenv(CONFIG_ENV, str(tmp_path / "missing.toml"))
    with pytest.raises(FileNotFoundError, match=r"missing\.toml"):
        CameraSettings.load()


def test_services_default_run_dir_is_the_folder_the_launcher_points_at(tmp_path: Path) -> None:
    """Services used to default to runs/latest while the launcher maintained runs/current."""
    assert CameraSettings.load().run_dir == CURRENT_RUN
    run = new_run_dir(tmp_path / CURRENT_RUN.parent)
    assert (tmp_path / CURRENT_RUN).resolve() == run.resolve()
