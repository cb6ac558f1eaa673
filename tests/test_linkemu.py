"""Link emulation: profiles, the delay line's bookkeeping, and `splittag link probe` recovering the
paper's 5G link (t0 = 39.9 ms, beta = 0.18 ms/kB) within 10 % on the emulated link (root only)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from shared.tools.cli import main
from shared.tools.delayline import DelayLine
from shared.tools.linkemu import PROFILES, profile, unavailable_reason


def test_profiles_match_the_paper() -> None:
    assert PROFILES["5g"].delay_ms == 39.9
    assert abs(PROFILES["5g"].beta_ms_per_kB - 0.18) < 1e-3
    assert PROFILES["5g-pre-tdd"].rate_mbit == 14.2
    assert PROFILES["unshaped"].beta_ms_per_kB == 0.0
    with pytest.raises(ValueError, match="known: 5g"):
        profile("6g")


def test_delay_line_is_fifo_and_holds_each_packet_for_the_delay() -> None:
    line = DelayLine(40.0)
    line.push(0.0, b"a")
    line.push(0.010, b"b")
    assert line.timeout(0.0) == pytest.approx(0.040)
    assert line.pop_due(0.039) == []
    assert line.pop_due(0.040) == [b"a"]
    line.set_delay_ms(5.0)  # shorter now, but b"c" must not overtake b"b"
    line.push(0.041, b"c")
    assert line.pop_due(0.046) == []
    assert line.pop_due(0.050) == [b"b", b"c"]
    assert line.state()["forwarded"] == 3
    with pytest.raises(ValueError, match="delay_ms"):
        line.set_delay_ms(-1)


@pytest.mark.multiprocess
def test_link_probe_recovers_the_5g_model(tmp_path: Path) -> None:
    reason = unavailable_reason()
    if reason is not None:
        pytest.skip(reason)
    out = tmp_path / "probe.json"
    argv = ["link", "probe", "--profile", "5g", "--prefix", "stp", "--repetitions", "6", "--json", str(out)]

    def recovered(doc: dict[str, float]) -> bool:
        return abs(doc["t0_ms"] - 39.9) <= 0.1 * 39.9 and abs(doc["beta_ms_per_kB"] - 0.18) <= 0.1 * 0.18

    # The delay line is a process on the same 2 cores: a stretch where the host gives it less CPU (seen in
    # CI and by hand: every size 2-50 ms slow for a minute, beta 0.20-0.22) slows the emulated link
    # itself, not the probe's fit. One more probe then; the fit must hold in one of the two.
    tries = []
    for _ in range(2):
        assert main([*argv, "--plot", str(tmp_path / "probe.png")]) == 0
        tries.append(json.loads(out.read_text()))
        if recovered(tries[-1]):
            break
    doc = tries[-1]
    assert recovered(doc), [(d["t0_ms"], d["beta_ms_per_kB"]) for d in tries]
    assert doc["floor_ms"] >= 39.9
    assert len(doc["samples"]) == 6 * 8
    assert (tmp_path / "probe.png").stat().st_size > 10_000


def test_profiles_load_from_toml_with_clear_errors(tmp_path: Path) -> None:
    from shared.tools.linkemu import load_profiles

    loaded = load_profiles(Path("deploy/link_profiles.example.toml"))
    assert set(loaded) == {"lte", "wifi"}
    assert profile("lte").rate_mbit == 8.0 and profile("lte").delay_ms == 25.0
    bad = tmp_path / "bad.toml"
    bad.write_text("[slow]\nrate_mbit = -1\n")
    with pytest.raises(ValueError, match=r"profile \[slow\]"):
        load_profiles(bad)
    bad.write_text("speed = 3\n")
    with pytest.raises(ValueError, match="must be a table"):
        load_profiles(bad)


def test_delay_line_control_rejects_bad_requests_and_keeps_its_delay() -> None:
    import json
    import socket

    from shared.tools.delayline import _handle_control

    line = DelayLine(39.9)
    for request, ok in ((b"not json", False), (b'{"delay_ms": -5}', False), (b'{"delay_ms": 12.5}', True)):
        ours, theirs = socket.socketpair()
        with ours:
            ours.sendall(request)
            _handle_control(theirs, line)
            answer = json.loads(ours.recv(4096))
        assert answer["ok"] is ok, (request, answer)
        if not ok:
            assert answer["error"] and line.delay_secs == pytest.approx(0.0399)
    assert line.delay_secs == pytest.approx(0.0125)


def test_demo_and_up_take_extra_link_profiles() -> None:
    """deploy/link_profiles.example.toml documents `splittag demo --link lte --link-profiles FILE`."""
    from shared.tools.cli import _load_link_profiles, build_parser

    example = Path(__file__).resolve().parent.parent / "deploy" / "link_profiles.example.toml"
    saved = dict(PROFILES)
    try:
        for command in ("demo", "up"):
            args = build_parser().parse_args([command, "--link", "lte", "--link-profiles", str(example)])
            _load_link_profiles(args)
            assert PROFILES["lte"].rate_mbit == 8.0 and PROFILES["lte"].delay_ms == 25.0
    finally:
        PROFILES.clear()
        PROFILES.update(saved)


def test_demo_and_up_set_fps_gamma_and_the_first_cut() -> None:
    """A researcher's knobs without editing a config or exporting SPLITTAG_* variables."""
    from shared.tools.cli import _launch_extra, build_parser

    for command in ("demo", "up"):
        args = build_parser().parse_args([command, "--fps", "30", "--gamma", "3", "--split-k", "0"])
        assert _launch_extra(args) == {"camera": {"fps": 30.0}, "robot_infer": {"gamma": 3.0, "split_k": 0}}
        assert _launch_extra(build_parser().parse_args([command])) == {}


def test_the_link_that_holds_an_address_is_found() -> None:
    """up() refuses a management address another link holds (a killed emulation's leftovers routed the
    next one's traffic into a dead namespace: a zenoh timeout instead of a reason)."""
    from shared.tools.linkemu import address_owner

    out = (
        "1: lo    inet 127.0.0.1/8 scope host lo\\       valid_lft forever preferred_lft forever\n"
        "7: stp-mr@if6    inet 10.78.0.1/30 scope global stp-mr\\       valid_lft forever preferred_lft forever\n"
    )
    assert address_owner(out, "10.78.0.1") == "stp-mr"
    assert address_owner(out, "10.78.0.2") is None
    assert address_owner(out, "10.78.0.10") is None
    assert address_owner("", "10.78.0.1") is None


def test_a_bad_profile_file_or_name_is_one_line_not_a_traceback(tmp_path: Path) -> None:
    """Found by a fresh-clone trial: a typo in a custom profile file, a negative rate, a missing file or an
    unknown name ended `splittag link ...` / `demo --link` in a Python traceback."""
    import subprocess
    import sys

    repo = Path(__file__).resolve().parent.parent
    bad = tmp_path / "bad.toml"
    cases = [
        ("[typo]\nrate_mbits = 8.0\n", ["link", "--profiles", str(bad), "set", "typo"], "rate_mbits"),
        ("[slow]\nrate_mbit = -3\n", ["link", "--profiles", str(bad), "set", "slow"], "rate_mbit"),
        ("[lag]\ndelay_ms = -5\n", ["demo", "--link", "lag", "--link-profiles", str(bad)], "delay_ms"),
        (None, ["link", "--profiles", str(tmp_path / "none.toml"), "set", "lte"], "cannot read link profiles"),
        (None, ["link", "set", "6g"], "unknown link profile '6g'"),
    ]
    for text, argv, said in cases:
        if text is not None:
            bad.write_text(text)
        out = subprocess.run(
            [sys.executable, "-m", "shared.tools.cli", *argv], capture_output=True, text=True, timeout=120, cwd=repo
        )
        assert out.returncode == 2, (argv, out.stdout, out.stderr)
        assert said in out.stderr and "Traceback" not in out.stderr, (argv, out.stderr)
        assert len(out.stderr.strip().splitlines()) == 1, out.stderr


def test_the_delay_line_records_each_profile_applied_in_its_run_folder_only(tmp_path: Path) -> None:
    """Whoever applies a profile (the launcher, or `splittag link set` from another shell), the request
    goes to the delay line, which appends the event to the events file of the run it was started for:
    no file in a shared folder names that run folder (a first version's /tmp state file let any local
    user point root's appends elsewhere: review). A checked event only, and never through a symlink."""
    import socket

    from shared.tools.delayline import DelayLine, _handle_control
    from shared.tools.linkemu import EVENTS_FILE, describe, read_events

    events = tmp_path / EVENTS_FILE

    def request(body: dict[str, object], path: Path | None = events) -> dict[str, object]:
        ours, theirs = socket.socketpair()
        with ours:
            ours.sendall(json.dumps(body).encode())
            _handle_control(theirs, DelayLine(39.9), path)
            answer: dict[str, object] = json.loads(ours.recv(4096))
        return answer

    def event(name: str, nanos: int) -> dict[str, object]:
        p = PROFILES[name]
        return {
            "unix_nanos": nanos,
            "profile": p.name,
            "rate_mbit": p.rate_mbit,
            "delay_ms": p.delay_ms,
            "beta_ms_per_kB": p.beta_ms_per_kB,
        }

    assert request({"delay_ms": 39.9, "event": event("5g-pre-tdd", 20)})["recorded"] is True
    assert request({"delay_ms": 39.9, "event": event("5g", 10)})["recorded"] is True
    assert request({"delay_ms": 0.0, "event": event("unshaped", 30)}, path=None)["recorded"] is False
    bad = request({"delay_ms": 39.9, "event": {**event("5g", 40), "log_dir": "/etc"}})
    assert bad["ok"] is False and "fields" in str(bad["error"])
    assert request({"delay_ms": 39.9, "event": {**event("5g", 50), "unix_nanos": "soon"}})["ok"] is False
    with events.open("a") as f:
        f.write('{"unix_nanos": 1, "prof')  # a line cut by a crash is skipped
    assert [e["profile"] for e in read_events(tmp_path)] == ["5g", "5g-pre-tdd"]  # by time, not by arrival
    assert describe(read_events(tmp_path)[1]) == "5g-pre-tdd (14.2 Mbit/s, +39.9 ms)"
    assert describe({"profile": "unshaped", "rate_mbit": None, "delay_ms": 0.0}) == "unshaped (unshaped, +0 ms)"
    assert read_events(tmp_path / "elsewhere") == []
    target = tmp_path / "precious"
    target.write_text("keep\n")
    linked = tmp_path / "linked.jsonl"
    linked.symlink_to(target)
    answer = request({"delay_ms": 39.9, "event": event("5g", 60)}, path=linked)
    assert answer["ok"] is True and answer["recorded"] is False  # the change holds, nothing written through
    assert target.read_text() == "keep\n"


@pytest.mark.multiprocess
def test_a_link_in_use_is_never_torn_down_by_a_probe_that_refuses(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A trial: `link probe --profile 5g` beside a running `link up` (or a run) said the link was in use,
    then removed it on its way out, and `link up` went on claiming a link that was gone. Now the probe
    refuses and leaves the link as it is; `link down` says what it removed, and `link up` notices that
    its link is gone and ends."""
    reason = unavailable_reason()
    if reason is not None:
        pytest.skip(reason)
    import subprocess
    import sys
    import time

    from shared.tools.linkemu import LinkEmulator, LinkEmulatorSettings, netns_pids

    prefix = "stq"
    emu = LinkEmulator(LinkEmulatorSettings(prefix=prefix))
    holder = subprocess.Popen(
        [sys.executable, "-m", "shared.tools.cli", "link", "up", "--profile", "5g", "--prefix", prefix],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        assert holder.stdout is not None
        assert holder.stdout.readline().startswith("link up:")  # printed once the link is up
        assert emu.is_up()
        argv = ["link", "probe", "--profile", "5g", "--prefix", prefix, "--repetitions", "1"]
        assert main([*argv, "--json", str(tmp_path / "p.json")]) == 2
        err = capsys.readouterr().err
        assert f"the emulated link with prefix '{prefix}' is up, held by pid {holder.pid}" in err, err
        assert emu.is_up() and holder.poll() is None  # untouched
        # A deployment's process in the link's namespace: `link down` refuses (a trial's blinded a demo)
        user = subprocess.Popen(["ip", "netns", "exec", f"{prefix}-robot", "sleep", "60"])
        try:
            deadline = time.monotonic() + 10
            while not emu.services_inside() and time.monotonic() < deadline:
                time.sleep(0.05)
            assert main(["link", "down", "--prefix", prefix]) == 1
            assert "in use by a running deployment" in capsys.readouterr().err
            assert emu.is_up()
        finally:
            user.kill()
            user.wait()
        assert main(["link", "down", "--prefix", prefix]) == 0
        assert capsys.readouterr().out.strip() == f"link {prefix} down"
        assert holder.wait(timeout=10) == 1
        assert holder.stderr is not None and "was removed by another process" in holder.stderr.read()
        assert main(["link", "down", "--prefix", prefix]) == 0
        assert capsys.readouterr().out.strip() == f"no emulated link with prefix '{prefix}' was up"
        # A `link up` killed outright leaves its link and delay line: `link down` removes both (the
        # delay line used to outlive the namespaces, in none, found by nothing: a trial)
        killed = subprocess.Popen(
            [sys.executable, "-m", "shared.tools.cli", "link", "up", "--profile", "5g", "--prefix", prefix],
            stdout=subprocess.PIPE,
            text=True,
        )
        assert killed.stdout is not None and killed.stdout.readline().startswith("link up:")
        delay_lines = [
            p for p in netns_pids(f"{prefix}-robot") if b"delayline" in Path(f"/proc/{p}/cmdline").read_bytes()
        ]
        killed.kill()
        killed.wait()
        assert delay_lines and emu.is_up()
        assert main(["link", "down", "--prefix", prefix]) == 0
        time.sleep(0.2)
        assert not any(
            Path(f"/proc/{p}").exists() and b"delayline" in Path(f"/proc/{p}/cmdline").read_bytes() for p in delay_lines
        )
    finally:
        if holder.poll() is None:
            holder.terminate()
            holder.wait(timeout=10)
        emu.down()


@pytest.mark.multiprocess
def test_down_after_a_dead_launcher_removes_its_emulated_link(tmp_path: Path) -> None:
    """A trial SIGKILLed a `--link` launcher; `splittag down` finished the run but left the namespaces and
    the delay line. Now the run's link goes too, unless something alive holds it."""
    reason = unavailable_reason()
    if reason is not None:
        pytest.skip(reason)
    import subprocess
    import sys

    from shared.tools.launch import finish_orphaned_run
    from shared.tools.linkemu import EVENTS_FILE, LinkEmulator, LinkEmulatorSettings

    emu = LinkEmulator(LinkEmulatorSettings())  # the launcher's link (the default prefix)
    run_dir = tmp_path / "run"
    run_dir.mkdir()
    (run_dir / EVENTS_FILE).write_text("")  # (the run had an emulated link)
    holder = subprocess.Popen(
        [sys.executable, "-m", "shared.tools.cli", "link", "up", "--profile", "5g"], stdout=subprocess.PIPE, text=True
    )
    try:
        assert holder.stdout is not None and holder.stdout.readline().startswith("link up:")
        live = finish_orphaned_run(run_dir, [])
        assert live["emulated_link"].startswith("left up") and emu.is_up()  # its owner runs: not ours to remove
        holder.kill()  # the owner dies as a killed launcher does
        holder.wait()
        orphaned = finish_orphaned_run(run_dir, [])
        assert orphaned["emulated_link"] == "removed by `splittag down`" and not emu.is_up()
    finally:
        if holder.poll() is None:
            holder.kill()
            holder.wait()
        emu.down()


def test_link_probe_connects_to_a_running_deployments_edge(tmp_path: Path) -> None:
    """`link probe --connect` against a deployment's edge, whose edge_infer serves the echo under its own
    token (a two-host trial's probe waited for `splittag echo`'s token alone, 30 s, then a traceback);
    with nothing there it says so in one line."""
    import subprocess
    import sys

    from shared.transport.probe import serve_echo
    from shared.transport.session import ZenohSettings, free_tcp_port, open_session
    from shared.wire import keys

    endpoint = f"tcp/127.0.0.1:{free_tcp_port()}"
    edge = open_session(ZenohSettings(mode="router", listen=[endpoint]))
    try:
        echo = serve_echo(edge, keys.echo("probe9"), max_bytes=64 << 20)
        token = edge.liveliness().declare_token(keys.alive("probe9", "edge_infer"))  # as edge_infer does
        out = tmp_path / "samples.json"
        args = ["link", "probe", "--connect", endpoint, "--robot-id", "probe9", "--repetitions", "1"]
        assert main([*args, "--tags", "1", "--samples-out", str(out)]) == 0
        samples = json.loads(out.read_text())
        assert samples and all(rtt > 0 for _, rtt in samples)
        token.undeclare()
        echo.undeclare()
    finally:
        edge.close()
    empty = open_session(ZenohSettings(mode="router", listen=[endpoint]))  # an edge without an echo
    try:
        nobody = subprocess.run(
            [sys.executable, "-m", "shared.tools.cli", "link", "probe", "--connect", endpoint, "--robot-id",
             "probe9", "--wait-secs", "1"],
            capture_output=True, text=True, timeout=120,
        )  # fmt: skip
    finally:
        empty.close()
    assert nobody.returncode == 1 and "Traceback" not in nobody.stderr, nobody.stderr
    assert f"no echo for probe9 behind {endpoint} within 1 s" in nobody.stderr, nobody.stderr


def test_the_paper_cost_model_is_eq4_over_cuts_1_to_7_without_edge_compute() -> None:
    """A researcher could not print the paper's Eq. 4: `link cost` always had k = 0 (the raw ROI, a cut the
    paper does not have) and E(k). With `paper`, T(k) = gamma C(k) + t0 + beta S(k) over k = 1..7."""
    from shared.control.linkmodel import LinkFit
    from shared.tools.linkprobe import FULL_MODEL, PAPER_MODEL, cost_table

    fit = LinkFit(40.0, 0.2, 40.0, 0.0, 8)
    compute = [0.0, 10.0, 12.0, 14.0, 16.0, 18.0, 19.0, 20.0]
    edge = [30.0, 25.0, 20.0, 15.0, 10.0, 5.0, 2.0, 0.0]
    payload = [64.0, 1024.0, 512.0, 256.0, 128.0, 32.0, 8.0, 0.1]
    paper = cost_table(compute_ms=compute, edge_ms=None, payload_kB=payload, fit=fit, gammas=[1.0, 8.0], paper=True)
    assert paper["model"] == PAPER_MODEL and paper["k"] == [1, 2, 3, 4, 5, 6, 7] and paper["E_ms"] is None
    for row in paper["gammas"]:
        expected = [row["gamma"] * compute[k] + 40.0 + 0.2 * payload[k] for k in range(1, 8)]
        assert row["T_ms"] == pytest.approx(expected)
        assert row["best_k"] == 1 + expected.index(min(expected))  # a k, not an index
    # the same with E(k) given: still not used by the paper's model
    with_edge = cost_table(compute_ms=compute, edge_ms=edge, payload_kB=payload, fit=fit, gammas=[1.0], paper=True)
    assert with_edge["gammas"][0]["T_ms"] == paper["gammas"][0]["T_ms"]
    full = cost_table(compute_ms=compute, edge_ms=edge, payload_kB=payload, fit=fit, gammas=[8.0])
    assert full["model"] == FULL_MODEL and full["k"] == list(range(8))
    assert full["gammas"][0]["T_ms"][0] == pytest.approx(0.0 + 40.0 + 0.2 * 64.0 + 30.0)
    assert full["gammas"][0]["best_k"] == 0  # the raw ROI wins on a slow robot: the cut the paper lacks
    with pytest.raises(ValueError, match="needs edge_ms"):
        cost_table(compute_ms=compute, edge_ms=None, payload_kB=payload, fit=fit, gammas=[1.0])


def test_link_cost_paper_says_which_model_it_printed(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    repo = Path(__file__).resolve().parents[1]
    out = tmp_path / "cost.json"
    argv = ["link", "cost", "--link", str(repo / "docs" / "link_5g.json"), "--paper", "--gamma", "1", "4"]
    assert main([*argv, "--repetitions", "2", "--json", str(out)]) == 0
    printed = capsys.readouterr().out
    assert printed.startswith("CPU: ")
    assert "model: T(k) = gamma C(k) + t0 + beta S(k), k = 1..7 (the paper's Eq. 4)" in printed
    rows = [line.split()[0] for line in printed.splitlines() if line[:2].strip().isdigit()]
    assert rows == [str(k) for k in range(1, 8)]
    doc = json.loads(out.read_text())
    assert doc["k"] == list(range(1, 8)) and doc["E_ms"] is None and len(doc["C_measured_ms"]) == 7


def test_up_link_takes_the_links_names_addresses_and_ports_from_the_config(tmp_path: Path) -> None:
    """A researcher could not run `up --link` on other ports or beside a second emulation: the launcher
    built the link with prefix st, 10.77/10.78 and ports 7447/7448 whatever the config said. The config's
    [link] table now names the link and its addresses, its routers' listen endpoints give the ports (pure:
    nothing is brought up)."""
    from shared.tools.launch import _placement

    repo = Path(__file__).resolve().parents[1]
    config = tmp_path / "mine.toml"
    config.write_text(
        (repo / "deploy" / "local.toml").read_text().replace(":7447", ":34447").replace(":7448", ":34448")
        + '\n[link]\nprefix = "fr"\nrobot_addr = "10.91.0.1"\nedge_addr = "10.91.0.2"\n'
        'mgmt_root_addr = "10.92.0.5"\nmgmt_edge_addr = "10.92.0.6"\n'
    )
    services = ("camera", "robot_infer", "edge_infer", "slam", "controller")
    topology, wrappers, emu = _placement(config, services, "5g")
    assert emu is not None
    s = emu.settings
    assert (s.prefix, s.robot_ns, s.edge_ns, s.uplink_dev, s.tun_dev) == (
        "fr",
        "fr-robot",
        "fr-edge",
        "fr-vr",
        "fr-tun",
    )
    assert (s.robot_addr, s.edge_addr, s.mgmt_root_addr, s.mgmt_edge_addr) == (
        "10.91.0.1",
        "10.91.0.2",
        "10.92.0.5",
        "10.92.0.6",
    )
    tables = topology.zenoh_tables()
    assert tables["edge_infer"]["zenoh"]["listen"] == ["tcp/0.0.0.0:34447"]
    assert tables["robot_infer"]["zenoh"]["listen"] == ["tcp/127.0.0.1:34448"]
    assert tables["robot_infer"]["zenoh"]["connect"] == ["tcp/10.91.0.2:34447"]
    assert tables["camera"]["zenoh"]["connect"] == ["tcp/127.0.0.1:34448"]
    assert tables["monitor"]["connect"] == ["tcp/10.92.0.6:34447"]
    assert wrappers["robot_infer"] == ["ip", "netns", "exec", "fr-robot"]
    assert wrappers["controller"] == ["ip", "netns", "exec", "fr-robot"]
    assert wrappers["slam"] == ["ip", "netns", "exec", "fr-edge"]
    # without a [link] table: the defaults, still on the config's ports
    config.write_text(config.read_text().split("\n[link]")[0])
    topology, _, emu = _placement(config, services, "5g")
    assert emu is not None and emu.settings.prefix == "st" and emu.settings.edge_addr == "10.77.0.2"
    assert topology.zenoh_tables()["robot_infer"]["zenoh"]["connect"] == ["tcp/10.77.0.2:34447"]


@pytest.mark.parametrize(
    ("table", "said"),
    [
        ('prefix = "toolong"', "prefix: String should match pattern"),  # <prefix>-tun must fit 15 characters
        ('prefix = "St"', "prefix: String should match pattern"),
        ('edge_addr = "10.77.0.5"', "the uplink veth's two addresses 10.77.0.1 and 10.77.0.5 must be two addresses"),
        (
            'mgmt_root_addr = "10.77.0.1"\nmgmt_edge_addr = "10.77.0.2"',
            "in different /30 subnets, both are 10.77.0.0/30",
        ),
        ('robot_addr = "10.77.0.3"\nedge_addr = "10.77.0.2"', "10.77.0.3 is the network or broadcast address"),
        ('edge_addr = "10.77.0.256"', "edge_addr: Value error, Octet 256"),
        ("rate = 3", "rate: Extra inputs are not permitted"),
    ],
)
def test_a_bad_link_table_is_refused_in_one_line_before_anything_starts(tmp_path: Path, table: str, said: str) -> None:
    from shared.tools.launch import LaunchError, _placement

    config = tmp_path / "bad.toml"
    config.write_text(f"[link]\n{table}\n")
    with pytest.raises(LaunchError) as refused:
        _placement(config, ("camera", "robot_infer", "edge_infer", "slam"), "5g")
    assert refused.value.exit_code == 2
    message = str(refused.value)
    assert message.startswith(f"{config}: [link] ") and said in message and "\n" not in message, message
