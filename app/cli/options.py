"""Pydantic configs as the command line: tyro builds the flags from the models, pydantic checks them.

Every default and every bound lives once, in the config model that uses it (``Field(ge=...)``). The
CLI adds two things through a tyro constructor rule for pydantic models:

- a model's validation error surfaces as ``OptionError`` (not a ValueError, which tyro would print
  as its own boxed message), so ``snakeloco`` ends with one line naming the flag and its range:
  ``snakeloco: error: --ensemble must be at least 2, got 1``;
- fields whose metadata says ``{"cli": False}`` (set by the data or fixed by the product, e.g. the
  model's number of joints) are not offered as flags and keep their defaults.
"""

from __future__ import annotations

import dataclasses
import math
import threading
import warnings
from pathlib import Path
from typing import Annotated

import tyro
from pydantic import BaseModel, ConfigDict, Field, ValidationError
from tyro.constructors import ConstructorRegistry, StructConstructorSpec, StructTypeInfo


class OptionError(Exception):
    """A command-line value the command cannot take, in one line naming the flag. Deliberately not a
    ValueError: tyro catches those while building a command and prints them in its own format."""

    @classmethod
    def from_validation(cls, model: type[BaseModel], error: ValidationError) -> OptionError:
        """The first bad field of a model's validation error, as its flag with its bounds and value."""
        first = error.errors()[0]
        name = str(first["loc"][0]) if first["loc"] else ""
        return cls(describe(name, first))


def flag(name: str) -> str:
    """The command-line flag of a config field."""
    return "--" + name.replace("_", "-")


def describe(name: str, error: dict) -> str:
    """A pydantic error of field ``name`` as one line naming the flag and the bound it
    broke (pydantic's error context carries the bound: ``{"ge": 2}``)."""
    value, ctx = error.get("input"), error.get("ctx") or {}
    what = flag(name)
    if isinstance(value, float) and not math.isfinite(value):
        return f"{what} must be a finite number, got {value}"
    if isinstance(value, int | float):
        if "gt" in ctx and isinstance(value, int) and isinstance(ctx["gt"], int):
            ctx = {"ge": ctx["gt"] + 1}  # a whole number above 0 is one of at least 1
        if ctx.get("gt") == 0:
            return f"{what} must be positive, got {value:g}"
        for key, words in (
            ("ge", "at least"),
            ("gt", "greater than"),
            ("le", "at most"),
            ("lt", "less than"),
        ):
            if key in ctx:
                return f"{what} must be {words} {ctx[key]:g}, got {value:g}"
    return f"{what}: {error.get('msg', 'invalid value')}"


def _offered(model: type[BaseModel], name: str) -> bool:
    extra = model.model_fields[name].json_schema_extra
    return not (isinstance(extra, dict) and extra.get("cli") is False)


REGISTRY = ConstructorRegistry()
_inside = threading.local()


@REGISTRY.struct_rule
def _pydantic_on_the_command_line(info: StructTypeInfo) -> StructConstructorSpec | None:
    """tyro's own rule for a pydantic model, with the hidden fields left out and validation errors
    raised as ``OptionError``."""
    model = info.type
    if getattr(_inside, "active", False) or not (isinstance(model, type) and issubclass(model, BaseModel)):
        return None
    _inside.active = True  # ask tyro's default rules for the spec, without coming back here
    try:
        spec = ConstructorRegistry.get_struct_spec(info)
    finally:
        _inside.active = False
    if not isinstance(spec, StructConstructorSpec):
        return spec

    def instantiate(**kwargs):
        try:
            return spec.instantiate(**kwargs)
        except ValidationError as exc:
            raise OptionError.from_validation(model, exc) from None

    fields = tuple(f for f in spec.fields if _offered(model, f.name))
    return dataclasses.replace(spec, instantiate=instantiate, fields=fields)


def parse(commands: dict[str, type], args: list[str], prog: str, description: str | None = None):
    """The chosen command's model, parsed from ``args`` (``OptionError`` for a value out of bounds)."""
    return tyro.extras.subcommand_cli_from_dict(
        commands, args=args, prog=prog, description=description, registry=REGISTRY
    )


def parse_one(command: type, args: list[str], prog: str, default: BaseModel):
    """One command's model from ``args``, starting from the field values of ``default`` (built with
    ``model_construct``; ``tyro.MISSING`` marks a field still required)."""
    return tyro.cli(command, args=args, prog=prog, default=default, registry=REGISTRY)


# --- what every command shares ----------------------------------------------------------------

Flat = tyro.conf.OmitArgPrefixes
"""A nested config whose fields are flags of their own (``--epochs``, not ``--train.epochs``)."""
Workers = Annotated[int | None, Field(ge=1)]
Seed = Annotated[int, Field(ge=0)]  # numpy's generators take no negative seed
Ensemble = Annotated[int, Field(ge=2)]  # the replay and at least one perturbed copy: a spread needs two
Checkpoint = Annotated[
    Path | None,
    tyro.conf.arg(
        help="A checkpoint directory, or a shipped one by gait family: structured (the default) or paper.",
        metavar="structured|paper|DIR",
    ),
]
WorldName = Annotated[str, tyro.conf.arg(metavar="flat|rough|steps|pegs|slope10|FILE.yaml")]
"""The ground a command replays on: flat (the plane), a shipped world (``sim/worlds``) or a world YAML."""
Json = Annotated[bool, tyro.conf.arg(help="Print the figures as one JSON object on the last line.")]


# ``--json`` is a field named json, which shadows pydantic's deprecated ``BaseModel.json`` method: fine
# for these option models, which are never serialised that way.
warnings.filterwarnings("ignore", message='Field name "json"', category=UserWarning)


class Command(BaseModel):
    """A subcommand's options (frozen, no unknown fields, no NaN)."""

    model_config = ConfigDict(frozen=True, extra="forbid", allow_inf_nan=False)
