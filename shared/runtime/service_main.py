"""The thin `python -m services.<name>` entry: parse --config, build settings, open Zenoh, run, stop on SIGINT."""

from __future__ import annotations

import argparse
import faulthandler
import logging
import os
import signal
import threading
import tomllib
from collections.abc import Callable
from concurrent.futures import Future
from pathlib import Path
from typing import TypeVar

import zenoh
from pydantic import ValidationError
from pydantic_settings import SettingsError

from shared.model.precision import ModelFileError  # no torch: the weights folder's errors only
from shared.runtime.cpus import CpuPlacementError, pin_cpus
from shared.runtime.errors import one_line_error
from shared.runtime.logs import setup_logging
from shared.runtime.settings import CONFIG_EXIT, SOURCE_ENDED_EXIT, ConfigurationError, ServiceSettings
from shared.runtime.signals import SignalStop
from shared.runtime.waiting import result_unless_set
from shared.transport.session import ZenohSettings, certificate_problem, open_session, zenoh_log_from_env
from shared.vision.files import atomic_write_text
from shared.vision.geometry import CameraFileError
from shared.vision.tagmap import TagMapError

S = TypeVar("S", bound=ServiceSettings)
SOURCE_ENDED = object()  # what a service's run returns when its input ended by itself (exit SOURCE_ENDED_EXIT)


def started_by_run_launcher(run_dir: Path) -> bool:
    """This process was started by the launcher of the run in `run_dir` (its pid in run_dir/launcher.pid
    is this process's parent): what it leaves there (its settings, robot_infer's split) belongs to that
    run, and a restart of it by that launcher continues the same run."""
    try:
        return int((run_dir / "launcher.pid").read_text().strip()) == os.getppid()
    except (OSError, ValueError):
        return False


def write_resolved(settings: ServiceSettings, name: str) -> Path | None:
    """The settings this process runs with (config file and environment resolved) as
    `run_dir/settings/<service>-<worker, "fleet" or robot>.json`: the run's record of what each process
    really ran with (the launcher's config.toml does not hold SPLITTAG_* overrides). Only for a process
    the run's launcher started (its pid in run_dir/launcher.pid is this process's parent): a service
    started by hand beside a run, or with runs/current's config after it, leaves that run's record alone."""
    if not started_by_run_launcher(settings.run_dir):
        return None
    worker = getattr(settings, "worker_id", None)
    who = worker or ("fleet" if getattr(settings, "robots", None) else settings.robot_id)
    path = settings.run_dir / "settings" / f"{name}-{who}.json"
    try:
        path.parent.mkdir(exist_ok=True)
        atomic_write_text(path, settings.model_dump_json(indent=2) + "\n")
    except OSError as exc:
        logging.getLogger(name).warning("%s: cannot write its settings to %s: %s", name, path, exc)
        return None
    return path


def unrecoverable_open_error(exc: zenoh.ZError, zenoh_settings: ZenohSettings) -> str | None:
    """Why a Zenoh client can never connect with these settings, however often it is retried: every
    endpoint it dials answers with a certificate this process refuses (not valid for the address dialled,
    not from its CA) or refuses this process's own (found by a TLS handshake of our own: zenoh says only
    that it timed out). None: it may open later (the router is not up yet, an address not assigned yet)."""
    if "Unable to connect" not in str(exc):
        return None  # a listen error (an address in use, not yet assigned) or anything else: retried
    problems = [certificate_problem(e, zenoh_settings.tls) for e in zenoh_settings.connect]
    if not problems or any(p is None for p in problems):
        return None  # an endpoint that shakes hands (or was not checked) may answer next time
    return "; ".join(p for p in problems if p)


def open_error_line(exc: zenoh.ZError) -> str:
    """Zenoh's open error in one line, saying what EADDRNOTAVAIL means (an address this host does not
    have, or not yet: Wi-Fi or DHCP still coming up)."""
    text = one_line_error(exc)
    if "os error 99" in text:
        text += " (no such address on this host, or not yet: check the listen endpoints)"
    return text


def _open_unless_stopped(zenoh_settings: ZenohSettings, stop: threading.Event) -> zenoh.Session | None:
    """The service's Zenoh session (its errors raised here), or None if `stop` is set while it opens.
    zenoh.open blocks for up to `connect_timeout_secs` when the router it dials is not up, without
    running Python, so a stop signal's handler would wait for it: it opens on a thread of its own while
    the main thread waits on both. A session that opens after the stop is closed, not left open."""
    opened: Future[zenoh.Session] = Future()
    lock = threading.Lock()
    abandoned = threading.Event()

    def open_it() -> None:
        try:
            session = open_session(zenoh_settings)
        except BaseException as exc:  # (handed to the main thread, which decides)
            opened.set_exception(exc)
            return
        with lock:
            if abandoned.is_set():
                session.close()
            else:
                opened.set_result(session)

    threading.Thread(target=open_it, name="zenoh-open", daemon=True).start()
    session = result_unless_set(opened, stop)
    if session is not None:
        return session
    with lock:
        abandoned.set()
        if opened.done() and opened.exception() is None:  # opened just as the stop came
            opened.result().close()
    return None


def service_main(
    name: str,
    settings_cls: type[S],
    run: Callable[[S, zenoh.Session, threading.Event], object],
    *,
    check: Callable[[S], object] | None = None,
) -> int:
    """Run a service until SIGINT/SIGTERM (or until its loop returns). Settings it cannot work with
    (refused by validation, a missing or malformed config file, or refused by `check`, which looks at
    what they name before any Zenoh session opens: a folder, a device) end it at once with one line in
    its log and exit code CONFIG_EXIT, as does a ConfigurationError raised by `run`."""
    parser = argparse.ArgumentParser(prog=f"python -m services.{name}")
    parser.add_argument("--config", type=Path, default=None, help="TOML settings file (see deploy/)")
    args = parser.parse_args()
    log = setup_logging(name)
    # `kill -USR1 <pid>` (and stop_services before it escalates to SIGKILL) writes every thread's
    # stack to this service's log: a hung service says where it hangs.
    faulthandler.register(signal.SIGUSR1, all_threads=True)
    try:
        settings = settings_cls.load(args.config)
        if check is not None:
            check(settings)
    except (ValidationError, SettingsError, FileNotFoundError, tomllib.TOMLDecodeError, ConfigurationError) as exc:
        log.error("%s: configuration error: %s", name, one_line_error(exc))
        return CONFIG_EXIT
    settings.log_resolved()
    write_resolved(settings, name)
    stop = threading.Event()
    SignalStop(stop)  # (not a handler that sets it: that can deadlock, see shared.runtime.signals)
    if settings.cpus is not None:
        try:
            pin_cpus(settings.cpus)  # before Zenoh and torch start their threads (those running move too)
        except CpuPlacementError as exc:
            log.error("%s: configuration error: cpus %s: %s", name, settings.cpus, exc)
            return CONFIG_EXIT
    zenoh_log_from_env()  # (RUST_LOG: zenoh's own log in this service's, e.g. access control's refusals)
    try:
        # A certificate that is not there, tls/ endpoints without TLS settings: the settings' fault.
        session = _open_unless_stopped(settings.zenoh, stop)
    except (FileNotFoundError, ValueError) as exc:
        log.error("%s: configuration error: zenoh: %s", name, one_line_error(exc))
        return CONFIG_EXIT
    except zenoh.ZError as exc:
        if (why := unrecoverable_open_error(exc, settings.zenoh)) is not None:
            log.error("%s: configuration error: zenoh: %s", name, why)
            return CONFIG_EXIT
        # the router it connects to is not (yet) up, an address not (yet) on this host: one line; the
        # launcher retries and prints it with each restart
        log.error("%s: cannot open its Zenoh session: %s", name, open_error_line(exc))
        return 1
    if session is None:
        # (a launcher stopping the run while the router this service dials is not up: a trial's camera
        # sat in zenoh.open for its 30 s connect timeout and was killed after 15)
        log.info("%s stopped before its Zenoh session opened", name)
        return 0
    code = 0
    try:
        if run(settings, session, stop) is SOURCE_ENDED and not stop.is_set():
            code = SOURCE_ENDED_EXIT  # (a source that ended as the stop came: stopped on request)
    except (ConfigurationError, ModelFileError, TagMapError, CameraFileError) as exc:
        # A file the settings name is missing or unusable (weights folder, tag map, camera file):
        # restarting cannot help. (Any other error, a FileNotFoundError included, is restarted.)
        log.error("%s: configuration error: %s", name, one_line_error(exc))
        return CONFIG_EXIT
    except Exception:
        logging.getLogger(name).exception("%s failed", name)
        return 1
    finally:
        session.close()
        log.info("%s stopped", name)
        # From here on the interpreter shuts down and restores default handlers for signals it
        # handles; a late SIGINT (a launcher stopping everyone, a second Ctrl-C) would then kill the
        # process mid-cleanup with -SIGINT. Ignored signals stay ignored: the exit code stays ours.
        for sig in (signal.SIGINT, signal.SIGTERM):
            signal.signal(sig, signal.SIG_IGN)
    return code
