"""The split index as shared state, and the Zenoh query protocol that reads and sets it.

Protocol on `splittag/<robot_id>/split` (any Zenoh client can use it):
- get with no parameters and no payload -> reply: the current SplitConfig (msgpack, schema
  splittag/SplitConfig/v1).
- get with selector parameters `k=<0..7>` (optionally `codec=fp16|fp32`) -> sets it (pinned, source
  "user") and replies the applied SplitConfig.
- `release=1` unpins (the controller may change k again); `source=controller` marks a controller
  decision, which is refused while a person's setting is pinned.
- a SplitConfig payload is the same request written as a message (k, codec, source; `pinned` false
  from a user means release): it goes through the same rules, so it cannot skip the pin.
- parsed strictly: `release` is 0, 1, true or false (`release=0` keeps a pin), an unknown or
  repeated parameter is an error, and a set through a wildcard key (`splittag/*/split?k=5`) is refused.
- anything invalid -> an error reply (UTF-8 text saying what was wrong); nothing changes.

A controller asks on `splittag/<robot_id>/split/auto` (keys.split_auto): every set there is the
controller's whatever its parameters or payload say (`source=user` is an error), so under access
control (shared.transport.access) a controller's identity steers there and may not ask the person's key:
a controller that left `source` out used to pin like a person, over an operator's pin (found by a
fresh-clone trial of the TLS fleet).
"""

from __future__ import annotations

import json
import logging
import re
import threading
from collections.abc import Callable
from pathlib import Path
from typing import Final

import zenoh
from pydantic import ValidationError

from shared.transport.session import encoding_for
from shared.vision.files import atomic_write_text
from shared.wire import keys
from shared.wire.codec import WireError
from shared.wire.cuts import N_CUTS
from shared.wire.messages import SplitConfig, decode, encode, framing_of

log = logging.getLogger(__name__)


class SplitRequestError(ValueError):
    """A split query that cannot be applied."""


MAX_QUOTED_CHARS = 40


def _quote(value: object) -> str:
    """A received value as an error reply (and the log) quotes it: never all of a 5,000-character `k` (a
    trial's went back to it and into robot_infer.log whole)."""
    text = repr(value) if not isinstance(value, int) else str(value)
    return text if len(text) <= MAX_QUOTED_CHARS else f"{text[:MAX_QUOTED_CHARS]}... ({len(text)} chars)"


class SplitState:
    """Thread-safe current SplitConfig."""

    def __init__(self, initial: SplitConfig, *, on_change: Callable[[SplitConfig], None] | None = None) -> None:
        self._lock = threading.Lock()
        self._config = initial
        self._on_change = on_change  # told every applied change (robot_infer remembers it across a restart)

    def get(self) -> SplitConfig:
        """The current config."""
        with self._lock:
            return self._config

    def apply(self, params: dict[str, str], payload: bytes | None, *, as_controller: bool = False) -> SplitConfig:
        """Apply a request (see module docstring); raises SplitRequestError and changes nothing if invalid.
        `as_controller`: asked on the controller's key, so the request is the controller's whatever it
        claims (a payload's source is overridden, `source=user` is an error) and may not release a pin."""
        unknown = set(params) - {"k", "codec", "release", "source"}
        if unknown:
            raise SplitRequestError(f"unknown parameters {_quote(sorted(unknown))}; use k, codec, release, source")
        if as_controller and params.get("source", "controller") != "controller":
            raise SplitRequestError(
                f"on the controller's key every set is the controller's, not {_quote(params['source'])}"
            )
        if payload:
            if params:
                raise SplitRequestError("give the request as parameters or as a SplitConfig payload, not both")
            params = _params_from_payload(payload)
        if as_controller:
            if params.get("release", "0") in ("1", "true"):  # (a payload from a user with pinned false too)
                raise SplitRequestError("a controller may not release a person's pin")
            params = {**params, "source": "controller"} if params else params
        with self._lock:
            cur = self._config
            if not params:
                return cur
            source = params.get("source", "user")
            if source not in ("user", "controller"):
                raise SplitRequestError(f"source must be user or controller, got {_quote(source)}")
            k = cur.k
            if "k" in params:
                if not _DECIMAL.fullmatch(params["k"]):  # int() also takes "+5", "05", " 5" and "٥"
                    got = _quote(params["k"])
                    raise SplitRequestError(f"k must be an integer 0..{N_CUTS - 1}, got {got}")
                k = int(params["k"])
                if not 0 <= k < N_CUTS:
                    raise SplitRequestError(f"k must be in 0..{N_CUTS - 1}, got {_quote(k)}")
            codec = params.get("codec", cur.codec)
            if codec not in ("fp16", "fp32"):
                raise SplitRequestError(f"codec must be fp16 or fp32, got {_quote(codec)}")
            flag = params.get("release", "0")
            if flag not in ("0", "1", "true", "false"):
                raise SplitRequestError(f"release must be 0, 1, true or false, got {_quote(flag)}")
            release = flag in ("1", "true")
            sets = "k" in params or "codec" in params
            if source == "controller" and cur.pinned and not release:
                raise SplitRequestError(f"k is pinned at {cur.k} by a user; the controller may not change it")
            if not sets and not release:
                return cur  # `release=0` (or only a source) changes nothing: a pin stays a pin
            pinned = source == "user" and not release and sets
            new = SplitConfig(k=k, codec=codec, pinned=pinned, source=source)  # type: ignore[arg-type]
            if new != cur:
                self._config = new
                log.info("split set to k=%d codec=%s pinned=%s (%s)", new.k, new.codec, new.pinned, new.source)
                if self._on_change is not None:
                    self._on_change(new)
            elif source == "user":  # a person's set is in the log even when it changes nothing (a trial)
                log.info("split set to k=%d codec=%s pinned=%s (user; as it was)", new.k, new.codec, new.pinned)
            return new


def remember_split(path: Path, config: SplitConfig) -> None:
    """Write the split (k, codec, pin, source) to `path` atomically; a failure is logged, never raised
    (the split itself has changed)."""
    try:
        atomic_write_text(path, json.dumps(config.model_dump()))
    except OSError as exc:  # the change is applied: its asker gets the reply either way
        log.warning("split not remembered in %s: %s", path, exc)


def split_memory(run_dir: Path, robot_id: str) -> Path:
    """Where a robot's split is remembered in its run (one file per robot: a fleet shares the folder)."""
    return run_dir / f"split_{robot_id}.json"


def resumed_split(path: Path) -> SplitConfig | None:
    """A person's setting that a previous process of the same robot and run left in `path`, pinned or
    released (a released k stays until a controller changes it; a fleet trial's released k=3 came back
    as the configured 7), else None: the controller sets its own k again, so its k is not forced on
    the next process (nor one that made this process die, unless a person chose it)."""
    config = remembered_split(path)
    return config if config is not None and config.source == "user" else None


def remembered_split(path: Path) -> SplitConfig | None:
    """The split a previous process of the same run left in `path`, or None (none, or unreadable: said)."""
    if not path.is_file():
        return None
    try:
        return SplitConfig(**json.loads(path.read_text()))
    except (OSError, ValueError, TypeError, ValidationError) as exc:
        log.warning("ignoring the remembered split in %s: %s", path, exc)
        return None


_DECIMAL: Final = re.compile(r"0|[1-9][0-9]{0,8}")  # ASCII digits, as written, no sign or leading zero


def parse_parameters(text: str) -> dict[str, str]:
    """`k=5;release=1` -> {"k": "5", "release": "1"}; a repeated or empty key is an error."""
    out: dict[str, str] = {}
    for item in filter(None, text.split(";")):
        key, _, value = item.partition("=")
        if not key:
            raise SplitRequestError(f"parameter {item!r} has no name")
        if key in out:
            raise SplitRequestError(f"parameter {key} given twice")
        out[key] = value
    return out


def _params_from_payload(payload: bytes) -> dict[str, str]:
    """A SplitConfig payload as the equivalent parameters (its `source` default counts as user)."""
    try:
        req = decode(payload, SplitConfig)
    except WireError as exc:
        raise SplitRequestError(f"payload is not a valid SplitConfig: {exc}") from exc
    source = "controller" if req.source == "controller" else "user"
    params = {"k": str(req.k), "codec": req.codec, "source": source}
    if source == "user" and not req.pinned:
        params["release"] = "1"
    return params


def _readable(asked: str) -> bool:
    """A read on a key that access control's split rules include (`splittag/*/split`, `.../split/auto`)."""
    from shared.transport.access import SPLIT_AUTO_KEY, SPLIT_KEY

    key = zenoh.KeyExpr(asked)
    return any(zenoh.KeyExpr(rule).includes(key) for rule in (SPLIT_KEY, SPLIT_AUTO_KEY))


def serve_split(
    session: zenoh.Session,
    key: str,
    state: SplitState,
    *,
    refused: Callable[[str, int, BaseException], None] | None = None,
) -> zenoh.Queryable[None]:
    """Declare the split queryable on `key` (a person's) and `key/auto` (a controller's). A refused request
    is answered with the reason and given to `refused` (what, payload bytes, why: a service's
    InputGuard.reject, which counts it and logs at most once a second; a trial's 3,000 refused gets in
    4.6 s wrote 440 kB of warnings, counted nowhere), else logged."""
    enc = encoding_for(SplitConfig.SCHEMA)
    auto = key + "/auto"

    def on_query(query: zenoh.Query) -> None:
        payload = query.payload.to_bytes() if query.payload is not None else None
        framing = framing_of(payload)  # the asker's: the reply is one it reads
        asked = str(query.key_expr)
        wildcard = keys.is_wildcard(asked)
        if wildcard and not payload and not str(query.parameters) and not _readable(asked):
            # A wildcard get beyond the split keys (`splittag/r1/**`, `splittag/r1/split/*`) reaches this
            # queryable past access control's deny rules, which apply to the keys they include, so any
            # identity read the split that way (an adversarial trial, as the secure config's camera). Reads
            # are answered only on keys those rules include, as the operator's tools ask: none here. This is
            # also what a wildcard that only overlaps `split/**` gets (`splittag/<robot>/*/stats` reaches
            # `split/stats`): it asks for something else, and an error reply beside the services' stats was
            # a fresh-clone trial's finding.
            query.drop()  # (finalised: the asker is told there are no more replies)
            return
        try:
            params = parse_parameters(str(query.parameters))
            if (params or payload) and keys.is_wildcard(asked):
                raise SplitRequestError(f"{asked} names robots by a wildcard: set one robot's split at a time")
            if asked not in (key, auto) and (params or payload):
                raise SplitRequestError(f"{asked}: the split is set on {key} or {auto}")
            applied = state.apply(params, payload, as_controller=asked == auto)
        except SplitRequestError as exc:
            if refused is not None:
                refused("split request", len(payload or b""), exc)
            else:
                log.warning("split request refused: %s", exc)
            query.reply_err(str(exc).encode(), encoding=zenoh.Encoding.TEXT_PLAIN)
            return
        # On this robot's own key (a wildcard get learns which robot answered), in the asker's framing: the
        # person's key or the controller's, whichever the asked key reaches (zenoh refuses a reply on a key
        # that does not intersect the query's: `split/auto/**` got no answer at all).
        asked_key = zenoh.KeyExpr(asked)
        on = key if asked_key.intersects(zenoh.KeyExpr(key)) else auto
        if not asked_key.intersects(zenoh.KeyExpr(on)):
            # A key of its own beneath split/ that names no split: a mistake, said. (No wildcard gets here:
            # a read through one is dropped above unless access control's split rules include it, and those
            # reach `key` or `auto`; a set through one is refused above.)
            query.reply_err(
                f"{asked}: the split is read on {key} or {auto}".encode(), encoding=zenoh.Encoding.TEXT_PLAIN
            )
            return
        query.reply(on, encode(applied, framing=framing), encoding=enc)

    return session.declare_queryable(key + "/**", on_query)  # `/**` matches the key itself too
