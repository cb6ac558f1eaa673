"""Emulated robot -> edge uplink: two network namespaces joined by a veth pair, tbf for the rate and a
user-space delay line (TUN device, shared/tools/delayline.py) for the latency floor.

    robot netns  (10.77.0.1)                                     edge netns (10.77.0.2)
    app --(ip rule: iif lo, to edge)--> TUN -> delay line -> TUN --forward--> veth [tbf] ======> veth
    app <------------------------------------------------------------------------------------ veth
                                                          root netns (10.78.0.1) <== mgmt veth ==> (10.78.0.2)

Only the uplink is shaped, as in the paper's measurement (probes carry the payload up, a tiny reply
comes back), so RTT(S) = t0 + beta * S with t0 the delay line's floor and beta = 8 bits / rate.
The management veth lets tools in the root namespace (tests, the demo's monitor) reach the edge
router without touching the shaped path. TCP in both namespaces uses reno and keeps its window
across idle gaps (BBR's probing adds latency on a 40 ms link; cubic is not allowed per namespace).
Shared memory never crosses a namespace (and is off in every splittag session anyway).
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import shutil
import subprocess
import sys
import tempfile
import time
from collections.abc import Mapping
from ipaddress import IPv4Address, IPv4Interface
from pathlib import Path
from types import TracebackType
from typing import Any

from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

from shared.tools.delayline import control_request

log = logging.getLogger(__name__)

BITS_PER_KB = 8 * 1024
EVENTS_FILE = "link_events.jsonl"  # in the emulator's log folder (a run's folder): every profile applied


class LinkProfileError(ValueError):
    """A link profile that does not exist or a profile file that cannot be used: said in one line."""


class LinkProfile(BaseModel):
    """One link condition: uplink rate (None = unshaped) and the added one-way floor delay."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    name: str
    rate_mbit: float | None = Field(default=None, gt=0)
    delay_ms: float = Field(default=0.0, ge=0, le=10_000)
    description: str = ""

    @property
    def beta_ms_per_kB(self) -> float:
        """The serialisation slope this rate gives: ms per kB (1024 bytes)."""
        return 0.0 if self.rate_mbit is None else BITS_PER_KB / (self.rate_mbit * 1e6) * 1e3


def _rate_for_beta(beta_ms_per_kB: float) -> float:
    return BITS_PER_KB / (beta_ms_per_kB * 1e-3) / 1e6


PROFILES: dict[str, LinkProfile] = {
    p.name: p
    for p in (
        LinkProfile(
            name="5g",
            rate_mbit=round(_rate_for_beta(0.18), 2),
            delay_ms=39.9,
            description="the paper's measured 5G uplink (IV-B): t0 = 39.9 ms, beta = 0.18 ms/kB",
        ),
        LinkProfile(
            name="5g-pre-tdd",
            rate_mbit=14.2,
            delay_ms=39.9,
            description="the uplink before TDD rebalancing: about 14.2 Mbit/s, same floor",
        ),
        LinkProfile(name="unshaped", description="veth at full speed, no added delay"),
    )
}


def read_events(folder: Path) -> list[dict[str, Any]]:
    """The link profiles applied during a run (folder's link_events.jsonl), oldest first; [] without."""
    path = folder / EVENTS_FILE
    if not path.is_file():
        return []
    events = []
    for line in path.read_text().splitlines():
        try:
            event = json.loads(line)
        except ValueError:
            continue  # a line cut by a crash
        if isinstance(event, dict) and isinstance(event.get("unix_nanos"), int):
            events.append(event)
    return sorted(events, key=lambda e: e["unix_nanos"])


def describe(event: dict[str, Any]) -> str:
    """One line for a person: `5g-pre-tdd (14.2 Mbit/s, +39.9 ms)`."""
    rate = f"{event['rate_mbit']:g} Mbit/s" if event.get("rate_mbit") else "unshaped"
    return f"{event['profile']} ({rate}, +{event.get('delay_ms', 0.0):g} ms)"


def load_profiles(path: Path) -> dict[str, LinkProfile]:
    """Profiles from a TOML file, one table per profile, e.g.

        [lte-uplink]
        rate_mbit = 8.0
        delay_ms = 25.0
        description = "a congested LTE uplink"

    They add to (or replace) the built-in ones in PROFILES; a bad entry raises a LinkProfileError naming it.
    """
    import tomllib

    from pydantic import ValidationError

    from shared.runtime.errors import one_line_error

    try:
        doc = tomllib.loads(path.read_text())
    except (OSError, tomllib.TOMLDecodeError) as exc:
        raise LinkProfileError(f"cannot read link profiles from {path}: {exc}") from exc
    out = {}
    for name, values in doc.items():
        if not isinstance(values, dict):
            raise LinkProfileError(f"{path}: [{name}] must be a table of rate_mbit / delay_ms / description")
        try:
            out[name] = LinkProfile(name=name, **values)
        except ValidationError as exc:
            raise LinkProfileError(
                f"{path}: profile [{name}]: {one_line_error(exc)} "
                "(a profile takes rate_mbit > 0 or none, delay_ms 0-10000, description)"
            ) from None
    PROFILES.update(out)
    return out


def profile(name: str) -> LinkProfile:
    """A named profile (built in, or added by load_profiles), or a LinkProfileError listing the names."""
    try:
        return PROFILES[name]
    except KeyError:
        raise LinkProfileError(f"unknown link profile {name!r}; known: {', '.join(PROFILES)}") from None


def netns_pids(ns: str) -> list[int]:
    """The processes inside network namespace `ns` (none when it does not exist)."""
    out = _run(["ip", "netns", "pids", ns], check=False).stdout
    return [int(t) for t in out.split() if t.isdigit()]


def _is_delay_line(pid: int) -> bool:
    try:
        return b"shared.tools.delayline" in Path(f"/proc/{pid}/cmdline").read_bytes()
    except OSError:
        return False


def delay_line_owner(pid: int) -> int | None:
    """The live process that started delay line `pid` (`link up`, a launcher, a bench; its
    `--owner-pid`), or None when that process is gone: a crashed run's leftover. A pid reused since, or
    a dead owner not yet reaped, is not the owner: the owner started before its delay line and runs."""
    try:
        args = Path(f"/proc/{pid}/cmdline").read_bytes().split(b"\0")
    except OSError:
        return None
    if b"--owner-pid" not in args:
        return None  # (started by an older version: taken for a leftover, as before)
    try:
        owner = int(args[args.index(b"--owner-pid") + 1])
    except (IndexError, ValueError):
        return None
    mine, theirs = _stat(pid), _stat(owner)
    if mine is None or theirs is None or theirs[0] == "Z" or theirs[1] > mine[1]:
        return None
    return owner


def _stat(pid: int) -> tuple[str, int] | None:
    """(state, start time in clock ticks since boot) of a process, None when it is gone."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
        return fields[0], int(fields[19])
    except (OSError, IndexError, ValueError):
        return None


def _describe(pid: int) -> str:
    try:
        words = Path(f"/proc/{pid}/cmdline").read_bytes().split(b"\0")
    except OSError:
        return f"pid {pid}"
    text = " ".join(w.decode(errors="replace") for w in words if w)
    return f"pid {pid}: {text[:120]}"


DEFAULT_PREFIX = "st"
LINK_TABLE = "link"  # a run config's table of the emulated link's settings (`splittag up --link`)


class LinkEmulatorSettings(BaseModel):
    """Names and addresses of the emulated link. A prefix keeps the namespaces and links of parallel
    emulations apart; the management address lives in the root namespace, so parallel emulations also
    need their own `mgmt_root_addr` / `mgmt_edge_addr` (up() refuses an address another link holds).
    A run config's `[link]` table sets them for `splittag up/demo --link` (`from_config_doc`)."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    prefix: str = Field(
        default=DEFAULT_PREFIX,
        # (<prefix>-tun and the other device names must fit Linux's 15-character interface names)
        pattern=r"^[a-z0-9]{1,6}$",
        description="names the namespaces (<prefix>-robot, <prefix>-edge) and the link's devices "
        "(<prefix>-vr, -ve, -mr, -me, -tun); 1-6 lowercase letters or digits",
    )
    robot_addr: str = Field(default="10.77.0.1", description="the robot's end of the uplink")
    edge_addr: str = Field(default="10.77.0.2", description="the edge's end of the uplink (the same /30 as robot_addr)")
    mgmt_root_addr: str = Field(default="10.78.0.1", description="the root namespace's end of the management veth")
    mgmt_edge_addr: str = Field(
        default="10.78.0.2",
        description="the edge's end of the management veth (the same /30 as mgmt_root_addr; tools reach the "
        "edge's router here)",
    )
    mtu: int = Field(default=4000, ge=1280, le=65000)
    tbf_limit_bytes: int = Field(default=8 * 1024 * 1024, gt=0)  # deep enough that TCP never sees a drop

    @field_validator("robot_addr", "edge_addr", "mgmt_root_addr", "mgmt_edge_addr")
    @classmethod
    def _ipv4(cls, value: str) -> str:
        return str(IPv4Address(value))  # (a ValueError names what is not an IPv4 address)

    @model_validator(mode="after")
    def _two_distinct_subnets(self) -> LinkEmulatorSettings:
        """The uplink's ends share a /30, the management veth's ends another: each pair must be two host
        addresses of one /30 (not its network or broadcast address), and the two /30s must differ (the
        same subnet on both veths would route the tools' traffic onto the shaped link, or nowhere)."""
        pairs = {"uplink": (self.robot_addr, self.edge_addr), "management": (self.mgmt_root_addr, self.mgmt_edge_addr)}
        nets = {}
        for name, (a, b) in pairs.items():
            net = IPv4Interface(f"{a}/30").network
            if IPv4Interface(f"{b}/30").network != net or a == b:
                raise ValueError(f"the {name} veth's two addresses {a} and {b} must be two addresses of one /30")
            for addr in (a, b):
                if IPv4Address(addr) in (net.network_address, net.broadcast_address):
                    raise ValueError(f"{addr} is the network or broadcast address of {net}: not usable on a veth")
            nets[name] = net
        if nets["uplink"] == nets["management"]:
            raise ValueError(
                f"the uplink and the management veth must be in different /30 subnets, both are {nets['uplink']}"
            )
        return self

    @classmethod
    def from_config_doc(cls, doc: Mapping[str, Any], *, source: str = "the config") -> LinkEmulatorSettings:
        """The link's settings from a run config's `[link]` table (defaults where it has none); a bad one
        raises LinkProfileError in one line, naming the table."""
        from pydantic import ValidationError

        from shared.runtime.errors import one_line_error

        table = doc.get(LINK_TABLE, {})
        if not isinstance(table, Mapping):
            raise LinkProfileError(f"{source}: [{LINK_TABLE}] must be a table (prefix, robot_addr, edge_addr, ...)")
        try:
            return cls(**table)
        except ValidationError as exc:
            raise LinkProfileError(f"{source}: [{LINK_TABLE}] {one_line_error(exc)}") from None

    @classmethod
    def from_config(cls, config: Path) -> LinkEmulatorSettings:
        """from_config_doc of a TOML file."""
        import tomllib

        return cls.from_config_doc(tomllib.loads(Path(config).read_text()), source=str(config))

    @property
    def robot_ns(self) -> str:
        return f"{self.prefix}-robot"

    @property
    def edge_ns(self) -> str:
        return f"{self.prefix}-edge"

    @property
    def uplink_dev(self) -> str:
        return f"{self.prefix}-vr"

    @property
    def tun_dev(self) -> str:
        return f"{self.prefix}-tun"

    @property
    def control_path(self) -> Path:
        return Path(tempfile.gettempdir()) / f"splittag-{self.prefix}-delay.sock"


class LinkEmulationUnavailable(RuntimeError):
    """Namespaces, veth, TUN or tc cannot be used here (not root, no iproute2, ...)."""


def _run(argv: list[str], *, check: bool = True) -> subprocess.CompletedProcess[str]:
    result = subprocess.run(argv, capture_output=True, text=True, timeout=30)
    if check and result.returncode != 0:
        raise RuntimeError(f"{' '.join(argv)} failed: {result.stderr.strip()}")
    return result


def address_owner(ip_addr_output: str, addr: str) -> str | None:
    """The link that holds IPv4 `addr`, from `ip -o -4 addr show` output (None: no link holds it)."""
    for line in ip_addr_output.splitlines():
        fields = line.split()
        # "7: stp-mr    inet 10.78.0.1/30 scope global stp-mr\       valid_lft forever ..."
        if len(fields) >= 4 and fields[2] == "inet" and fields[3].split("/")[0] == addr:
            return fields[1].split("@")[0]
    return None


def in_netns(ns: str, argv: list[str]) -> list[str]:
    """argv run inside network namespace `ns`."""
    return ["ip", "netns", "exec", ns, *argv]


def unavailable_reason() -> str | None:
    """Why link emulation cannot run here, or None when it can."""
    if os.geteuid() != 0:
        return "link emulation needs root (network namespaces, veth, TUN, tc)"
    for tool in ("ip", "tc"):
        if shutil.which(tool) is None:
            return f"link emulation needs `{tool}` (iproute2)"
    if not Path("/dev/net/tun").exists():
        return "link emulation needs /dev/net/tun"
    probe = f"stprobe{os.getpid() % 100000}"
    made = _run(["ip", "netns", "add", probe], check=False)
    if made.returncode != 0:
        return f"cannot create a network namespace: {made.stderr.strip()}"
    _run(["ip", "netns", "del", probe], check=False)
    return None


class LinkEmulator:
    """Bring the emulated link up (context manager), switch profiles live, tear it down."""

    def __init__(self, settings: LinkEmulatorSettings | None = None, *, log_dir: Path | None = None) -> None:
        self.settings = settings or LinkEmulatorSettings()
        self.log_dir = log_dir
        self._delay: subprocess.Popen[bytes] | None = None
        # Whether up() took this prefix's namespaces over: only then does leaving the `with` block tear
        # them down (a refused up() used to remove the running link it refused to touch: a trial).
        self.owned = False

    # -- lifecycle -------------------------------------------------------------------------------
    def refuse_if_in_use(self) -> list[int]:
        """LinkEmulationUnavailable if a running deployment's processes are in this emulation's namespaces:
        tearing them down as leftovers cut that run's link, and its monitor then read the new run's
        frames (a trial's second `up --link` did both). Returns the pids of a crashed run's delay line
        there, the one process a dead run leaves behind."""
        s = self.settings
        users = {ns: netns_pids(ns) for ns in (s.robot_ns, s.edge_ns)}
        services = {ns: [p for p in pids if not _is_delay_line(p)] for ns, pids in users.items()}
        if any(services.values()):
            held = "; ".join(f"{ns}: pids {' '.join(map(str, p))}" for ns, p in services.items() if p)
            raise LinkEmulationUnavailable(
                f"the emulated link's namespaces are in use by a running deployment ({held}): stop it first "
                "(`splittag down`)"
            )
        # A delay line whose starter still runs is a link in use (`splittag link up`, a launcher, a
        # bench): a probe took it for a leftover, and the live link vanished under its owner (a trial).
        owners = {o for pids in users.values() for p in pids if (o := delay_line_owner(p)) is not None}
        owners.discard(os.getpid())
        if owners:
            holders = "; ".join(map(_describe, sorted(owners)))
            raise LinkEmulationUnavailable(
                f"the emulated link with prefix {s.prefix!r} is up, held by {holders}: "
                "stop that process or remove the link (`splittag link down`) first; `splittag link set "
                "PROFILE` switches it as it is"
            )
        return [p for pids in users.values() for p in pids]

    def up(self, initial: LinkProfile) -> LinkEmulator:
        """Create namespaces, links, routes and the delay line, then apply `initial`."""
        reason = unavailable_reason()
        if reason is not None:
            raise LinkEmulationUnavailable(reason)
        s = self.settings
        for pid in self.refuse_if_in_use():  # a crashed run's delay line (it runs in a session of its own)
            with contextlib.suppress(OSError):
                os.kill(pid, 9)
        self.owned = True
        self.down()  # leftovers of a crashed run with the same prefix
        owner = address_owner(_run(["ip", "-o", "-4", "addr", "show"], check=False).stdout, s.mgmt_root_addr)
        if owner is not None:
            # Another emulation (or a killed one's leftovers) would take this one's management traffic:
            # its processes would time out connecting instead of saying why.
            raise LinkEmulationUnavailable(
                f"{s.mgmt_root_addr} is already on link {owner}: another link emulation is up, or a killed one "
                f"left it (remove it: ip link del {owner}, and its namespaces), or give this one other "
                "mgmt_root_addr / mgmt_edge_addr"
            )
        r, e = s.robot_ns, s.edge_ns
        mr, me, ve = f"{s.prefix}-mr", f"{s.prefix}-me", f"{s.prefix}-ve"
        try:
            for argv in (
                ["ip", "netns", "add", r],
                ["ip", "netns", "add", e],
                ["ip", "link", "add", s.uplink_dev, "type", "veth", "peer", "name", ve],
                ["ip", "link", "set", s.uplink_dev, "netns", r],
                ["ip", "link", "set", ve, "netns", e],
                ["ip", "link", "add", mr, "type", "veth", "peer", "name", me],
                ["ip", "link", "set", me, "netns", e],
                ["ip", "addr", "add", f"{s.mgmt_root_addr}/30", "dev", mr],
                ["ip", "link", "set", mr, "up"],
                *(
                    in_netns(r, a)
                    for a in (
                        ["ip", "link", "set", "lo", "up"],
                        ["ip", "addr", "add", f"{s.robot_addr}/30", "dev", s.uplink_dev],
                        ["ip", "link", "set", s.uplink_dev, "mtu", str(s.mtu), "up"],
                        ["ip", "tuntap", "add", "dev", s.tun_dev, "mode", "tun"],
                        ["ip", "link", "set", s.tun_dev, "mtu", str(s.mtu), "up"],
                        # Local traffic to the edge goes into the TUN device (the delay line) ...
                        [
                            "ip",
                            "route",
                            "add",
                            f"{s.edge_addr}/32",
                            "dev",
                            s.tun_dev,
                            "src",
                            s.robot_addr,
                            "table",
                            "77",
                        ],
                        ["ip", "rule", "add", "iif", "lo", "to", f"{s.edge_addr}/32", "table", "77", "pref", "100"],
                        # ... and comes back out of it to be forwarded onto the shaped veth.
                        [
                            "sysctl",
                            "-qw",
                            "net.ipv4.ip_forward=1",
                            "net.ipv4.conf.all.rp_filter=0",
                            "net.ipv4.conf.default.rp_filter=0",
                            f"net.ipv4.conf.{s.tun_dev}.rp_filter=0",
                            f"net.ipv4.conf.{s.tun_dev}.accept_local=1",
                            "net.ipv4.tcp_congestion_control=reno",
                            "net.ipv4.tcp_slow_start_after_idle=0",
                        ],
                    )
                ),
                *(
                    in_netns(e, a)
                    for a in (
                        ["ip", "link", "set", "lo", "up"],
                        ["ip", "addr", "add", f"{s.edge_addr}/30", "dev", ve],
                        ["ip", "link", "set", ve, "mtu", str(s.mtu), "up"],
                        ["ip", "addr", "add", f"{s.mgmt_edge_addr}/30", "dev", me],
                        ["ip", "link", "set", me, "up"],
                        [
                            "sysctl",
                            "-qw",
                            "net.ipv4.tcp_congestion_control=reno",
                            "net.ipv4.tcp_slow_start_after_idle=0",
                        ],
                    )
                ),
            ):
                _run(argv)
            self._start_delay_line(initial.delay_ms)
            self.set_profile(initial)
        except BaseException:
            self.down()
            raise
        return self

    def _start_delay_line(self, delay_ms: float) -> None:
        s = self.settings
        s.control_path.unlink(missing_ok=True)
        out = (self.log_dir / "delayline.log").open("wb") if self.log_dir else subprocess.DEVNULL
        self._delay = subprocess.Popen(
            in_netns(
                s.robot_ns,
                [
                    sys.executable,
                    "-m",
                    "shared.tools.delayline",
                    "--tun",
                    s.tun_dev,
                    "--delay-ms",
                    str(delay_ms),
                    "--control",
                    str(s.control_path),
                    "--owner-pid",
                    str(os.getpid()),
                    *(["--events", str(Path(self.log_dir).resolve() / EVENTS_FILE)] if self.log_dir else []),
                ],
            ),
            stdout=out,
            stderr=subprocess.STDOUT,
            start_new_session=True,
            cwd=Path(__file__).resolve().parents[2],
        )
        deadline = time.monotonic() + 20
        while not s.control_path.exists():
            if self._delay.poll() is not None or time.monotonic() > deadline:
                raise RuntimeError("the delay line did not start (see delayline.log)")
            time.sleep(0.05)

    def set_profile(self, p: LinkProfile) -> None:
        """Switch the link live: tbf rate on the uplink veth, floor delay in the delay line."""
        s = self.settings
        applied_nanos = time.time_ns()  # the change starts now: a frame sent from here may meet it
        if not s.control_path.exists():
            raise LinkEmulationUnavailable(
                f"no emulated link with prefix {s.prefix!r} is up (start one with `splittag link up`)"
            )
        delay_lines = [p for ns in (s.robot_ns, s.edge_ns) for p in netns_pids(ns) if _is_delay_line(p)]
        if delay_lines and self._delay is None and all(delay_line_owner(p) is None for p in delay_lines):
            log.warning(
                "the emulated link with prefix %r has no owner any more (its `link up` or launcher was killed): "
                "switched all the same; `splittag link down` removes it",
                s.prefix,
            )
        if p.rate_mbit is None:
            _run(in_netns(s.robot_ns, ["tc", "qdisc", "del", "dev", s.uplink_dev, "root"]), check=False)
        else:
            burst = s.mtu + 1000  # one packet: a bigger bucket would shave burst/rate off the floor
            _run(
                in_netns(
                    s.robot_ns,
                    [
                        "tc",
                        "qdisc",
                        "replace",
                        "dev",
                        s.uplink_dev,
                        "root",
                        "tbf",
                        "rate",
                        f"{p.rate_mbit}mbit",
                        "burst",
                        str(burst),
                        "limit",
                        str(s.tbf_limit_bytes),
                    ],
                )
            )
        event = {
            "unix_nanos": applied_nanos,
            "profile": p.name,
            "rate_mbit": p.rate_mbit,
            "delay_ms": p.delay_ms,
            "beta_ms_per_kB": p.beta_ms_per_kB,
        }
        # The delay line records the event in the run folder it was started for (the launcher's), whoever
        # applies the profile: no file outside the run names that folder.
        control_request(s.control_path, {"delay_ms": p.delay_ms, "event": event})
        rate = f"{p.rate_mbit} Mbit/s" if p.rate_mbit else "unshaped"
        log.info("link profile %s: rate %s, delay %.1f ms", p.name, rate, p.delay_ms)

    def services_inside(self) -> list[int]:
        """The processes in this link's namespaces other than its delay line: a deployment using it."""
        s = self.settings
        return [p for ns in (s.robot_ns, s.edge_ns) for p in netns_pids(ns) if not _is_delay_line(p)]

    def down(self) -> None:
        """Remove everything (idempotent), another process's delay line included (a link whose `link up`
        or launcher was killed: its delay line outlived the namespaces, in none, found by nothing)."""
        s = self.settings
        if self._delay is not None and self._delay.poll() is None:
            os.killpg(self._delay.pid, 15)
            try:
                self._delay.wait(timeout=5)
            except subprocess.TimeoutExpired:
                os.killpg(self._delay.pid, 9)
                self._delay.wait()
        self._delay = None
        for ns in (s.robot_ns, s.edge_ns):
            for pid in netns_pids(ns):
                if _is_delay_line(pid):
                    with contextlib.suppress(OSError):
                        os.kill(pid, 9)
        for ns in (s.robot_ns, s.edge_ns):
            _run(["ip", "netns", "del", ns], check=False)
        _run(["ip", "link", "del", f"{s.prefix}-mr"], check=False)
        s.control_path.unlink(missing_ok=True)

    def __enter__(self) -> LinkEmulator:
        return self

    def __exit__(self, *exc: tuple[type[BaseException] | None, BaseException | None, TracebackType | None]) -> None:
        if self.owned:
            self.down()

    def is_up(self) -> bool:
        """Whether this prefix's namespaces exist and, when this process started the delay line, it runs
        (a live `link up` checks it: another process may have removed the link under it)."""
        s = self.settings
        listed = _run(["ip", "netns", "list"], check=False).stdout.split()
        if s.robot_ns not in listed or s.edge_ns not in listed:
            return False
        return self._delay is None or self._delay.poll() is None
