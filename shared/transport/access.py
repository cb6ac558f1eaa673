"""Who may do what on splittag's keys: roles by certificate common name, as Zenoh access control.

The routers (edge_infer's and robot_infer's sessions) enforce it on the messages of every peer and
client they serve; a process is identified by the common name of the certificate it presented over
mutual TLS. Default deny: a certificate of an unknown name may do nothing. The robot and the edge are
trusted with everything (the routers forward each other's traffic). The other roles may do
everything on `splittag/**` except, explicitly denied (deny wins over allow in Zenoh's ACL):

| role | may not |
| --- | --- |
| operator (people, `splittag split`, the launcher's monitor) | publish any data |
| controller | publish data other than its ControllerState; query the map (save) |
| slam | publish data other than camera poses and its map; query the split (steer) or the map (save) |
| camera | publish data other than frames, ground truth and data-set stamps; query the split or the map |

and each role may declare only its own queryables (slam its map and stats, the controller its
stats): nobody can impersonate robot_infer's split control, the edge's link probe or another
service's map or stats. Zenoh's ACL cannot tell a
split get from a set (both are queries): steering is allowed to the operator and controller only.
"""

from __future__ import annotations

from typing import Any, Final

from pydantic import BaseModel, ConfigDict, Field

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
SPLIT_KEY: Final[str] = "splittag/*/split"
# Every version of a key (`/**` also matches the key itself): the map went v2 -> v3 while this said v2,
# and every identity could query (and save) the map unchecked; tests/test_access.py now checks these
# against the keys the services use.
MAP_KEY: Final[str] = "splittag/*/map/**"
# The queryables the services declare; a role may declare only its own (MAY_SERVE).
SERVICE_QUERYABLES: Final[dict[str, str]] = {
    "split": "splittag/*/split",
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
MAY_STEER: Final[set[str]] = {"operators", "controllers"}
MAY_SAVE_MAP: Final[set[str]] = {"operators"}


class AccessControlSettings(BaseModel):
    """Certificate common names per role (deploy/make-certs.sh issues one certificate per name)."""

    model_config = ConfigDict(extra="forbid")

    enabled: bool = False
    trusted: list[str] = Field(default_factory=lambda: ["edge", "robot"])
    operators: list[str] = Field(default_factory=lambda: ["operator"])
    controllers: list[str] = Field(default_factory=lambda: ["controller"])
    slam: list[str] = Field(default_factory=lambda: ["slam"])
    cameras: list[str] = Field(default_factory=lambda: ["camera"])


def _rule(rule_id: str, permission: str, messages: list[str], keys: list[str], flows: list[str]) -> dict[str, Any]:
    return {"id": rule_id, "permission": permission, "messages": messages, "flows": flows, "key_exprs": keys}


def access_control_config(settings: AccessControlSettings) -> dict[str, Any]:
    """The `access_control` section of a router's Zenoh config for these roles."""
    rules = [_rule("everything", "allow", ALL_MESSAGES, ["splittag/**"], ["ingress", "egress"])]
    rules.append(_rule("no-steer", "deny", ["query"], [SPLIT_KEY], ["ingress"]))
    rules.append(_rule("no-map-query", "deny", ["query"], [MAP_KEY], ["ingress"]))
    subjects: list[dict[str, Any]] = []
    policies: list[dict[str, Any]] = []

    def role(role_id: str, names: list[str], rule_ids: list[str]) -> None:
        if not names:
            return
        subjects.append({"id": role_id, "cert_common_names": names})
        policies.append({"id": f"{role_id}-policy", "rules": rule_ids, "subjects": [role_id]})

    role("trusted", settings.trusted, ["everything"])
    for name, may in MAY_PUBLISH.items():
        denied = sorted(set(DATA_KEYS) - may)
        rule_id = f"{name}-no-publish"
        rules.append(_rule(rule_id, "deny", ["put", "delete"], [DATA_KEYS[k] for k in denied], ["ingress"]))
        serve_id = f"{name}-no-serve"
        not_theirs = [SERVICE_QUERYABLES[q] for q in sorted(set(SERVICE_QUERYABLES) - MAY_SERVE[name])]
        rules.append(_rule(serve_id, "deny", ["declare_queryable"], not_theirs, ["ingress"]))
        extra = [serve_id]
        if name not in MAY_STEER:
            extra.append("no-steer")
        if name not in MAY_SAVE_MAP:
            extra.append("no-map-query")
        role(name, getattr(settings, name), ["everything", rule_id, *extra])
    return {
        "enabled": True,
        "default_permission": "deny",
        "rules": rules,
        "subjects": subjects,
        "policies": policies,
    }
