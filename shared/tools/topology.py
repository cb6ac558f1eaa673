"""The deployment topology in one place: which Zenoh endpoint each service listens on or connects to,
and the run config written from a deploy TOML with it.

Every deployment has the same shape: the edge runs a router (edge_infer) that slam joins; the robot
runs its own router (robot_infer, so camera frames never leave the robot) that connects to the edge
and that the camera and the controller join; tools (monitor, tests, benches) reach the edge router.
Where the edge side can reach the robot's router too (one host, or two hosts whose robot router
listens on an address the edge reaches), slam and the monitor have it as their second endpoint: a
client fails over to it while edge_infer (and its router) is away, so the poses the robot computes on
board still reach them. A client does not fail back: it stays on the robot's router until that one
goes. Only the addresses differ: loopback on fixed or free ports, two hosts, or the
emulated link's namespaces. The launcher, link emulation, benchmarks and tests all build their configs
here.
"""

from __future__ import annotations

import json
import tomllib
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Final

from shared.transport.session import free_tcp_port

EDGE_PORT: Final[int] = 7447
ROBOT_PORT: Final[int] = 7448
ROBOT_SIDE: Final[tuple[str, ...]] = ("camera", "robot_infer", "controller")
EDGE_SIDE: Final[tuple[str, ...]] = ("edge_infer", "slam")
LOOPBACK_HOSTS: Final[frozenset[str]] = frozenset({"127.0.0.1", "localhost", "[::1]", "::1"})


@dataclass(frozen=True)
class Topology:
    """Endpoints of one deployment (hosts as seen from where each connection starts)."""

    edge_port: int = EDGE_PORT
    robot_port: int = ROBOT_PORT
    edge_bind: str = "127.0.0.1"  # the edge router listens here
    robot_bind: str = "127.0.0.1"  # the robot router listens here (robot-local bus)
    edge_from_robot: str = "127.0.0.1"  # how the robot router reaches the edge router
    edge_from_tools: str = "127.0.0.1"  # how tools (monitor, tests, benches) reach the edge router
    protocol: str = "tcp"  # "tls" for deploy/secure.toml (every process then needs its certificate)

    @classmethod
    def loopback(cls, protocol: str = "tcp") -> Topology:
        """Everything on this host, on free ports (tests and benchmarks run side by side)."""
        return cls(edge_port=free_tcp_port(), robot_port=free_tcp_port(), protocol=protocol)

    @classmethod
    def emulated_link(
        cls,
        *,
        edge_addr: str,
        mgmt_edge_addr: str,
        protocol: str = "tcp",
        edge_port: int = EDGE_PORT,
        robot_port: int = ROBOT_PORT,
    ) -> Topology:
        """Robot and edge sides in the emulated uplink's namespaces (shared.tools.linkemu): the robot
        reaches the edge over the shaped veth, tools over the management veth, in the config's
        `protocol` (a secure config's tls/ stays TLS: a trial's went plain tcp/ and nothing connected)
        and on its ports (`splittag up --link` used 7447 / 7448 whatever the config said)."""
        return cls(
            edge_port=edge_port,
            robot_port=robot_port,
            edge_bind="0.0.0.0",
            edge_from_robot=edge_addr,
            edge_from_tools=mgmt_edge_addr,
            protocol=protocol,
        )

    @classmethod
    def from_config(cls, config: Path) -> Topology:
        """The topology a deploy TOML describes (deploy/local.toml, deploy/two_host.toml, ...): the
        edge and robot routers' listen endpoints and the robot router's connect endpoint."""
        doc = tomllib.loads(config.read_text())
        protocols: set[str] = set()

        def endpoint(service: str, field: str, default: tuple[str, int]) -> tuple[str, int]:
            values = doc.get(service, {}).get("zenoh", {}).get(field, [])
            if not values:
                return default
            proto, _, rest = str(values[0]).partition("/")
            host, _, port = rest.rpartition(":")
            if proto not in ("tcp", "tls") or not host or not port.isdigit():
                raise ValueError(f"{config}: [{service}.zenoh] {field} {values[0]!r} is not tcp/ or tls/HOST:PORT")
            protocols.add(proto)
            return host, int(port)

        edge_bind, edge_port = endpoint("edge_infer", "listen", ("127.0.0.1", EDGE_PORT))
        robot_bind, robot_port = endpoint("robot_infer", "listen", ("127.0.0.1", ROBOT_PORT))
        local = "127.0.0.1" if edge_bind == "0.0.0.0" else edge_bind
        edge_from_robot, _ = endpoint("robot_infer", "connect", (local, edge_port))
        monitor = doc.get("monitor", {}).get("connect", [])
        edge_from_tools = str(monitor[0]).partition("/")[2].rpartition(":")[0] if monitor else local
        if len(protocols) > 1:
            raise ValueError(f"{config}: mixes tcp/ and tls/ endpoints; use one protocol for the whole deployment")
        protocol = protocols.pop() if protocols else "tcp"
        return cls(edge_port, robot_port, edge_bind, robot_bind, edge_from_robot, edge_from_tools, protocol)

    @property
    def edge_router(self) -> str:
        """The edge router's endpoint for tools."""
        return f"{self.protocol}/{self.edge_from_tools}:{self.edge_port}"

    @property
    def robot_router(self) -> str:
        """The robot router's endpoint (robot side only)."""
        return f"{self.protocol}/{self.robot_bind}:{self.robot_port}"

    @property
    def robot_from_edge(self) -> str | None:
        """The robot router's endpoint as the edge side (slam, tools) reaches it, or None where it cannot:
        a robot router on the robot's own loopback while the edge listens elsewhere (another host, or
        the emulated link's namespaces)."""
        if self.robot_bind in LOOPBACK_HOSTS and self.edge_bind != self.robot_bind:
            return None
        return self.robot_router

    def edge_side_endpoints(self, edge: str) -> list[str]:
        """`edge`, then the robot's router where the edge side reaches it (robot_from_edge)."""
        robot = self.robot_from_edge
        return [edge] if robot is None else [edge, robot]

    def zenoh_tables(self) -> dict[str, dict[str, Any]]:
        """The `[<service>.zenoh]` tables (and `[monitor]`) of a run config."""
        p = self.protocol
        edge_local = f"{p}/{'127.0.0.1' if self.edge_bind == '0.0.0.0' else self.edge_bind}:{self.edge_port}"
        return {
            "edge_infer": {"zenoh": {"mode": "router", "listen": [f"{p}/{self.edge_bind}:{self.edge_port}"]}},
            "robot_infer": {
                "zenoh": {
                    "mode": "router",
                    "listen": [self.robot_router],
                    "connect": [f"{p}/{self.edge_from_robot}:{self.edge_port}"],
                }
            },
            "camera": {"zenoh": {"mode": "client", "connect": [self.robot_router]}},
            "controller": {"zenoh": {"mode": "client", "connect": [self.robot_router]}},
            # A client with the robot's router as its second endpoint: while the edge's is away, the poses
            # the robot computes on board still reach slam. Not a peer of both: a peer's own puts reached
            # a subscriber at either router twice (through both; a review counted 40 of 20).
            "slam": {"zenoh": {"mode": "client", "connect": self.edge_side_endpoints(edge_local)}},
            "monitor": {"connect": self.edge_side_endpoints(self.edge_router)},
        }


def merge(base: dict[str, Any], extra: dict[str, Any]) -> dict[str, Any]:
    """Deep merge of TOML documents (extra wins)."""
    out = dict(base)
    for key, value in extra.items():
        out[key] = merge(out[key], value) if isinstance(value, dict) and isinstance(out.get(key), dict) else value
    return out


def write_config(
    path: Path,
    *,
    topology: Topology | None = None,
    base: Path | None = None,
    extra: dict[str, dict[str, Any]] | None = None,
) -> Path:
    """Write a run config: the base deploy TOML (if any), its endpoints replaced by `topology` (if
    given), then `extra` tables merged in. Returns `path`."""
    doc: dict[str, Any] = tomllib.loads(base.read_text()) if base is not None else {}
    if topology is not None:
        doc = merge(doc, topology.zenoh_tables())
    doc = merge(doc, extra or {})
    path.write_text(to_toml(doc))
    return path


def to_toml(doc: dict[str, Any], prefix: str = "") -> str:
    """A TOML document (tables of scalars, lists and nested tables) as text."""
    lines, tables = [], []
    for key, value in doc.items():
        if isinstance(value, dict):
            tables.append((key, value))
        else:
            lines.append(f"{key} = {json.dumps(value)}")
    out = "\n".join(lines) + ("\n" if lines else "")
    for key, value in tables:
        name = f"{prefix}.{key}" if prefix else key
        out += f"\n[{name}]\n" + to_toml(value, name)
    return out
