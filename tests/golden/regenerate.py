"""Regenerate the golden wire bytes of framing 3: `python -m tests.golden.regenerate` (review the diff!).
framing1/ and framing2/ are frozen: those are the bytes older peers send, never regenerated."""

from __future__ import annotations

from pathlib import Path

from shared.wire.messages import encode
from tests.examples import example_messages, golden_name

HERE = Path(__file__).parent


def main() -> None:
    """Write one framing3/*.splittag file per schema."""
    (HERE / "framing3").mkdir(exist_ok=True)
    for schema, msg in example_messages().items():
        path = HERE / golden_name(schema)
        path.write_bytes(encode(msg))
        print(f"wrote {path} ({path.stat().st_size} bytes)")


if __name__ == "__main__":
    main()
