"""Client side of the split protocol (what `splittag split get|set|release` does)."""

from __future__ import annotations

import zenoh

from shared.transport.query import get_until_answered
from shared.transport.session import TlsSettings, ZenohSettings, open_session
from shared.wire import keys
from shared.wire.messages import SplitConfig, decode


class SplitQueryError(RuntimeError):
    """The robot refused the request or did not answer."""


def query_split(
    session: zenoh.Session,
    robot_id: str,
    *,
    params: str = "",
    timeout_secs: float = 5.0,
    identity: str | None = None,
    auto: bool = False,
    ask_again: bool = True,
) -> SplitConfig:
    """One get on splittag/<robot_id>/split[?params] (`auto`: on the controller's key, split/auto, where
    every set is a controller's); returns the reply's SplitConfig. `identity`: the certificate the
    session presents (TLS), named when nothing answers. `ask_again`: until something answers or the
    timeout passes (get_until_answered); False for a caller that asks again anyway (the controller,
    every decision: it would otherwise block its decisions while robot_infer is away)."""
    key = keys.split_auto(robot_id) if auto else keys.split(robot_id)
    selector = key + (f"?{params}" if params else "")
    replies = (
        get_until_answered(session, selector, timeout_secs)
        if ask_again
        else list(session.get(selector, timeout=timeout_secs))
    )
    for reply in replies:
        if reply.ok is not None:
            return decode(reply.ok.payload.to_bytes(), SplitConfig)
        err = reply.err.payload.to_string() if reply.err is not None else "unknown error"
        if err.strip().lower() == "timeout":  # zenoh's own: the query reached robot_infer's side, no answer came
            raise SplitQueryError(
                f"no answer on {selector} within {timeout_secs:g} s (zenoh: Timeout): "
                + (
                    "the change is not confirmed and may not have been taken; `split get` says which k runs"
                    if params
                    else "is the link to the robot up?"
                )
            )
        raise SplitQueryError(err)
    if identity is not None:  # access control drops a query it denies: no reply, no error
        raise SplitQueryError(
            f"no reply on {selector}: robot_infer is not running, or access control does not let "
            f"{identity!r} ask it (a denied query gets no reply)"
        )
    raise SplitQueryError(f"no reply on {selector} (is robot_infer running?)")


def every_split(
    session: zenoh.Session, *, timeout_secs: float = 5.0, identity: str | None = None
) -> dict[str, SplitConfig | str]:
    """Every robot's split (a get on splittag/*/split: each robot_infer answers on its own key); a robot
    whose answer is an error or cannot be read gets the reason instead, so one does not hide the others."""
    selector = keys.for_every_robot(keys.split("any"))
    found: dict[str, SplitConfig | str] = {}
    for reply in get_until_answered(session, selector, timeout_secs):
        if reply.ok is not None:
            where = str(reply.ok.key_expr)
            try:
                found[keys.robot_of(where)] = decode(reply.ok.payload.to_bytes(), SplitConfig)
            except ValueError as exc:  # WireError, or a reply on a key that names no robot
                found[where] = f"refused its reply: {exc}"
        elif reply.err is not None:
            found[f"(error {len(found)})"] = reply.err.payload.to_string()
    if not found:
        hint = f"; or access control does not let {identity!r} ask it" if identity else ""
        raise SplitQueryError(f"no reply on {selector} (is any robot_infer running?{hint})")
    return dict(sorted(found.items()))


def split_line(robot_id: str, cfg: SplitConfig) -> str:
    """What `splittag split` prints for one robot."""
    return f"{robot_id} k={cfg.k} codec={cfg.codec} pinned={cfg.pinned} source={cfg.source}"


def split_query(
    robot_id: str,
    connect: list[str],
    *,
    k: int | None,
    release: bool,
    codec: str | None = None,
    tls: TlsSettings | None = None,
) -> str:
    """CLI helper: get, set (k and/or codec) or release; returns a printable line. `tls`: the
    operator's certificate in a TLS deployment (deploy/secure.toml)."""
    # A person waits at the prompt: 5 s to reach the router, not the services' patient default.
    session = open_session(ZenohSettings(mode="client", connect=connect, tls=tls, connect_timeout_secs=5.0))
    try:
        sets = [f"k={k}"] if k is not None else []
        sets += [f"codec={codec}"] if codec is not None else []
        params = "release=1" if release else ";".join(sets)  # Zenoh separates selector parameters by ';'
        if robot_id == "*":  # reading every robot's (robot_infer refuses a set through a wildcard)
            if params:
                raise SplitQueryError("a set or release names one robot (--robot-id), not '*'")
            found = every_split(session, identity=tls.certificate.stem if tls else None)
            return "\n".join(split_line(r, c) if isinstance(c, SplitConfig) else f"{r} {c}" for r, c in found.items())
        cfg = query_split(session, robot_id, params=params, identity=tls.certificate.stem if tls else None)
        return split_line(robot_id, cfg)
    finally:
        session.close()
