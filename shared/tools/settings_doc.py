"""Every setting of every service, with its default and what it does, read from the settings models
themselves: `splittag settings [SERVICE ...]` prints them, and docs/services.md's *Settings reference*
is this module's markdown (written by `python -m shared.tools.docgen`; tests/test_docs.py fails when the
two differ, so a setting cannot be added, renamed or given another default without the doc).

The meaning of a field is the comment on its line, or the comment block right above it, in the
class that declares it (the settings' source is the one place it is written).
"""

from __future__ import annotations

import argparse
import importlib
import inspect
import io
import json
import re
import sys
import tokenize
import typing
from collections.abc import Iterator
from enum import Enum
from pathlib import Path
from typing import Any, Final, NamedTuple

from pydantic import BaseModel
from pydantic_core import PydanticUndefined

SERVICES: Final[tuple[str, ...]] = ("camera", "robot_infer", "edge_infer", "controller", "slam")
COMMON: Final[str] = "common"  # the fields every service has (ServiceSettings), also set under [common]


class Row(NamedTuple):
    """One setting: its dotted name as TOML and the environment spell it, its default, its meaning."""

    name: str
    default: str
    meaning: str


def settings_class(service: str) -> type[BaseModel]:
    """The settings model of a service (`common`: the fields every service has)."""
    if service == COMMON:
        from shared.runtime.settings import ServiceSettings

        return ServiceSettings
    module = importlib.import_module(f"services.{service}.settings")
    for value in vars(module).values():
        if isinstance(value, type) and issubclass(value, BaseModel) and getattr(value, "SERVICE", None) == service:
            return value
    raise LookupError(f"services.{service}.settings defines no settings class for {service!r}")


def _comments(cls: type) -> dict[str, str]:
    """field name -> its comment (same line, else the comment lines right above it) in `cls`'s body."""
    try:
        source = inspect.getsource(cls)
    except (OSError, TypeError):
        return {}
    lines = source.splitlines()
    trailing: dict[int, str] = {}
    for tok in tokenize.generate_tokens(io.StringIO(source).readline):
        if tok.type == tokenize.COMMENT:
            trailing[tok.start[0]] = tok.string.lstrip("#").strip()
    out: dict[str, str] = {}
    field_line = re.compile(r"^    ([a-z_][a-z0-9_]*)\s*:")
    for number, line in enumerate(lines, start=1):
        match = field_line.match(line)
        if match is None:
            continue
        parts = []
        above = number - 1
        block: list[str] = []
        while above >= 1 and lines[above - 1].strip().startswith("#"):
            block.insert(0, lines[above - 1].strip().lstrip("#").strip())
            above -= 1
        parts.extend(block)
        if number in trailing and not line.strip().startswith("#"):
            parts.append(trailing[number])
        # "... and this": a comment continued from the field above reads on its own
        text = " ".join(re.sub(r"^\.\.\.\s*|\s*\.\.\.$", "", p) for p in parts if p)
        out[match.group(1)] = text.strip()
    return out


def _meaning(model: type[BaseModel], name: str) -> str:
    for cls in model.__mro__:
        if name in getattr(cls, "__annotations__", {}):
            return _comments(cls).get(name, "")
    return ""


def format_default(value: Any) -> str:
    """A default as one would write it in the TOML file (`none` where the setting is unset)."""
    if value is None:
        return "none"
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, Enum):
        value = value.value
    if isinstance(value, Path):
        return json.dumps(str(value))
    if isinstance(value, str):
        return json.dumps(value)
    if isinstance(value, float):
        return repr(value)
    if isinstance(value, (tuple, list)):
        return "[" + ", ".join(format_default(v) for v in value) + "]"
    if isinstance(value, dict):
        return "{" + ", ".join(f"{k} = {format_default(v)}" for k, v in value.items()) + "}"
    if isinstance(value, BaseModel):
        return "(below)"
    return str(value)


def _nested_model(annotation: Any) -> type[BaseModel] | None:
    for candidate in (annotation, *typing.get_args(annotation)):
        if isinstance(candidate, type) and issubclass(candidate, BaseModel):
            return candidate
    return None


def _choices(annotation: Any) -> list[str]:
    """The values a Literal setting takes (an optional Literal's too)."""
    for candidate in (annotation, *typing.get_args(annotation)):
        if typing.get_origin(candidate) is typing.Literal:
            return [str(v) for v in typing.get_args(candidate)]
    return []


def _limits(field: Any) -> str:
    """A number setting's bounds as its model checks them ("> 0, <= 1"; empty without any): a contributor
    found the reference silent on them (the model refuses 0 for a `gt=0` field at start-up)."""
    out = []
    for constraint in field.metadata:
        for attr, sign in (("gt", ">"), ("ge", ">="), ("lt", "<"), ("le", "<=")):
            bound = getattr(constraint, attr, None)
            if bound is not None:
                out.append(f"{sign} {bound}")
    return ", ".join(out)


def short(text: str, max_chars: int = 240) -> str:
    """The first sentence of a meaning (the source has the rest), cut at `max_chars`."""
    match = re.search(r"(?<=[a-z0-9)])\.\s+(?=[A-Z(])", text)
    first = text[: match.start() + 1] if match else text
    return first if len(first) <= max_chars else first[: max_chars - 3].rsplit(" ", 1)[0] + " ..."


def rows(model: type[BaseModel], *, skip: frozenset[str] = frozenset(), prefix: str = "") -> Iterator[Row]:
    """Every leaf setting of `model` (nested settings flattened to dotted names), in declaration order."""
    for name, field in model.model_fields.items():
        if not prefix and name in skip:
            continue
        if field.default_factory is not None:
            default = field.default_factory()  # type: ignore[call-arg]
        else:
            default = None if field.default is PydanticUndefined else field.default
        nested = _nested_model(field.annotation)
        dotted = prefix + name
        if nested is not None:
            meaning = _meaning(model, name)
            if default is None:
                yield Row(dotted, "none", meaning or f"unset; its fields below when set ({nested.__name__})")
            yield from rows(nested, prefix=dotted + ".")
        else:
            meaning = _meaning(model, name)
            choices = _choices(field.annotation)
            if choices:
                meaning = f"one of {' | '.join(choices)}" + (f": {meaning}" if meaning else "")
            if limits := _limits(field):
                meaning = f"({limits}) {meaning}".strip()
            yield Row(dotted, format_default(default), meaning)


def service_rows(service: str) -> list[Row]:
    """A service's own settings (the common ones only under `common`)."""
    model = settings_class(service)
    skip = frozenset() if service == COMMON else frozenset(settings_class(COMMON).model_fields)
    return list(rows(model, skip=skip))


def _cell(text: str) -> str:
    return text.replace("|", "\\|").replace("<", "&lt;").replace(">", "&gt;") or "-"


def reference_markdown() -> str:
    """docs/services.md's settings reference (shared.tools.docgen puts it between its markers)."""
    out = io.StringIO()
    out.write(
        "Every setting with its default, generated from the settings models (`splittag settings SERVICE`\n"
        "prints the same). A service reads `[common]` and then its own table of the TOML file; the\n"
        "environment overrides both: `SPLITTAG_<SERVICE>_<NAME>`, nested names joined by `__`\n"
        "(`SPLITTAG_ROBOT_INFER_STAGE1__LINES__ENABLED=false`).\n"
    )
    for service in (COMMON, *SERVICES):
        title = "every service (`[common]` or the service's table)" if service == COMMON else f"`[{service}]`"
        out.write(f"\n### {title}\n\n| setting | default | meaning |\n| --- | --- | --- |\n")
        for row in service_rows(service):
            out.write(f"| `{row.name}` | `{_cell(row.default)}` | {_cell(short(row.meaning))} |\n")
    return out.getvalue()


_UNSET_PARENT: Final = object()


def _value_at(settings: BaseModel, dotted: str) -> Any:
    value: Any = settings
    for part in dotted.split("."):
        if value is None:
            return _UNSET_PARENT  # a field of an optional group that is not set (zenoh.tls without TLS)
        value = getattr(value, part)
    return value


def resolved_rows(service: str, config_file: Path | None) -> list[Row]:
    """Every setting of a service (the common ones included) as `config_file` and the environment
    resolve them; `meaning` says the default where the value differs from it."""
    model = settings_class(service)
    settings = model.load(config_file)  # type: ignore[attr-defined]
    out = []
    for row in rows(model):
        raw = _value_at(settings, row.name)
        if raw is _UNSET_PARENT:
            continue
        value = format_default(raw)
        out.append(Row(row.name, value, "" if value == row.default else f"default {row.default}"))
    return out


def print_rows(services: list[str], *, config_file: Path | None = None, resolve: bool = False) -> None:
    """Plain text for a terminal: one block per service; `resolve`: the values `config_file` (and the
    environment) give, each changed one with its default."""
    for service in services:
        if resolve and service == COMMON and len(services) > 1:
            continue  # every service's block holds them, resolved with its own table
        table = resolved_rows(service, config_file) if resolve else service_rows(service)
        print(f"[{service}]" + (f"  ({config_file or 'defaults and environment'})" if resolve else ""))
        width = max(len(r.name) for r in table)
        for row in table:
            mark = "*" if resolve and row.meaning else " "
            print(f" {mark}{row.name:<{width}}  = {row.default}" + (f"   # {row.meaning}" if row.meaning else ""))
        print()


def add_arguments(ap: argparse.ArgumentParser) -> None:
    """The arguments `splittag settings` shares with this module's entry point."""
    ap.add_argument("services", nargs="*", metavar="SERVICE", help=f"{', '.join((COMMON, *SERVICES))} (default: all)")
    ap.add_argument(
        "--config",
        type=Path,
        default=None,
        help="show the values this TOML file and this shell's SPLITTAG_* variables give, changed ones marked * with "
        "their default (what a run's processes really ran with is in its settings/*.json)",
    )


def run(args: argparse.Namespace) -> int:
    """Print the settings of the services asked for (all by default)."""
    unknown = [s for s in args.services if s not in (COMMON, *SERVICES)]
    if unknown:
        print(f"unknown service {', '.join(unknown)} (known: {', '.join((COMMON, *SERVICES))})", file=sys.stderr)
        return 2
    print_rows(args.services or [COMMON, *SERVICES], config_file=args.config, resolve=args.config is not None)
    return 0
