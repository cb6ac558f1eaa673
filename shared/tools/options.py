"""Command-line options generated from a pydantic settings model, so a CLI never re-declares (and
drifts from) the defaults its settings own: `add_model_options(parser, TrainSettings)`, then
`model_from_args(TrainSettings, args)`. Field descriptions become the help text."""

from __future__ import annotations

import argparse
import types
from pathlib import Path
from typing import Any, Literal, TypeVar, Union, get_args, get_origin

from pydantic import BaseModel
from pydantic_core import PydanticUndefined

M = TypeVar("M", bound=BaseModel)


def _option(name: str) -> str:
    return "--" + name.replace("_", "-")


def add_model_options(parser: argparse.ArgumentParser, model: type[BaseModel]) -> None:
    """One option per field: bools as --x/--no-x, Literals as choices, lists as repeatable options,
    `X | None` as optional X; fields without a default are required."""
    for name, field in model.model_fields.items():
        annotation: Any = field.annotation
        required = field.default is PydanticUndefined and field.default_factory is None
        default = None if required else field.get_default(call_default_factory=True)
        kwargs: dict[str, Any] = {"help": field.description, "dest": name}
        if get_origin(annotation) in (Union, types.UnionType):
            inner = [a for a in get_args(annotation) if a is not type(None)]
            if len(inner) != 1:
                raise TypeError(f"{model.__name__}.{name}: cannot make an option of {annotation}")
            annotation = inner[0]
        origin = get_origin(annotation)
        if annotation is bool:
            kwargs["action"] = argparse.BooleanOptionalAction
        elif origin is Literal:
            kwargs["choices"] = list(get_args(annotation))
        elif origin is list:
            (item,) = get_args(annotation)
            kwargs.update(action="append", type=item)
            default = None if required else default
        elif annotation in (int, float, str, Path):
            kwargs["type"] = annotation
        else:
            raise TypeError(f"{model.__name__}.{name}: cannot make an option of {annotation}")
        if required:
            kwargs["required"] = True
        else:
            kwargs["default"] = default
            if kwargs["help"]:
                kwargs["help"] += f" (default: {default})"
        parser.add_argument(_option(name), **kwargs)


def model_from_args(model: type[M], args: argparse.Namespace) -> M:
    """The model built from the options add_model_options declared."""
    return model(**{name: getattr(args, name) for name in model.model_fields})
