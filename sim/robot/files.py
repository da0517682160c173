"""Descriptions read from YAML files (robots, variation sets, worlds): each refused with the file, the
field and the reason, in one line."""

from __future__ import annotations

from pathlib import Path

from pydantic import ValidationError


def validation_message(exc: ValidationError) -> str:
    """One line per problem, each naming the field: 'n_joints: Input should be greater than or
    equal to 4 (got 2)'."""
    lines = []
    for err in exc.errors():
        where = ".".join(str(p) for p in err["loc"]) or "robot"
        msg = err["msg"].removeprefix("Value error, ")
        if err["type"] == "extra_forbidden":
            msg = "unknown field (a typo? see `snakeloco robot show --help` for the fields)"
        got = f" (got {err['input']!r})" if err["loc"] and err["type"] != "extra_forbidden" else ""
        lines.append(f"{where}: {msg}{got}")
    return "; ".join(lines)


def validated(cls, data: object, source: str, error: type[ValueError], kind: str):
    """``cls`` validated from a parsed mapping; ``error`` names ``source``, the field and the reason."""
    if not isinstance(data, dict):
        raise error(f"{source}: a {kind} description is a mapping of fields, got {type(data).__name__}")
    try:
        return cls.model_validate(data)
    except ValidationError as exc:
        message = validation_message(exc).replace("snakeloco robot show", f"snakeloco {kind} show")
        raise error(f"{source}: {message}") from None


def read_yaml(path: Path, error: type[ValueError], hint: str = "") -> object:
    """A YAML file's contents ({} for an empty one); ``error`` names the file and why it cannot be read."""
    import yaml

    try:
        text = path.read_text()
    except OSError as exc:
        raise error(f"{path}: cannot read ({exc.strerror}){hint}") from None
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        raise error(f"{path}: not YAML ({str(exc).splitlines()[0]})") from None
    return {} if data is None else data
