"""The split state's request rules: parameters and SplitConfig payloads go through the same pin guard."""

from __future__ import annotations

import contextlib
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
import zenoh

from shared.transport.split_control import SplitRequestError, SplitState, parse_parameters
from shared.wire.messages import SplitConfig, encode


def _state() -> SplitState:
    return SplitState(SplitConfig(k=7, codec="fp16", pinned=False, source="default"))


@contextlib.contextmanager
def _served(state: SplitState, guard: Any = None) -> Iterator[zenoh.Session]:
    """robot w1's split queryable over real Zenoh (a peer), and a client session to ask it."""
    from shared.transport.session import ZenohSettings, free_tcp_port, open_session
    from shared.transport.split_control import serve_split
    from shared.wire import keys

    port = free_tcp_port()
    server = open_session(ZenohSettings(mode="peer", listen=[f"tcp/127.0.0.1:{port}"]))
    client = open_session(ZenohSettings(mode="client", connect=[f"tcp/127.0.0.1:{port}"]))
    queryable = serve_split(server, keys.split("w1"), state, refused=None if guard is None else guard.reject)
    try:
        yield client
    finally:
        queryable.undeclare()
        client.close()
        server.close()


def test_a_person_pins_and_the_controller_is_refused() -> None:
    state = _state()
    assert state.apply({"k": "3"}, None) == SplitConfig(k=3, codec="fp16", pinned=True, source="user")
    with pytest.raises(SplitRequestError, match="pinned"):
        state.apply({"k": "5", "source": "controller"}, None)
    assert state.get().k == 3 and state.get().pinned
    assert not state.apply({"release": "1"}, None).pinned
    assert state.apply({"k": "5", "source": "controller"}, None) == SplitConfig(
        k=5, codec="fp16", pinned=False, source="controller"
    )


def test_a_controller_payload_cannot_override_a_pin() -> None:
    """A SplitConfig payload used to be applied as-is: pinned=False, source=controller unpinned a person's k."""
    state = _state()
    state.apply({"k": "3"}, None)
    forged = encode(SplitConfig(k=0, codec="fp16", pinned=False, source="controller"))
    with pytest.raises(SplitRequestError, match="pinned"):
        state.apply({}, forged)
    assert state.get() == SplitConfig(k=3, codec="fp16", pinned=True, source="user")
    # A controller payload can never pin either.
    state.apply({"release": "1"}, None)
    assert not state.apply({}, encode(SplitConfig(k=2, codec="fp16", pinned=True, source="controller"))).pinned


def test_a_user_payload_is_the_same_request_as_parameters() -> None:
    state = _state()
    assert state.apply({}, encode(SplitConfig(k=4, codec="fp32", pinned=True, source="user"))) == SplitConfig(
        k=4, codec="fp32", pinned=True, source="user"
    )
    released = state.apply({}, encode(SplitConfig(k=4, codec="fp32", pinned=False, source="user")))
    assert not released.pinned
    with pytest.raises(SplitRequestError, match="not both"):
        state.apply({"k": "1"}, encode(SplitConfig(k=4, codec="fp16", pinned=True, source="user")))
    with pytest.raises(SplitRequestError, match="not a valid SplitConfig"):
        state.apply({}, b"\x00garbage")


def test_parameters_are_parsed_strictly() -> None:
    state = _state()
    state.apply({"k": "3"}, None)
    assert state.apply({"release": "0"}, None).pinned  # used to unpin
    assert state.apply({"source": "user"}, None).pinned
    with pytest.raises(SplitRequestError, match="release must be"):
        state.apply({"release": "maybe"}, None)
    with pytest.raises(SplitRequestError, match="unknown"):
        state.apply({"kk": "3"}, None)
    for written in ("+5", "05", " 5", "5 ", "\u0665", "5.0", ""):  # int() takes the first five (an integrator's)
        with pytest.raises(SplitRequestError, match=r"k must be an integer 0\.\.7"):
            state.apply({"k": written}, None)
    assert parse_parameters("k=5;codec=fp32") == {"k": "5", "codec": "fp32"}
    with pytest.raises(SplitRequestError, match="twice"):
        parse_parameters("k=5;k=6")
    with pytest.raises(SplitRequestError, match="no name"):
        parse_parameters("=5")
    assert state.get() == SplitConfig(k=3, codec="fp16", pinned=True, source="user")
    # a huge value is quoted, not echoed whole into the reply and the log (a trial's 5,000-character k)
    for params in ({"k": "9" * 5000}, {"k": "x" * 5000}, {"codec": "y" * 5000}, {"z" * 5000: "1"}):
        with pytest.raises(SplitRequestError) as refused:
            state.apply(params, None)
        said = str(refused.value)
        assert len(said) < 200 and "chars)" in said, said[:300]


def test_a_wildcard_set_is_refused_over_real_zenoh() -> None:
    """`splittag/*/split?k=5` used to set every robot's split at once; reading through a wildcard is fine."""
    from shared.wire import keys
    from shared.wire.messages import decode

    state = _state()
    with _served(state) as client:
        errors = [r.err.payload.to_string() for r in client.get("splittag/*/split?k=5", timeout=5) if r.err]
        assert errors and "wildcard" in errors[0]
        assert state.get().k == 7
        ok = [r.ok for r in client.get("splittag/*/split", timeout=5) if r.ok is not None]
        assert ok and decode(ok[0].payload.to_bytes(), SplitConfig).k == 7
        ok = [r.ok for r in client.get(keys.split("w1") + "?k=5", timeout=5) if r.ok is not None]
        assert ok and state.get().k == 5
        # a `**` read gets nothing: it passes access control's deny rule on the split keys (an adversarial
        # trial read the split as the secure config's camera with `splittag/robot1/**`)
        for wide in ("splittag/w1/**", "splittag/**", "splittag/w1/split/**"):
            assert not [r for r in client.get(wide, timeout=2) if r.ok is not None or r.err is not None], wide


def test_the_controllers_key_sets_only_as_the_controller_over_real_zenoh() -> None:
    """On splittag/<r>/split/auto every set is the controller's whatever it claims: refused while a
    person's pin holds, never a pin, never a release (under access control a controller's identity
    steers only there: one that left `source` out on the person's key pinned over an operator, found by
    a fresh-clone trial). A read there answers on that key; another key beneath split sets nothing."""
    from shared.transport.split_client import SplitQueryError, query_split
    from shared.wire import keys
    from shared.wire.messages import decode

    state = _state()
    with _served(state) as client:
        applied = query_split(client, "w1", params="k=4", auto=True)
        assert applied == SplitConfig(k=4, codec="fp16", pinned=False, source="controller")
        assert query_split(client, "w1", params="k=3").pinned  # a person pins
        for params, why in (("k=5", "pinned"), ("k=5;source=user", "not 'user'"), ("release=1", "release")):
            with pytest.raises(SplitQueryError, match=why):
                query_split(client, "w1", params=params, auto=True)
        as_user = encode(SplitConfig(k=6, codec="fp16", pinned=True, source="user"))
        replies = list(client.get(keys.split_auto("w1"), payload=as_user, timeout=5))
        assert replies and replies[0].err is not None and "pinned" in replies[0].err.payload.to_string()
        assert state.get() == SplitConfig(k=3, codec="fp16", pinned=True, source="user")
        read = [r.ok for r in client.get(keys.split_auto("w1"), timeout=5) if r.ok is not None]
        assert read and str(read[0].key_expr) == keys.split_auto("w1")
        for wide in ("splittag/*/split/auto", "splittag/*/split"):
            read = [r.ok for r in client.get(wide, timeout=5) if r.ok is not None]  # answered (none once)
            assert read and decode(read[0].payload.to_bytes(), SplitConfig).k == 3, wide
        for wide in (keys.split_auto("w1") + "/**", keys.split("w1") + "/*"):  # beyond the keys the ACL rules
            assert not list(client.get(wide, timeout=2)), wide  # include: no answer (an adversarial trial)
        errors = [r.err.payload.to_string() for r in client.get(keys.split("w1") + "/other", timeout=5) if r.err]
        assert errors and "is read on" in errors[0]
        errors = [r.err.payload.to_string() for r in client.get(keys.split("w1") + "/other?k=1", timeout=5) if r.err]
        assert errors and "is set on" in errors[0] and state.get().k == 3
        query_split(client, "w1", params="release=1")
        assert query_split(client, "w1", params="k=5", auto=True).k == 5


def test_on_the_controllers_key_the_request_is_the_controllers() -> None:
    """SplitState.apply(as_controller=True), what the controller's key (split/auto) applies: a set is
    the controller's whatever it claims, never pins, is refused while a person's pin holds, and may not
    release one (as parameters or as a payload)."""
    state = _state()
    assert state.apply({"k": "4"}, None, as_controller=True).source == "controller"
    assert not state.apply(
        {}, encode(SplitConfig(k=2, codec="fp16", pinned=True, source="user")), as_controller=True
    ).pinned
    state.apply({"k": "3"}, None)  # a person pins
    for params, payload, why in (
        ({"k": "5"}, None, "pinned"),
        ({"k": "5", "source": "user"}, None, "not 'user'"),
        ({"release": "true"}, None, "release"),
        ({}, encode(SplitConfig(k=6, codec="fp16", pinned=False, source="user")), "release"),
        ({}, encode(SplitConfig(k=6, codec="fp16", pinned=True, source="user")), "pinned"),
    ):
        with pytest.raises(SplitRequestError, match=why):
            state.apply(params, payload, as_controller=True)
    assert state.get() == SplitConfig(k=3, codec="fp16", pinned=True, source="user")


def test_a_wildcard_that_only_overlaps_the_split_gets_no_error_from_it_over_real_zenoh() -> None:
    """`splittag/<r>/*/stats` reaches the split's queryable (`split/**` holds `split/stats`): the services'
    stats came with an error reply beside them (a fresh-clone trial). Such a query is dropped (serve_split's
    wildcard read rule) and gets nothing from the split; a key of its own under split/ that names no split
    is still told where to ask."""
    state = _state()
    with _served(state) as client:
        # first: the queryable answers on this path (else the empty answer below would prove nothing)
        errors = [r.err.payload.to_string() for r in client.get("splittag/w1/split/foo", timeout=5) if r.err]
        assert errors and "the split is read on" in errors[0]
        replies = list(client.get("splittag/w1/*/stats", timeout=3))
        assert replies == [], [r.err.payload.to_string() for r in replies if r.err]


def test_the_split_survives_a_restart_of_its_process(tmp_path: Path) -> None:
    """A person's pin was lost, silently, when the launcher restarted robot_infer (a fresh-clone trial):
    every change is remembered in the run's split_<robot>.json and a restarted process resumes a person's
    setting, pinned or released."""
    from shared.transport.split_control import remember_split, remembered_split, resumed_split, split_memory

    memory = split_memory(tmp_path, "r1")
    assert memory != split_memory(tmp_path, "r2")  # a fleet's robots share the run folder, not the file
    first = SplitState(
        SplitConfig(k=7, codec="fp16", pinned=False, source="default"), on_change=lambda c: remember_split(memory, c)
    )
    assert remembered_split(memory) is None
    first.apply({"k": "3"}, None)
    assert remembered_split(memory) == SplitConfig(k=3, codec="fp16", pinned=True, source="user")
    restarted = SplitState(resumed_split(memory) or SplitConfig(k=7, codec="fp16", pinned=False, source="default"))
    assert restarted.get().pinned and restarted.get().k == 3
    with pytest.raises(SplitRequestError, match="pinned"):
        restarted.apply({"k": "0"}, None, as_controller=True)
    first.apply({"release": "1"}, None)
    assert remembered_split(memory) == SplitConfig(k=3, codec="fp16", pinned=False, source="user")
    # Released, it is still the person's k: it stays until a controller changes it, restart or not (a
    # fleet trial's released k=3 came back as the configured 7).
    assert resumed_split(memory) == SplitConfig(k=3, codec="fp16", pinned=False, source="user")
    first.apply({"k": "0", "source": "controller"}, None)
    assert remembered_split(memory) is not None and resumed_split(memory) is None  # the controller's: not forced
    memory.write_text('{"k": 11}')  # damaged: said, and the configured split is used
    assert remembered_split(memory) is None and resumed_split(memory) is None
    assert sorted(p.name for p in tmp_path.iterdir()) == ["split_r1.json"]  # no temporary file left


def test_a_split_get_waits_for_a_queryable_that_is_not_routed_yet() -> None:
    """A get that no queryable matches ends at once; right after a restart robot_infer's token can be seen
    before its queryable is routed (CI: 'no reply' on a set). query_split asks again until its timeout."""
    import threading
    import time

    from shared.transport.session import ZenohSettings, free_tcp_port, open_session
    from shared.transport.split_client import SplitQueryError, query_split
    from shared.transport.split_control import serve_split
    from shared.wire import keys

    port = free_tcp_port()
    server = open_session(ZenohSettings(mode="peer", listen=[f"tcp/127.0.0.1:{port}"]))
    client = open_session(ZenohSettings(mode="client", connect=[f"tcp/127.0.0.1:{port}"]))
    state = _state()
    declared: list[zenoh.Queryable[None]] = []
    late = threading.Timer(1.0, lambda: declared.append(serve_split(server, keys.split("w1"), state)))
    try:
        started = time.monotonic()
        with pytest.raises(SplitQueryError, match="no reply"):  # nothing serves it: the whole timeout
            query_split(client, "w1", timeout_secs=0.6)
        assert time.monotonic() - started >= 0.5
        late.start()
        assert query_split(client, "w1", params="k=4", timeout_secs=10).k == 4  # asked before it existed
        assert state.get().k == 4
    finally:
        late.cancel()
        for q in declared:
            q.undeclare()
        client.close()
        server.close()


def test_a_split_set_that_gets_no_answer_in_time_says_it_is_not_confirmed() -> None:
    """A set whose query reaches robot_infer's side but gets no answer (a two-host trial's uplink was down:
    the CLI printed a bare 'Timeout' and nothing said whether k had changed)."""
    from shared.transport.session import ZenohSettings, free_tcp_port, open_session
    from shared.transport.split_client import SplitQueryError, query_split
    from shared.wire import keys

    endpoint = f"tcp/127.0.0.1:{free_tcp_port()}"
    robot = open_session(ZenohSettings(mode="router", listen=[endpoint]))
    held: list[object] = []
    try:
        silent = robot.declare_queryable(keys.split("mute1"), held.append)  # takes the query, never answers
        asker = open_session(ZenohSettings(mode="client", connect=[endpoint]))
        try:
            with pytest.raises(SplitQueryError, match="not confirmed and may not have been taken") as info:
                query_split(asker, "mute1", params="k=3", timeout_secs=0.5)
            assert "within 0.5 s (zenoh: Timeout)" in str(info.value)
        finally:
            asker.close()
        held.clear()
        silent.undeclare()
    finally:
        robot.close()


def test_refused_split_requests_and_probes_are_counted_and_logged_once_a_second(
    caplog: pytest.LogCaptureFixture,
) -> None:
    """A trial flooded the split queryable (3,000 refused gets in 4.6 s: 440 kB of warnings in
    robot_infer.log, counted nowhere) and the echo (2,000 garbage probes, as many warnings): with the
    service's guard, each refusal is counted by reason and said at most once a second, and still answered."""
    from shared.runtime.guard import InputGuard
    from shared.transport.probe import serve_echo
    from shared.wire import keys

    guard = InputGuard("robot_infer", schedule=lambda _secs, _fn: None)
    state = _state()
    with caplog.at_level("WARNING"), _served(state, guard) as client:
        for i in range(40):
            errors = [r.err for r in client.get(keys.split("w1") + f"/x{i}?k=999", timeout=5) if r.err is not None]
            assert errors  # still answered, with the reason
        echo_guard = InputGuard("edge_infer", schedule=lambda _secs, _fn: None)
        server = client  # (a queryable on the client's session: the same code path)
        echo = serve_echo(server, keys.echo("w1"), max_bytes=1 << 20, refused=echo_guard.reject)
        try:
            for _ in range(40):
                list(client.get(keys.echo("w1"), payload=b"garbage", timeout=5))
            # a key discovery is no probe: unanswered and not counted (it read as a refused one)
            for discovery in ("splittag/**", "splittag/w1/*/v1", "splittag/w1/**"):
                assert [
                    r for r in client.get(discovery, timeout=5) if "echo" in str(r.ok.key_expr if r.ok else "")
                ] == []
            assert [r.ok is not None for r in client.get(keys.echo("w1"), timeout=5)] == [True]  # empty probe: answered
        finally:
            echo.undeclare()
    assert guard.rejected == {"split request: SplitRequestError": 40}
    assert sum(echo_guard.rejected.values()) == 41  # (the empty probe on the echo's own key too)
    assert state.get().k == 7
    said = [r for r in caplog.records if "split request" in r.getMessage() or "probe" in r.getMessage()]
    assert len(said) <= 6, [r.getMessage() for r in said]  # (at most one a second each, not 80)
