"""The documents say what the code does where it can be checked mechanically: every setting with its
default (docs/services.md's generated reference), every current schema (docs/wire.md), and
`splittag settings` resolving a config file as the services do."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

from shared.tools import settings_doc
from shared.wire.messages import MESSAGE_TYPES

REPO = Path(__file__).resolve().parent.parent


def test_the_settings_reference_matches_the_settings_models() -> None:
    text = settings_doc.DOC.read_text()
    assert settings_doc.BEGIN in text and settings_doc.END in text
    assert settings_doc.replace_section(text, settings_doc.markdown()) == text, (
        "docs/services.md's settings reference is out of date: python -m shared.tools.settings_doc --write"
    )


def test_the_reference_lists_every_leaf_setting_with_its_default() -> None:
    # Independent of the generator's walk: a few settings looked up by hand in the models.
    from services.controller.settings import ControllerSettings
    from services.robot_infer.settings import RobotInferSettings

    text = settings_doc.DOC.read_text()
    assert f"| `dwell` | `{ControllerSettings().dwell}` |" in text
    assert f"| `split_k` | `{RobotInferSettings().split_k}` |" in text
    quad_decimate = RobotInferSettings().stage1.apriltag.quad_decimate
    assert f"| `stage1.apriltag.quad_decimate` | `{quad_decimate!r}` |" in text
    assert "| `zenoh.tls.certificate` | `none` |" in text  # a field of an unset optional group
    for service in settings_doc.SERVICES:
        for row in settings_doc.service_rows(service):
            assert row.meaning, f"{service}.{row.name} has no comment in its settings class"


def test_every_current_schema_is_in_the_wire_document() -> None:
    wire = (REPO / "docs" / "wire.md").read_text()
    listed = set(re.findall(r"^\| `(splittag/[A-Za-z]+/v\d+)` \|", wire, flags=re.MULTILINE))
    current = {m.SCHEMA for m in MESSAGE_TYPES}
    assert current <= listed, f"docs/wire.md's schema table lacks {sorted(current - listed)}"


def test_settings_command_shows_what_a_config_file_changes(tmp_path: Path) -> None:
    config = tmp_path / "site.toml"
    config.write_text('[common]\nrobot_id = "rover7"\n[controller]\ndwell = 4\n[controller.zenoh]\nmode = "client"\n')
    out = subprocess.run(
        [sys.executable, "-m", "shared.tools.cli", "settings", "controller", "--config", str(config)],
        capture_output=True,
        text=True,
        timeout=120,
        cwd=REPO,
    )
    assert out.returncode == 0, out.stderr
    lines = {line.split("=")[0].strip(" *"): line for line in out.stdout.splitlines() if "=" in line}
    assert lines["dwell"].startswith(" *") and "= 4   # default 2" in lines["dwell"]
    assert lines["robot_id"].startswith(" *") and '"rover7"' in lines["robot_id"]
    assert lines["zenoh.mode"].startswith(" *") and 'default "peer"' in lines["zenoh.mode"]
    assert lines["min_gain_ms"].startswith("  ") and "default" not in lines["min_gain_ms"]
    assert "zenoh.tls.certificate" not in lines  # TLS unset: its fields are not values to show


def test_settings_command_refuses_an_unknown_service_and_a_bad_file(tmp_path: Path) -> None:
    def run(*args: str) -> subprocess.CompletedProcess[str]:
        return subprocess.run(
            [sys.executable, "-m", "shared.tools.cli", "settings", *args],
            capture_output=True,
            text=True,
            timeout=120,
            cwd=REPO,
        )

    out = run("robot")
    assert out.returncode == 2 and "unknown service robot" in out.stderr
    bad = tmp_path / "bad.toml"
    bad.write_text("[slam]\nwindow_frame = 3\n")
    out = run("slam", "--config", str(bad))
    assert out.returncode == 2 and "window_frame" in out.stderr and "Traceback" not in out.stderr
    assert out.stdout == ""
