"""Zenoh plumbing: sessions from settings, tensor publishers, latest-only subscribers, liveliness."""

from __future__ import annotations

import collections
import contextlib
import functools
import json
import logging
import os
import random
import socket
import ssl
import threading
import time
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import Final, Literal

import zenoh
from pydantic import BaseModel, ConfigDict, Field, model_validator

from shared.transport.access import AccessControlSettings, access_control_config, keep_local_config

log = logging.getLogger(__name__)

# Framing 2 of shared.wire.codec: a msgpack header with the tensors out of band (not plain msgpack).
WIRE_ENCODING = "application/x-splittag-frame"


# The largest legitimate message: a Frame or Features under the codec's 64 MiB cap, plus headers.
MAX_MESSAGE_BYTES: Final[int] = 64 * 1024 * 1024 + 1024 * 1024


class TlsSettings(BaseModel):
    """Zenoh TLS: this process's certificate and key (its identity: the certificate's common name),
    and the CA every peer's certificate must chain to. `mutual`: peers must present one too (mTLS),
    which is what lets the routers' access control know who is asking."""

    model_config = ConfigDict(extra="forbid")

    root_ca_certificate: Path  # PEM of the CA that signed every identity (deploy/make-certs.sh)
    certificate: Path  # this process's PEM certificate (its common name is its identity)
    private_key: Path  # this process's PEM private key
    mutual: bool = True  # both ends show a certificate (the access control needs it)

    @classmethod
    def from_dir(cls, certs_dir: Path, identity: str) -> TlsSettings:
        """The layout deploy/make-certs.sh writes: ca.pem, <identity>.pem, <identity>.key."""
        d = Path(certs_dir)
        return cls(
            root_ca_certificate=d / "ca.pem", certificate=d / f"{identity}.pem", private_key=d / f"{identity}.key"
        )

    def check_files(self) -> None:
        """FileNotFoundError naming the first missing file (before Zenoh reports it less clearly)."""
        for what, path in (
            ("root_ca_certificate", self.root_ca_certificate),
            ("certificate", self.certificate),
            ("private_key", self.private_key),
        ):
            if not Path(path).is_file():
                raise FileNotFoundError(f"zenoh tls {what} {path} does not exist (deploy/make-certs.sh makes them)")


class ZenohSettings(BaseModel):
    """How a process joins the Zenoh network. Shared memory is OFF unless asked for: zenoh 1.10
    enables it by default, and it silently bypasses any network shaping between local processes."""

    model_config = ConfigDict(extra="forbid")

    mode: Literal["peer", "client", "router"] = "peer"  # a router forwards for the others, a client joins one
    # endpoints this session accepts connections on (tcp/HOST:PORT, tls/HOST:PORT)
    listen: list[str] = Field(default_factory=list)
    connect: list[str] = Field(default_factory=list)  # endpoints this session connects to
    multicast_scouting: bool = False  # find peers by UDP multicast (off: only the endpoints given)
    shared_memory: bool = False  # same host only; it bypasses any link shaping (docs/wire.md)
    config_file: Path | None = None  # JSON5; the fields above are applied on top of it
    # A client or peer: open() fails after this long without a connection; a router starts without one
    # and keeps connecting in the background.
    connect_timeout_secs: float = Field(default=30.0, gt=0)
    # Larger messages are refused by the transport before they are reassembled (zenoh's default: 1 GiB).
    max_message_bytes: int = Field(default=MAX_MESSAGE_BYTES, gt=0)
    # Largest batch a link sends (the smaller of the two ends is used); a larger message goes in
    # fragments. zenoh's default and its maximum: on loopback 8 KiB batches take a 0.9 MB tensor 4.5x
    # as long, on the emulated 5G uplink every size is link-bound (bench/zenoh_options.py, docs/wire.md).
    batch_size_bytes: int = Field(default=65535, ge=1024, le=65535)
    # A reliable (BLOCK) put waits at most this long for room in a link's queue; then zenoh closes that
    # link (and reconnects when it can) so the put and every later one go on. zenoh's default is 5 s: a
    # link cut longer than a few seconds (the queue and the socket full of messages for the far side)
    # froze the robot's on-board pipeline for 5 s (a two-host trial: 5 of 7 cuts of 10 s). Keep it above
    # what one batch takes on the slowest link in use (64 KiB: 0.5 s at 1 Mbit/s).
    block_close_secs: float = Field(default=1.0, gt=0, le=60)
    tls: TlsSettings | None = None  # needed by tls/ endpoints
    # Enforced by a router on the messages of the peers and clients it serves (shared.transport.access).
    access_control: AccessControlSettings = Field(default_factory=AccessControlSettings)
    # Keys whose puts a router delivers to its own session and to no other process, whoever subscribes
    # (robot_infer's router keeps the camera's frames: shared.transport.access.keep_local_config).
    # Only a router can enforce it: set on a peer or client it is refused.
    keep_local: list[str] = Field(default_factory=list)

    @model_validator(mode="after")
    def _only_a_router_keeps(self) -> ZenohSettings:
        if self.keep_local and self.mode != "router":
            raise ValueError(
                f"keep_local ({self.keep_local}) needs mode = 'router': a {self.mode} forwards nothing to hold back"
            )
        return self


def build_config(settings: ZenohSettings) -> zenoh.Config:
    """A zenoh.Config from settings (the optional JSON5 file first, explicit fields on top)."""
    if settings.config_file is not None:
        if not settings.config_file.is_file():
            raise FileNotFoundError(f"zenoh config file {settings.config_file} does not exist")
        config = zenoh.Config.from_file(str(settings.config_file))
    else:
        config = zenoh.Config()
    config.insert_json5("mode", json.dumps(settings.mode))
    if settings.listen or settings.config_file is None:
        config.insert_json5("listen/endpoints", json.dumps(settings.listen))
    if settings.connect or settings.config_file is None:
        config.insert_json5("connect/endpoints", json.dumps(settings.connect))
    if settings.connect:
        # A client or peer waits for the other side to come up (start order does not matter), but fails
        # loudly. A router starts at once and keeps connecting in the background, as zenoh's own router
        # default does: robot_infer's router, whose robot computes on board while no edge is in reach (it
        # used to exit when the edge was not up within the timeout, and a robot's host started before
        # its edge never came up: found by a fresh-clone trial).
        config.insert_json5("connect/timeout_ms", json.dumps(int(settings.connect_timeout_secs * 1000)))
        config.insert_json5("connect/exit_on_failure", json.dumps(settings.mode != "router"))
    config.insert_json5("scouting/multicast/enabled", json.dumps(settings.multicast_scouting))
    config.insert_json5("transport/shared_memory/enabled", json.dumps(settings.shared_memory))
    config.insert_json5("transport/link/rx/max_message_size", json.dumps(settings.max_message_bytes))
    if settings.config_file is None or "batch_size_bytes" in settings.model_fields_set:
        # (a config file's own batch size stands unless the setting is given explicitly)
        config.insert_json5("transport/link/tx/batch_size", json.dumps(settings.batch_size_bytes))
    if settings.config_file is None or "block_close_secs" in settings.model_fields_set:
        config.insert_json5(
            "transport/link/tx/queue/congestion_control/block/wait_before_close",
            json.dumps(round(settings.block_close_secs * 1e6)),  # microseconds
        )
    uses_tls = any(e.startswith("tls/") for e in (*settings.listen, *settings.connect))
    if uses_tls and settings.tls is None:
        raise ValueError("tls/ endpoints need zenoh.tls settings (certificates: deploy/make-certs.sh)")
    if settings.tls is not None:
        tls = settings.tls
        tls.check_files()
        link = {
            "root_ca_certificate": str(tls.root_ca_certificate),
            "listen_certificate": str(tls.certificate),
            "listen_private_key": str(tls.private_key),
            "connect_certificate": str(tls.certificate),
            "connect_private_key": str(tls.private_key),
            "enable_mtls": tls.mutual,
            "verify_name_on_connect": True,
        }
        for key, value in link.items():
            config.insert_json5(f"transport/link/tls/{key}", json.dumps(value))
    if settings.access_control.enabled:
        if settings.tls is None or not settings.tls.mutual:
            raise ValueError("access control matches certificate names: it needs zenoh.tls with mutual = true")
        acl = access_control_config(settings.access_control, keep_local=settings.keep_local)
        config.insert_json5("access_control", json.dumps(acl))
    elif settings.keep_local:
        if settings.config_file is not None and json.loads(config.get_json("access_control")).get("enabled"):
            # (replacing the file's rules would open a default-deny router to everyone)
            raise ValueError(
                f"{settings.config_file} has its own access_control: keep_local ({settings.keep_local}) would "
                "replace it; add a rule denying put on those keys (egress) to each of its policies and set "
                "keep_local = [] (robot_infer: frames_leave_robot = true)"
            )
        config.insert_json5("access_control", json.dumps(keep_local_config(settings.keep_local)))
    return config


@functools.cache
def zenoh_log_from_env() -> bool:
    """Zenoh's own log (off unless `RUST_LOG` is set, in its syntax) to this process's output, without
    colour codes: how an operator sees what Zenoh does not tell the application, such as access control
    refusing a message (zenoh 1.10 says each decision at trace level:
    RUST_LOG="error,zenoh::net::routing::interceptor::access_control=trace", docs/security.md). Called
    by the services (service_main), whose output is their log; not by the command line tools, whose
    output may be JSON. Whether it was turned on."""
    if not os.environ.get("RUST_LOG"):
        return False
    os.environ.setdefault("NO_COLOR", "1")  # (read when zenoh's log starts: a log file gets no escape codes)
    zenoh.try_init_log_from_env()
    return True


def open_session(settings: ZenohSettings) -> zenoh.Session:
    """Open a session; logs the resolved mode and endpoints once. A client given several endpoints opens
    on whichever answers: zenoh 1.10 fails such a client when its first endpoint is down although
    another answers (a trial: slam and the monitor, whose second endpoint is the robot's router, could
    not start while the edge's was away), so the others are tried first in turn, each for
    `connect_timeout_secs`."""
    try:
        session = zenoh.open(build_config(settings))
    except zenoh.ZError:
        if settings.mode != "client" or len(settings.connect) < 2:
            raise
        session = _open_rotated(settings)
    log.info(
        "zenoh session %s: mode=%s listen=%s connect=%s multicast=%s shm=%s",
        session.info.zid(),
        settings.mode,
        settings.listen,
        settings.connect,
        settings.multicast_scouting,
        settings.shared_memory,
    )
    if settings.mode == "router" and settings.connect:
        _warn_if_unconnected(session, settings)
    return session


def _open_rotated(settings: ZenohSettings) -> zenoh.Session:
    """A client session whose first endpoint is each of the others in turn (the last error if none opens)."""
    ends = settings.connect
    for i in range(1, len(ends) - 1):
        with contextlib.suppress(zenoh.ZError):
            return zenoh.open(build_config(settings.model_copy(update={"connect": ends[i:] + ends[:i]})))
    return zenoh.open(build_config(settings.model_copy(update={"connect": ends[-1:] + ends[:-1]})))


def _warn_if_unconnected(session: zenoh.Session, settings: ZenohSettings) -> None:
    """A router keeps connecting in the background without a word (zenoh logs each failed attempt at
    debug level): when nothing has been reached for `connect_timeout_secs` from the start, say so once,
    with the likely causes (and, for a tls/ endpoint whose certificate is wrong, what is wrong with it),
    so a wrong address or certificate is not mistaken for an edge that is merely away. A router that
    reached a peer in that time and lost it again is not told it reached none."""

    def connected() -> bool:
        return any(session.info.routers_zid()) or any(session.info.peers_zid())

    def check() -> None:
        deadline = time.monotonic() + settings.connect_timeout_secs
        try:
            while time.monotonic() < deadline:
                if session.is_closed() or connected():
                    return
                time.sleep(0.5)
            if session.is_closed() or connected():
                return
        except Exception:  # closed meanwhile: nothing to say
            return
        found = "; ".join(filter(None, (certificate_problem(e, settings.tls) for e in settings.connect)))
        log.warning(
            "zenoh router: none of %s reached in %.0f s; still trying in the background (%s)",
            settings.connect,
            settings.connect_timeout_secs,
            found
            or "check the address, that the other side listens there, and with TLS the certificates' CA and names",
        )

    threading.Thread(target=check, name="zenoh-connect-check", daemon=True).start()


def certificate_problem(endpoint: str, tls: TlsSettings | None, *, timeout_secs: float = 3.0) -> str | None:
    """What is wrong with the certificates between this process and a tls/ `endpoint`, found by a TLS
    handshake of our own with the same CA, certificate and key (zenoh only says it timed out): the
    endpoint's certificate not valid for the address dialled or not from this CA, or this process's
    certificate refused there. None when the handshake succeeds, for any other endpoint, or when
    nothing answers at the address (not a certificate problem)."""
    if tls is None or not endpoint.startswith("tls/") or "#" in endpoint:
        return None  # (an endpoint with a configuration of its own may use other certificates)
    host, _, port = endpoint.removeprefix("tls/").split("?")[0].rpartition(":")
    host = host.strip("[]")
    try:
        context = ssl.create_default_context(cafile=str(tls.root_ca_certificate))
        context.verify_flags &= ~ssl.VERIFY_X509_STRICT  # (Python >= 3.13 sets it; rustls does not ask that)
        context.load_cert_chain(str(tls.certificate), str(tls.private_key))
    except (OSError, ssl.SSLError) as exc:
        return f"{endpoint}: this process's TLS files cannot be used: {exc}"
    try:
        with (
            socket.create_connection((host, int(port)), timeout=timeout_secs) as raw,
            context.wrap_socket(raw, server_hostname=host) as conn,
            contextlib.suppress(TimeoutError),
        ):
            # TLS 1.3: the server judges the client's certificate after the handshake; its alert
            # arrives on the first read (a timeout means it kept the connection: accepted)
            conn.settimeout(0.5)
            conn.recv(1)
    except ssl.SSLCertVerificationError as exc:
        return f"{endpoint}: its certificate is refused here: {exc.verify_message or exc.reason}"
    except ssl.SSLError as exc:
        if any(alert in str(exc.reason) for alert in _CERTIFICATE_ALERTS):  # not an EOF, a reset, ...
            return f"{endpoint}: it refused this process's certificate (TLS alert {exc.reason})"
        return None
    except (OSError, ValueError):
        return None
    return None


# TLS alerts a server sends about the client's certificate (OpenSSL's reason names).
_CERTIFICATE_ALERTS: Final = (
    "UNKNOWN_CA",
    "BAD_CERTIFICATE",
    "DECRYPT_ERROR",
    "CERTIFICATE_REQUIRED",
    "CERTIFICATE_UNKNOWN",
    "CERTIFICATE_EXPIRED",
    "UNSUPPORTED_CERTIFICATE",
    "CERTIFICATE_REVOKED",
)


def encoding_for(schema: str) -> zenoh.Encoding:
    """The Zenoh encoding of a splittag message: our framing, with the versioned schema id."""
    return zenoh.Encoding(WIRE_ENCODING).with_schema(schema)


def declare_tensor_publisher(session: zenoh.Session, key: str, schema: str) -> zenoh.Publisher:
    """Reliable, congestion-control BLOCK publisher: the default DROP silently loses large messages."""
    return session.declare_publisher(
        key,
        encoding=encoding_for(schema),
        congestion_control=zenoh.CongestionControl.BLOCK,
        reliability=zenoh.Reliability.RELIABLE,
    )


def declare_latest_subscriber(
    session: zenoh.Session, key: str
) -> zenoh.Subscriber[zenoh.handlers.Handler[zenoh.Sample]]:
    """Subscriber that keeps only the newest sample (a ring of one): never works on stale frames."""
    return session.declare_subscriber(key, zenoh.handlers.RingChannel(1))


def declare_fifo_subscriber(
    session: zenoh.Session, key: str, capacity: int = 256
) -> zenoh.Subscriber[zenoh.handlers.Handler[zenoh.Sample]]:
    """Subscriber that queues samples in order (for streams where every message counts)."""
    return session.declare_subscriber(key, zenoh.handlers.FifoChannel(capacity))


def next_sample(
    subscriber: zenoh.Subscriber[zenoh.handlers.Handler[zenoh.Sample]],
    stop: threading.Event,
    *,
    poll_secs: float = 0.001,
) -> zenoh.Sample | None:
    """The next sample of a channel subscriber, or None once `stop` is set (checked every poll_secs)."""
    while not stop.is_set():
        sample = subscriber.try_recv()
        if sample is not None:
            return sample
        stop.wait(poll_secs)
    return None


def wait_for_liveliness(
    session: zenoh.Session,
    keys: Iterable[str],
    *,
    timeout_secs: float = 30.0,
    every_second: Callable[[], object] | None = None,
) -> None:
    """Block until a liveliness token is alive on every key, or raise TimeoutError naming the rest.
    `every_second` runs on the waiting thread about once a second meanwhile (a launcher supervises)."""
    wanted = set(keys)
    seen: set[str] = set()
    lock = threading.Lock()
    done = threading.Event()

    def on_sample(sample: zenoh.Sample) -> None:
        key = str(sample.key_expr)
        with lock:
            if sample.kind == zenoh.SampleKind.PUT:
                seen.add(key)
            else:
                seen.discard(key)
            if wanted <= seen:
                done.set()

    subs = [session.liveliness().declare_subscriber(k, on_sample, history=True) for k in wanted]
    try:
        deadline = time.monotonic() + timeout_secs
        while every_second is not None and not done.is_set() and time.monotonic() < deadline:
            if not done.wait(min(1.0, max(0.0, deadline - time.monotonic()))):
                every_second()
        if not done.wait(max(0.0, deadline - time.monotonic())):
            with lock:
                missing = sorted(wanted - seen)
            raise TimeoutError(f"no liveliness after {timeout_secs:.1f} s for: {', '.join(missing)}")
    finally:
        for s in subs:
            s.undeclare()


EPHEMERAL_PORTS_FILE: Final[Path] = Path("/proc/sys/net/ipv4/ip_local_port_range")
_LOWEST_PICKED_PORT: Final[int] = 10_000  # below: well-known and registered services more often listen
_RECENT_PORTS: collections.deque[int] = collections.deque(maxlen=256)  # handed out, maybe not bound yet


def ephemeral_port_range(path: Path = EPHEMERAL_PORTS_FILE) -> tuple[int, int]:
    """The kernel's range for outgoing connections' source ports (Linux's default where it cannot be read)."""
    try:
        low, high = (int(v) for v in path.read_text().split())
    except (OSError, ValueError):
        return 32768, 60999
    return low, high


def free_tcp_port(*, ephemeral: tuple[int, int] | None = None, attempts: int = 200) -> int:
    """A TCP port on 127.0.0.1 that was free a moment ago (for tests and benchmarks), outside the kernel's
    ephemeral range where one is free: a port from that range can be taken before its listener binds it by
    any outgoing connection's source port, including a Zenoh client of that very port, retrying while its
    router starts, that connects to itself (TCP simultaneous open; found when bench.pipeline's robot_infer
    could not bind its router's port: "Address already in use"). Random, so parallel processes rarely meet;
    never one of this process's last 256 answers (its callers bind them later, all at once)."""
    low, high = ephemeral if ephemeral is not None else ephemeral_port_range()
    candidates = [(_LOWEST_PICKED_PORT, low - 1), (high + 1, 65535)]
    candidates = [(a, b) for a, b in candidates if b >= a]
    rng = random.SystemRandom()
    for _ in range(attempts if candidates else 0):
        a, b = rng.choice(candidates)
        port = rng.randint(a, b)
        if port in _RECENT_PORTS:
            continue
        with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
            try:
                s.bind(("127.0.0.1", port))
            except OSError:
                continue
        _RECENT_PORTS.append(port)
        return port
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:  # nothing outside the range: the kernel's pick
        s.bind(("127.0.0.1", 0))
        chosen: int = s.getsockname()[1]
        return chosen
