"""Who may do what on splittag's keys: roles by certificate common name, as Zenoh access control.

The routers (edge_infer's and robot_infer's sessions) enforce it on the messages of every peer and
client they serve; a process is identified by the common name of the certificate it presented over
mutual TLS. Default deny: a certificate of an unknown name may do nothing. The robot and the edge are
trusted with everything (the routers forward each other's traffic). The other roles may read
everything (subscribe, query, receive) but write only what is theirs, by allow-lists:

| role | may publish | may serve (queryables, replies) | liveliness token | may not query |
| --- | --- | --- | --- | --- |
| operator (people, `splittag split`, the launcher's monitor) | nothing | nothing | none | |
| controller | its ControllerState | its stats | its own | the person's split key (pin), the map (save) |
| slam | camera poses, its map | its map, its stats | its own (and a fleet's) | the split (steer), the map |
| camera | frames, ground truth, data-set stamps | nothing | its own | the split, the map |

Allow-lists, not "everything but": Zenoh applies a rule to a message whose key the rule's key
*includes*, so a deny rule on `splittag/*/tag_poses/**` never met a put on `splittag/r1/**` (which
subscribers on every key of r1 receive) or a queryable declared on `splittag/**`, and an allow-all
let both through. Now such a key is included in no allow rule of a restricted role and is refused
(tests/test_security_multiprocess.py). Zenoh's ACL cannot tell a split get from a set (both are
queries, and it never sees a query's parameters): the person's split key (`splittag/*/split`, where a
set pins) is the operator's alone, the controller's key (`splittag/*/split/auto`, every set there a
controller's, refused while a pin holds) the operator's and the controllers'; a fleet's edge workers,
trusted with every robot's data, may ask neither (`trusted_clients`); a set or a map save through a
wildcard key is refused by robot_infer and slam themselves.
"""

from __future__ import annotations

from typing import Any, Final

from pydantic import BaseModel, ConfigDict, Field, model_validator

ALL_MESSAGES: Final[list[str]] = [
    "put",
    "delete",
    "declare_subscriber",
    "query",
    "reply",
    "declare_queryable",
    "liveliness_token",
    "liveliness_query",
    "declare_liveliness_subscriber",
]
DATA_KEYS: Final[dict[str, str]] = {
    "frame": "splittag/*/frame/**",
    "ground_truth": "splittag/*/ground_truth/**",
    "frame_stamp": "splittag/*/frame_stamp/**",
    "features": "splittag/*/features/**",
    "tag_poses": "splittag/*/tag_poses/**",
    "frame_sent": "splittag/*/frame_sent/**",
    "compute": "splittag/*/compute/**",
    "camera_pose": "splittag/*/camera_pose/**",
    "map": "splittag/*/map/**",
    "controller": "splittag/*/controller/**",
}
SPLIT_KEY: Final[str] = "splittag/*/split"  # a person's: a set there pins
SPLIT_AUTO_KEY: Final[str] = "splittag/*/split/auto"  # a controller's: refused while a person's pin holds
# Every version of a key (`/**` also matches the key itself): the map went v2 -> v3 while this said v2,
# and every identity could query (and save) the map unchecked; tests/test_transport.py now checks these
# against the keys the services use.
MAP_KEY: Final[str] = "splittag/*/map/**"
# The queryables the services declare; a role may declare only its own (MAY_SERVE).
SERVICE_QUERYABLES: Final[dict[str, str]] = {
    "split": "splittag/*/split/**",  # the person's key and the controller's beneath it
    "echo": "splittag/*/echo/**",  # and the raw echo beneath it
    "map": MAP_KEY,
    "robot_infer_stats": "splittag/*/robot_infer/stats",
    "edge_infer_stats": "splittag/*/edge_infer/stats",
    "slam_stats": "splittag/*/slam/stats",
    "controller_stats": "splittag/*/controller/stats",
}
MAY_SERVE: Final[dict[str, set[str]]] = {
    "operators": set(),
    "controllers": {"controller_stats"},
    "slam": {"map", "slam_stats"},
    "cameras": set(),
}
# What each restricted role may publish; every other data key is denied to it.
MAY_PUBLISH: Final[dict[str, set[str]]] = {
    "operators": set(),
    "controllers": {"controller"},
    "slam": {"camera_pose", "map"},
    "cameras": {"frame", "ground_truth", "frame_stamp"},
}
# The liveliness tokens each restricted role may declare (readiness: nobody may impersonate another
# service's, e.g. the edge's, whose token tells the robot to stop computing on board).
MAY_ANNOUNCE: Final[dict[str, set[str]]] = {
    "operators": set(),
    "controllers": {"splittag/*/alive/controller"},
    "slam": {"splittag/*/alive/slam", "splittag/@fleet/slam"},
    "cameras": {"splittag/*/alive/camera"},
}
# Where everyone may read ('**' does not match a verbatim chunk like @fleet: the fleet's keys apart).
EVERY_KEY: Final[list[str]] = ["splittag/**", "splittag/@fleet/**"]
# Replies are not reading: a queryable a wildcard get reaches could answer as another service's key,
# so each role may reply only on the keys it serves (its `-serve` keys), like declaring them.
READ_MESSAGES: Final[list[str]] = ["declare_subscriber", "query", "liveliness_query", "declare_liveliness_subscriber"]
# What a robot's router must see of the others' interest, whatever keys it names: the edge's wildcard
# subscriptions, queryables and queries (a fleet slam subscribes to `splittag/*/ground_truth/v3`, an
# operator asks `splittag/*/split`); the data that then flows stays on the robot's own keys.
INTEREST_MESSAGES: Final[list[str]] = [*READ_MESSAGES, "declare_queryable"]
MAY_STEER: Final[set[str]] = {"operators"}  # may ask SPLIT_KEY: set and pin
# May ask SPLIT_AUTO_KEY, where every set is a controller's (a controller that asked the person's key
# without `source=controller` pinned over an operator: found by a fresh-clone trial).
MAY_STEER_AUTO: Final[set[str]] = {"operators", "controllers"}
MAY_SAVE_MAP: Final[set[str]] = {"operators"}


class AccessControlSettings(BaseModel):
    """Certificate common names per role (deploy/make-certs.sh issues one certificate per name)."""

    model_config = ConfigDict(extra="forbid")

    enabled: bool = False  # a router enforces the roles below on the sessions it serves (docs/security.md)
    # identities allowed everything, both split keys included (the routers: they forward each other's
    # queries, an operator's too; a split set under one pins as a person's does)
    trusted: list[str] = Field(default_factory=lambda: ["edge", "robot"])
    # Trusted like `trusted` but may not steer (neither split key): processes, not routers, that serve
    # every robot, such as a fleet's edge workers (they never set a split; a router's identity may not
    # be here: the routers forward each other's queries, an operator's too).
    trusted_clients: list[str] = Field(default_factory=list)
    # people: may set and pin the split (both split keys), read everything
    operators: list[str] = Field(default_factory=lambda: ["operator"])
    # may steer only on the controller's key (split/auto)
    controllers: list[str] = Field(default_factory=lambda: ["controller"])
    slam: list[str] = Field(default_factory=lambda: ["slam"])  # reads TagPoses, publishes poses and the map
    cameras: list[str] = Field(default_factory=lambda: ["camera"])  # publish frames (to their own robot's router only)
    # A fleet: certificate name -> the one robot it acts for. Such a name, listed in `trusted`,
    # `controllers` or `cameras`, gets that role's rules on that robot's keys only (a robot's router
    # may not publish, serve or read for another robot; a camera may not feed another robot).
    robot_of_name: dict[str, str] = Field(default_factory=dict)

    @model_validator(mode="after")
    def _scoped_names_have_a_role(self) -> AccessControlSettings:
        roles = set(self.trusted) | set(self.controllers) | set(self.cameras)
        stray = sorted(set(self.robot_of_name) - roles)
        if stray:
            raise ValueError(f"robot_of_name names {stray}, in no role that acts for one robot")
        for name, robot in self.robot_of_name.items():
            if not robot or any(c in robot for c in "/*$?#@ "):
                raise ValueError(f"robot_of_name[{name!r}]: {robot!r} is not a robot id")
        return self


def _rule(rule_id: str, permission: str, messages: list[str], keys: list[str], flows: list[str]) -> dict[str, Any]:
    return {"id": rule_id, "permission": permission, "messages": messages, "flows": flows, "key_exprs": keys}


KEEP_LOCAL_RULE: Final[str] = "keep-local"


def _keep_local_rule(keys: list[str]) -> dict[str, Any]:
    return _rule(KEEP_LOCAL_RULE, "deny", ["put", "delete"], keys, ["egress"])


def keep_local_config(keys: list[str]) -> dict[str, Any]:
    """An `access_control` section that only holds `keys` on this router: allow everything, but deny
    their puts on the way out to every other process (a subject with no attributes matches every
    face). The router's own session still receives them: local delivery passes no face's ACL."""
    return {
        "enabled": True,
        "default_permission": "allow",
        "rules": [_keep_local_rule(keys)],
        "subjects": [{"id": "every-face"}],
        "policies": [{"id": "keep-local-policy", "rules": [KEEP_LOCAL_RULE], "subjects": ["every-face"]}],
    }


def access_control_config(settings: AccessControlSettings, *, keep_local: list[str] | None = None) -> dict[str, Any]:
    """The `access_control` section of a router's Zenoh config for these roles. `keep_local`: keys whose
    puts go out to no face at all, whatever a role may read (the rule joins every policy, and within
    one a deny wins over its allows)."""
    rules = [
        _rule("everything", "allow", ALL_MESSAGES, EVERY_KEY, ["ingress", "egress"]),
        # What the router sends a restricted role: only what it subscribed to, queried or serves.
        _rule("receive", "allow", ALL_MESSAGES, EVERY_KEY, ["egress"]),
        _rule("read", "allow", READ_MESSAGES, EVERY_KEY, ["ingress"]),
        _rule("no-steer", "deny", ["query"], [SPLIT_KEY], ["ingress"]),
        _rule("no-auto-steer", "deny", ["query"], [SPLIT_AUTO_KEY], ["ingress"]),
        _rule("no-map-query", "deny", ["query"], [MAP_KEY], ["ingress"]),
    ]
    subjects: list[dict[str, Any]] = []
    policies: list[dict[str, Any]] = []

    def role(role_id: str, names: list[str], rule_ids: list[str]) -> None:
        if not names:
            return
        subjects.append({"id": role_id, "cert_common_names": names})
        policies.append({"id": f"{role_id}-policy", "rules": rule_ids, "subjects": [role_id]})

    scoped = settings.robot_of_name
    role("trusted", [n for n in settings.trusted if n not in scoped], ["everything"])
    role("trusted-clients", settings.trusted_clients, ["everything", "no-steer", "no-auto-steer"])
    for robot in sorted(set(scoped.values())):
        # A robot's own router: everything on its robot's keys, and reading the fleet's (the workers').
        mine = [f"splittag/{robot}/**"]
        rules.append(_rule(f"robot-{robot}-everything", "allow", ALL_MESSAGES, mine, ["ingress", "egress"]))
        rules.append(_rule(f"robot-{robot}-fleet", "allow", READ_MESSAGES, ["splittag/@fleet/**"], ["ingress"]))
        rules.append(_rule(f"robot-{robot}-fleet-receive", "allow", ALL_MESSAGES, ["splittag/@fleet/**"], ["egress"]))
        rules.append(_rule(f"robot-{robot}-interest", "allow", INTEREST_MESSAGES, EVERY_KEY, ["egress"]))
        names = [n for n in settings.trusted if scoped.get(n) == robot]
        role(
            f"robot-{robot}",
            names,
            [
                f"robot-{robot}-everything",
                f"robot-{robot}-fleet",
                f"robot-{robot}-fleet-receive",
                f"robot-{robot}-interest",
            ],
        )
    for name in MAY_PUBLISH:
        own = [
            (f"{name}-publish", ["put", "delete"], [DATA_KEYS[k] for k in sorted(MAY_PUBLISH[name])]),
            (f"{name}-serve", ["declare_queryable", "reply"], [SERVICE_QUERYABLES[q] for q in sorted(MAY_SERVE[name])]),
            (f"{name}-announce", ["liveliness_token"], sorted(MAY_ANNOUNCE[name])),
        ]
        denied = [
            r
            for r, may in (
                ("no-steer", name in MAY_STEER),
                ("no-auto-steer", name in MAY_STEER_AUTO),
                ("no-map-query", name in MAY_SAVE_MAP),
            )
            if not may
        ]
        role_names: list[str] = getattr(settings, name)
        scopes: list[str | None] = [None, *sorted({scoped[n] for n in role_names if n in scoped})]
        for scope in scopes:
            # Unscoped names: any robot's keys; a robot's names: the same rules on its keys alone.
            members = [n for n in role_names if scoped.get(n) == scope]
            suffix = "" if scope is None else f"-{scope}"
            granted = []
            for rule_id, messages, keys in own:
                if scope is not None:
                    keys = [k.replace("splittag/*/", f"splittag/{scope}/", 1) for k in keys]
                if keys:  # Zenoh refuses a rule without keys; nothing of that kind is this role's
                    rules.append(_rule(rule_id + suffix, "allow", messages, keys, ["ingress"]))
                    granted.append(rule_id + suffix)
            if scope is None:
                readers = ["receive", "read"]
            else:  # reads its own robot's keys (and the fleet's), nobody else's
                mine = [f"splittag/{scope}/**", "splittag/@fleet/**"]
                rules.append(_rule(f"{name}{suffix}-read", "allow", READ_MESSAGES, mine, ["ingress"]))
                rules.append(_rule(f"{name}{suffix}-receive", "allow", ALL_MESSAGES, mine, ["egress"]))
                rules.append(_rule(f"{name}{suffix}-interest", "allow", INTEREST_MESSAGES, EVERY_KEY, ["egress"]))
                readers = [f"{name}{suffix}-read", f"{name}{suffix}-receive", f"{name}{suffix}-interest"]
            role(f"{name}{suffix}", members, [*readers, *granted, *denied])
    if keep_local:
        rules.append(_keep_local_rule(keep_local))
        for policy in policies:
            policy["rules"].append(KEEP_LOCAL_RULE)
    return {
        "enabled": True,
        "default_permission": "deny",
        "rules": rules,
        "subjects": subjects,
        "policies": policies,
    }
