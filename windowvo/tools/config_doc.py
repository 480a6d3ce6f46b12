"""The config reference (docs/config.md), generated from the config models so that it cannot drift.

``python -m windowvo.config_doc`` prints the reference (a markdown table of every key: type,
default, meaning); ``--write docs/config.md`` replaces the text between the markers
``<!-- config-reference:start -->`` and ``<!-- config-reference:end -->``; ``--check docs/config.md``
exits with 1 when that text is out of date. Every field of every section must carry a
``Field(..., description=...)``: the generator refuses to run without one.
"""

from __future__ import annotations

import enum
import types
import typing
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

from pydantic import BaseModel
from pydantic.fields import FieldInfo

from ..config import Config
from ..errors import ConfigError

START = "<!-- config-reference:start -->"
END = "<!-- config-reference:end -->"
REGENERATE = "python -m windowvo.config_doc --write docs/config.md"


@dataclass(frozen=True)
class KeyDoc:
    key: str  # dotted, e.g. backend.odometry.robust
    type: str
    default: str
    description: str | None
    is_section: bool


def _args(annotation) -> tuple:
    return typing.get_args(annotation)


def _is_union(annotation) -> bool:
    return typing.get_origin(annotation) in (typing.Union, types.UnionType)


def _section_model(annotation) -> type[BaseModel] | None:
    """The section model of a field (``Section`` or ``Section | None``), else None."""
    if isinstance(annotation, type) and issubclass(annotation, BaseModel):
        return annotation
    if _is_union(annotation):
        models = [a for a in _args(annotation) if isinstance(a, type) and issubclass(a, BaseModel)]
        if len(models) == 1:
            return models[0]
    return None


def _type_text(annotation) -> str:
    if _is_union(annotation):
        parts = [a for a in _args(annotation) if a is not type(None)]
        text = " or ".join(_type_text(a) for a in parts)
        return f"{text} or none" if len(parts) < len(_args(annotation)) else text
    origin = typing.get_origin(annotation)
    if origin is typing.Annotated:  # a constrained type (``Annotated[int, Field(ge=1)]``): its base type
        return _type_text(_args(annotation)[0])
    if origin is typing.Literal:
        return "one of " + ", ".join(f"`{v}`" for v in _args(annotation))
    if origin is list:
        (item,) = _args(annotation) or (typing.Any,)
        return f"list of {_type_text(item)}"
    if isinstance(annotation, type) and issubclass(annotation, enum.Enum):
        return "one of " + ", ".join(f"`{m.value}`" for m in annotation)
    if isinstance(annotation, type) and issubclass(annotation, BaseModel):
        return "section"
    names = {bool: "bool", int: "int", float: "float", str: "string", Path: "path"}
    return names.get(annotation, getattr(annotation, "__name__", str(annotation)))


def _value_text(value) -> str:
    if value is None:
        return "none"
    if isinstance(value, enum.Enum):
        return f"`{value.value}`"
    if isinstance(value, bool):
        return f"`{str(value).lower()}`"
    if isinstance(value, (list, tuple)):
        return "`[" + ", ".join(str(v) for v in value) + "]`"
    return f"`{value}`"


def _default_text(field: FieldInfo, is_section: bool) -> str:
    if field.is_required():
        return "required"
    if field.default_factory is not None:
        value = field.default_factory()  # type: ignore[call-arg]
    else:
        value = field.default
    if is_section:
        return "none" if value is None else ""
    return _value_text(value)


def iter_keys(model: type[BaseModel] = Config, prefix: str = "") -> Iterator[KeyDoc]:
    """Every key of ``model``, sections first and then their keys, in declaration order."""
    for name, field in model.model_fields.items():
        key = prefix + name
        section = _section_model(field.annotation)
        description = (field.description or "").strip() or None
        if section is not None:
            optional = _is_union(field.annotation)
            yield KeyDoc(key, "section" + (" or none" if optional else ""), _default_text(field, True),
                         description, True)
            yield from iter_keys(section, key + ".")
        else:
            yield KeyDoc(key, _type_text(field.annotation), _default_text(field, False), description, False)


def missing_descriptions(model: type[BaseModel] = Config) -> list[str]:
    """Dotted keys that have no description."""
    return [k.key for k in iter_keys(model) if k.description is None]


def _cell(text: str) -> str:
    return text.replace("|", "\\|").replace("\n", " ")


def generate_reference(model: type[BaseModel] = Config) -> str:
    """The markdown table of every key; raises ConfigError when a key has no description."""
    missing = missing_descriptions(model)
    if missing:
        raise ConfigError(f"config keys without a description (add Field(..., description=...) in "
                          f"windowvo/config.py): {', '.join(missing)}")
    rows = ["| key | type | default | meaning |", "|---|---|---|---|"]
    for k in iter_keys(model):
        key = f"**`{k.key}`**" if k.is_section else f"`{k.key}`"
        rows.append(f"| {key} | {_cell(k.type)} | {_cell(k.default)} | {_cell(k.description or '')} |")
    return "\n".join(rows) + "\n"


def replace_between_markers(text: str, body: str, where: str = "docs/config.md") -> str:
    if text.count(START) != 1 or text.count(END) != 1 or text.index(START) > text.index(END):
        raise ConfigError(f"{where}: needs one '{START}' line followed by one '{END}' line")
    head, rest = text.split(START, 1)
    _, tail = rest.split(END, 1)
    return f"{head}{START}\n{body}{END}{tail}"


def reference_in(text: str, where: str = "docs/config.md") -> str:
    """The text between the markers (without them)."""
    if text.count(START) != 1 or text.count(END) != 1 or text.index(START) > text.index(END):
        raise ConfigError(f"{where}: needs one '{START}' line followed by one '{END}' line")
    inner = text.split(START, 1)[1].split(END, 1)[0]
    return inner[1:] if inner.startswith("\n") else inner
