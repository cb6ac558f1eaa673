"""Regenerate the golden wire bytes: `python -m tests.golden.regenerate` rewrites framing3/ (what encode
writes; review the diff!). framing1/ and framing2/ are frozen, the bytes older peers send: no run
rewrites them. `--missing` writes only the golden files that do not exist yet, in every framing (those
of a new schema or version), and never overwrites one."""

from __future__ import annotations

import argparse
from pathlib import Path

from shared.wire.messages import encode
from tests.examples import GOLDEN_FRAMINGS, example_messages, golden_name, golden_names

HERE = Path(__file__).parent


def write_framing3() -> None:
    """Write one framing3/*.splittag file per schema."""
    (HERE / "framing3").mkdir(exist_ok=True)
    for schema, msg in example_messages().items():
        path = HERE / golden_name(schema)
        path.write_bytes(encode(msg))
        print(f"wrote {path} ({path.stat().st_size} bytes)")


def write_missing() -> None:
    """Write each current schema's golden file in each framing where it does not exist yet (a new schema
    or version needs all three); an existing file is left as it is. Legacy versions' files cannot be
    written (no example of them): they are the framing1/ files of the version before."""
    for schema, msg in example_messages().items():
        for framing in GOLDEN_FRAMINGS:
            path = HERE / golden_name(schema, framing)
            path.parent.mkdir(exist_ok=True)
            try:
                with path.open("xb") as out:  # exclusive: an existing golden file is never rewritten
                    out.write(encode(msg, framing=framing))
            except FileExistsError:
                continue
            print(f"wrote {path} ({path.stat().st_size} bytes)")
    read = golden_names()
    for path in sorted(HERE.glob("framing*/*")):
        if path.relative_to(HERE).as_posix() not in read:
            print(f"stale: {path} is read by no test (a superseded version's? delete it)")


def main(argv: list[str] | None = None) -> None:
    """Rewrite framing3/, or (--missing) add only the golden files that do not exist."""
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument(
        "--missing",
        action="store_true",
        help="write only missing golden files, in every framing (a new schema or version); never overwrite one",
    )
    args = ap.parse_args(argv)
    if args.missing:
        write_missing()
    else:
        write_framing3()


if __name__ == "__main__":
    main()
