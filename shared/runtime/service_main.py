"""The thin `python -m services.<name>` entry: parse --config, build settings, open Zenoh, run, stop on SIGINT."""

from __future__ import annotations

import argparse
import faulthandler
import logging
import signal
import threading
from collections.abc import Callable
from pathlib import Path
from typing import TypeVar

import zenoh

from shared.runtime.cpus import CpuPlacementError, pin_cpus
from shared.runtime.logs import setup_logging
from shared.runtime.settings import ServiceSettings
from shared.transport.session import open_session

S = TypeVar("S", bound=ServiceSettings)


def service_main(name: str, settings_cls: type[S], run: Callable[[S, zenoh.Session, threading.Event], object]) -> int:
    """Run a service until SIGINT/SIGTERM (or until its loop returns)."""
    parser = argparse.ArgumentParser(prog=f"python -m services.{name}")
    parser.add_argument("--config", type=Path, default=None, help="TOML settings file (see deploy/)")
    args = parser.parse_args()
    log = setup_logging(name)
    # `kill -USR1 <pid>` (and stop_services before it escalates to SIGKILL) writes every thread's
    # stack to this service's log: a hung service says where it hangs.
    faulthandler.register(signal.SIGUSR1, all_threads=True)
    settings = settings_cls.load(args.config)
    settings.log_resolved()
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    if settings.cpus is not None:
        try:
            pin_cpus(settings.cpus)  # before Zenoh and torch start their threads (those running move too)
        except CpuPlacementError as exc:
            log.error("%s: cpus %s: %s", name, settings.cpus, exc)
            return 2
    session = open_session(settings.zenoh)
    try:
        run(settings, session, stop)
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
    return 0
