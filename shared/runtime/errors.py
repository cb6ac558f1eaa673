"""Errors said to a user in one line (kept apart from the settings so that a light client, which has no
OpenCV or Rerun, can say its errors the same way)."""

from __future__ import annotations

import re
import tomllib


def one_line_error(exc: BaseException, *, max_chars: int = 600) -> str:
    """One line for a user: every field a ValidationError refused (`split_kk: Extra inputs are not
    permitted`), a malformed config file, or any other error's message (without Zenoh's Rust source locations)."""
    from pydantic import ValidationError

    if isinstance(exc, ValidationError):
        parts = []
        for err in exc.errors(include_url=False):
            where = ".".join(str(p) for p in err["loc"]) or "<settings>"
            got = repr(err.get("input"))
            got = got if len(got) <= 60 else got[:60] + "..."
            msg = err["msg"] if len(err["msg"]) <= 200 else err["msg"][:200] + "..."
            parts.append(f"{where}: {msg}" + ("" if err["type"] == "missing" else f" (got {got})"))
        text = "; ".join(parts)  # each message capped: every field's name is said
    elif isinstance(exc, tomllib.TOMLDecodeError):
        text = f"the config file is not valid TOML: {exc}"
    else:
        text = str(exc)
    text = re.sub(r" at /\S+\.rs:\d+\.?", "", " ".join(text.split()))  # Zenoh's Rust source locations
    return text if isinstance(exc, ValidationError) or len(text) <= max_chars else text[:max_chars] + "..."
