"""The documents say what the code does where it can be checked mechanically: every setting with its
default (docs/services.md's generated reference), every current schema (docs/wire.md), and
`splittag settings` resolving a config file as the services do."""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
from pathlib import Path

from shared.tools import settings_doc
from shared.wire.messages import MESSAGE_TYPES

REPO = Path(__file__).resolve().parent.parent


def _without_splittag_variables() -> dict[str, str]:
    """This environment without SPLITTAG_* (a developer's exported override must not change a test)."""
    return {k: v for k, v in os.environ.items() if not k.startswith("SPLITTAG_")}


def test_the_generated_document_sections_match_the_code() -> None:
    """docs/services.md's settings reference and docs/wire.md's schema layouts are what the code
    generates (`python -m shared.tools.docgen` rewrites them)."""
    from shared.tools import docgen

    stale = [f"{s.doc.name}: {s.name}" for s in docgen.stale()]
    assert not stale, f"out of date: {stale}; run python -m shared.tools.docgen"


def test_the_reference_lists_every_leaf_setting_with_its_default() -> None:
    # Independent of the generator's walk: a few settings looked up by hand in the models.
    from services.controller.settings import ControllerSettings
    from services.robot_infer.settings import RobotInferSettings
    from shared.vision.detector import DetectorSettings

    text = (REPO / "docs" / "services.md").read_text()
    # The models' declared defaults (not an instance: an exported SPLITTAG_* variable would change that).
    assert f"| `dwell` | `{ControllerSettings.model_fields['dwell'].default}` |" in text
    assert f"| `split_k` | `{RobotInferSettings.model_fields['split_k'].default}` |" in text
    quad_decimate = DetectorSettings.model_fields["quad_decimate"].default
    assert f"| `stage1.apriltag.quad_decimate` | `{quad_decimate!r}` |" in text
    assert "| `zenoh.tls.certificate` | `none` |" in text  # a field of an unset optional group
    for service in (settings_doc.COMMON, *settings_doc.SERVICES):
        for row in settings_doc.service_rows(service):
            assert row.meaning, f"{service}.{row.name} has no comment in its settings class"


def test_the_wire_document_gives_every_schemas_field_order() -> None:
    """A client of its own (another language) needs each header's fields in order (a fresh-clone trial
    had to read them from the source): docs/wire.md's section is generated from the models."""
    text = (REPO / "docs" / "wire.md").read_text()
    # Independent of the generator: TagPoses' fields as the model declares them, in order.
    from shared.wire.messages import TagPoses

    section = text[text.index(f"**`{TagPoses.SCHEMA}`**") :]
    section = section[: section.index("\n\n**`")]
    top = [line.split("`")[1] for line in section.splitlines() if line[:1].isdigit()]
    assert top == list(TagPoses.model_fields)


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
        env=_without_splittag_variables(),
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
            env=_without_splittag_variables(),
        )

    out = run("robot")
    assert out.returncode == 2 and "unknown service robot" in out.stderr
    bad = tmp_path / "bad.toml"
    bad.write_text("[slam]\nwindow_frame = 3\n")
    out = run("slam", "--config", str(bad))
    assert out.returncode == 2 and "window_frame" in out.stderr and "Traceback" not in out.stderr
    assert out.stdout == ""


def test_a_process_records_its_settings_only_in_the_run_of_the_launcher_that_started_it(tmp_path: Path) -> None:
    """settings/<service>-<who>.json is a run's record: a service started by hand beside a run (or later,
    with runs/current's config) must not overwrite it (review); the fleet's one slam is `slam-fleet`."""
    from services.edge_infer.settings import EdgeInferSettings
    from services.slam.settings import SlamServiceSettings
    from shared.runtime.service_main import write_resolved

    run = tmp_path / "run"
    run.mkdir()
    slam = SlamServiceSettings(run_dir=run, robot_id="r9")
    assert write_resolved(slam, "slam") is None  # no launcher.pid: not a launcher's run
    (run / "launcher.pid").write_text("1\n")  # another process's run
    assert write_resolved(slam, "slam") is None and not (run / "settings").exists()
    (run / "launcher.pid").write_text(f"{os.getppid()}\n")  # this process's parent started it
    written = write_resolved(slam, "slam")
    assert written == run / "settings" / "slam-r9.json"
    assert json.loads(written.read_text())["slam"]["window_frames"] == slam.slam.window_frames
    fleet = write_resolved(SlamServiceSettings(run_dir=run, robots=["a", "b"]), "slam")
    assert fleet is not None and fleet.name == "slam-fleet.json"
    worker = write_resolved(EdgeInferSettings(run_dir=run, worker_id="edge7"), "edge_infer")
    assert worker is not None and worker.name == "edge_infer-edge7.json"
    assert sorted(p.name for p in (run / "settings").iterdir()) == [
        "edge_infer-edge7.json",
        "slam-fleet.json",
        "slam-r9.json",
    ]  # no temporary file left
