"""The `splittag` console script: one entry point, one subcommand per capability."""

from __future__ import annotations

import argparse
from collections.abc import Sequence

from shared.logs import setup_logging


def _cmd_demo(args: argparse.Namespace) -> int:
    from shared.demo import run_demo

    return run_demo(robot_id=args.robot_id, repetitions=args.repetitions)


def _cmd_echo(args: argparse.Namespace) -> int:
    from shared import echo
    from shared.transport import ZenohSettings

    settings = ZenohSettings(mode="router", listen=args.listen, connect=args.connect)
    echo.run(settings, robot_id=args.robot_id)
    return 0


def build_parser() -> argparse.ArgumentParser:
    """The argument parser of every subcommand."""
    parser = argparse.ArgumentParser(prog="splittag", description=__doc__)
    sub = parser.add_subparsers(dest="command", required=True)

    p = sub.add_parser("demo", help="two-process Zenoh exchange of split tensors on loopback")
    p.add_argument("--robot-id", default="demo")
    p.add_argument("--repetitions", type=int, default=20)
    p.set_defaults(func=_cmd_demo)

    p = sub.add_parser("echo", help="run the edge echo queryable for link probes")
    p.add_argument("--robot-id", default="robot1")
    p.add_argument("--listen", action="append", default=[], help="zenoh endpoint, repeatable")
    p.add_argument("--connect", action="append", default=[], help="zenoh endpoint, repeatable")
    p.set_defaults(func=_cmd_echo)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Parse arguments and run the chosen subcommand."""
    args = build_parser().parse_args(argv)
    setup_logging(f"splittag-{args.command}")
    code: int = args.func(args)
    return code


if __name__ == "__main__":
    raise SystemExit(main())
