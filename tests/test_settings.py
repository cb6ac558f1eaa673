"""Service settings: layered sources, SPLITTAG_CONFIG, and the run folder shared with the launcher."""

from __future__ import annotations

from pathlib import Path

import pytest

from services.camera.settings import CameraSettings
from shared.runtime.settings import CONFIG_ENV, CURRENT_RUN
from shared.tools.launch import link_current, new_run_dir


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
    link_current(run)
    assert (tmp_path / CURRENT_RUN).resolve() == run.resolve()


def test_the_fresh_frame_and_soft_read_settings_refuse_nonsense() -> None:
    """robot_infer's fresh_frame_fraction is a fraction of an interval below one; slam's soft-read mode is
    one of three and its surveyed thresholds are positive: anything else fails at start-up, by name."""
    from pydantic import ValidationError

    from services.robot_infer.settings import RobotInferSettings
    from shared.slam.marker_slam import SlamSettings

    for bad in (-0.1, 1.0, 2.0):
        with pytest.raises(ValidationError, match="fresh_frame_fraction"):
            RobotInferSettings.model_validate({"fresh_frame_fraction": bad})
    for field in ("soft_reads", "tracked_reads"):
        with pytest.raises(ValidationError, match=field):
            SlamSettings.model_validate({field: "sometimes"})
    for field in ("soft_surveyed_sigma_m", "soft_surveyed_sigma_deg", "max_speed_m_s", "max_turn_deg_s"):
        with pytest.raises(ValidationError, match=field):
            SlamSettings.model_validate({field: 0.0})
    for field in ("envelope_margin_m", "envelope_margin_deg"):
        with pytest.raises(ValidationError, match=field):
            SlamSettings.model_validate({field: -1.0})
    with pytest.raises(ValidationError, match="soft_sigma_scale"):
        SlamSettings.model_validate({"soft_sigma_scale": 0.5})


_PIN_CHECK = """
import json, os, threading
from pathlib import Path
from shared.runtime.cpus import CpuPlacementError, allowed_cpus, pin_cpus

def threads():
    return [int(p.name) for p in Path("/proc/self/task").iterdir()]

gate = threading.Event()
early = threading.Thread(target=gate.wait)  # a thread that exists before the pin (Zenoh's, torch's)
early.start()
first = min(allowed_cpus())
before = pin_cpus([first])
moved = {t: sorted(os.sched_getaffinity(t)) for t in threads()}
seen = []
later = threading.Thread(target=lambda: seen.append(sorted(os.sched_getaffinity(0))))  # started after
later.start(); later.join()
try:
    pin_cpus([os.cpu_count() + 7])
    refused = ""
except CpuPlacementError as exc:
    refused = str(exc)
pin_cpus(before)
restored = sorted(allowed_cpus())
gate.set(); early.join()
print(json.dumps({"first": first, "before": sorted(before), "moved": list(moved.values()), "later": seen[0],
                  "refused": refused, "restored": restored}))
"""


def test_a_pinned_service_moves_every_thread_and_the_ones_it_starts_later() -> None:
    """`cpus` (shared.runtime.cpus) places the whole process: threads running before the pin, threads
    started after it; a CPU the host lacks is refused with the ones it has; the old set comes back."""
    import json
    import subprocess
    import sys

    out = subprocess.run([sys.executable, "-c", _PIN_CHECK], capture_output=True, text=True, check=True, timeout=60)
    got = json.loads(out.stdout)
    assert len(got["moved"]) >= 2 and all(cpus == [got["first"]] for cpus in got["moved"])
    assert got["later"] == [got["first"]]
    assert "not on this host" in got["refused"]
    assert got["restored"] == got["before"]


def test_cpus_setting_is_a_non_empty_list_of_cpu_numbers() -> None:
    assert CameraSettings(cpus=[0, 1]).cpus == [0, 1]
    assert CameraSettings().cpus is None
    for bad in ([], [-1]):
        with pytest.raises(ValueError, match="cpus"):
            CameraSettings(cpus=bad)


def test_a_cpu_the_host_lacks_stops_the_echo_with_a_clear_error() -> None:
    import os
    import subprocess
    import sys

    cpu = str((os.cpu_count() or 1) + 7)
    out = subprocess.run(
        [sys.executable, "-m", "shared.tools.cli", "echo", "--listen", "tcp/127.0.0.1:0", "--cpus", cpu],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert out.returncode == 2
    assert "not on this host" in out.stderr and "Traceback" not in out.stderr


def test_the_cli_says_a_users_mistake_in_one_line(tmp_path: Path) -> None:
    """What a person gets wrong at the prompt is one line on stderr and exit 2, not a traceback: a
    missing or malformed config file, a set without a value, a camera file that is not there."""
    import subprocess
    import sys

    bad_toml = tmp_path / "bad.toml"
    bad_toml.write_text("[camera\nfps = 1\n")
    cases = [
        (["demo", "--config", str(tmp_path / "nope.toml")], "No such file"),
        (["up", "--config", str(bad_toml), "--runs", str(tmp_path / "runs")], "not valid TOML"),
        (["split", "set"], "give k"),
        (["split", "get", "3"], "are for set"),
        (["split", "set", "9", "--connect", "tcp/127.0.0.1:1"], "split index must be an int in 0..7, got 9"),
        # a TLS endpoint without certificates (a trial got a traceback)
        (["split", "get", "--connect", "tls/127.0.0.1:7447"], "is a TLS endpoint: give --certs"),
        (["split", "get", "--connect", "tcp/127.0.0.1:7447", "--certs", str(tmp_path)], "listens on a tls/"),
        (
            ["detect", str(tmp_path), "--camera", str(tmp_path / "nope.yaml"), "--tag-size", "0.1", "--json", "o.json"],
            "nope.yaml",
        ),
    ]
    for argv, expected in cases:
        out = subprocess.run(
            [sys.executable, "-m", "shared.tools.cli", *argv], capture_output=True, text=True, timeout=120
        )
        assert out.returncode == 2, (argv, out.stderr)
        assert expected in out.stderr and "Traceback" not in out.stderr, (argv, out.stderr)
        assert len(out.stderr.strip().splitlines()) == 1, (argv, out.stderr)
    assert not (tmp_path / "runs").exists()  # refused before a run folder was made
    # Numbers the parser refuses at once (a trial's --fps 0 and --gamma 0.5 started every service first)
    runs = ["--runs", str(tmp_path / "runs")]
    for argv, expected in [
        (["up", "--fps", "0", *runs], "--fps: 0 must be > 0"),
        (["up", "--gamma", "0.5", *runs], "--gamma: 0.5 must be >= 1"),
        (["up", "--duration", "-1", *runs], "--duration: -1 must be > 0"),
        (["demo", "--fps", "nan"], "--fps: nan must be > 0"),
        (["up", "--link", "6g", *runs], "unknown link profile '6g'"),
    ]:
        out = subprocess.run(
            [sys.executable, "-m", "shared.tools.cli", *argv], capture_output=True, text=True, timeout=120
        )
        assert out.returncode == 2 and expected in out.stderr and "Traceback" not in out.stderr, (argv, out.stderr)
    assert not (tmp_path / "runs").exists()


def test_split_connects_over_tls_when_given_certificates() -> None:
    """`splittag split --certs` without --connect reaches the local edge router over TLS (it tried
    plain TCP: found by a fresh-clone trial); an endpoint given is used as it is."""
    from shared.tools.cli import split_endpoint

    assert split_endpoint(None, tls=False) == ["tcp/127.0.0.1:7447"]
    assert split_endpoint(None, tls=True) == ["tls/127.0.0.1:7447"]
    assert split_endpoint(["tcp/10.0.0.2:7447"], tls=True) == ["tcp/10.0.0.2:7447"]


def test_the_in_flight_window_asked_for_stays_that_window() -> None:
    """in_flight_limit: 6 by default; a max_in_flight set alone keeps its window fixed (a deployment
    that set 1 to bound latency or memory does not get 6); a limit below the window is refused."""
    from services.robot_infer.settings import RobotInferSettings

    assert RobotInferSettings().in_flight_limit == 6
    assert RobotInferSettings(max_in_flight=1).in_flight_limit == 1
    assert RobotInferSettings(max_in_flight=8).in_flight_limit == 8
    assert RobotInferSettings(max_in_flight=1, in_flight_limit=4).in_flight_limit == 4
    with pytest.raises(ValueError, match="in_flight_limit"):
        RobotInferSettings(max_in_flight=3, in_flight_limit=2)


def test_the_settings_reference_states_each_number_settings_bounds() -> None:
    """A contributor found the reference silent on the bounds the models check (a `gt=0` field refuses 0
    at start-up): each row now begins with them."""
    from shared.tools.settings_doc import service_rows

    rows = {r.name: r.meaning for r in service_rows("controller")}
    assert rows["probe_budget_share"].startswith("(> 0, <= 1) ")
    assert rows["decide_period_secs"].startswith("(> 0) ")
    assert not rows["enabled"].startswith("(")
