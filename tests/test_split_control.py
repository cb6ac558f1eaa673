"""The split state's request rules: parameters and SplitConfig payloads go through the same pin guard."""

from __future__ import annotations

import pytest

from shared.transport.split_control import SplitRequestError, SplitState
from shared.wire.messages import SplitConfig, encode


def _state() -> SplitState:
    return SplitState(SplitConfig(k=7, codec="fp16", pinned=False, source="default"))


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
