"""Gets that wait for an answer, not for the first route."""

from __future__ import annotations

import time

import zenoh

RETRY_SECS = 0.25


def get_until_answered(session: zenoh.Session, selector: str, timeout_secs: float) -> list[zenoh.Reply]:
    """Every reply to one get on `selector`, asked again until something answers or `timeout_secs` pass.

    A get that no queryable matches ends at once with no reply. Right after a router or a service
    restarts, a service's liveliness token can already be seen while its queryable is not yet routed:
    CI saw a split get sent just after robot_infer's token came back end at once with nothing (about 1
    run in 4 here). So `timeout_secs` is how long the caller waits for an answer, not how long one get
    may take. A set asked again is the same set."""
    deadline = time.monotonic() + timeout_secs
    while True:
        left = deadline - time.monotonic()
        replies = list(session.get(selector, timeout=max(left, 0.05)))
        if replies or deadline - time.monotonic() <= RETRY_SECS:
            return replies
        time.sleep(RETRY_SECS)
