"""The configuration reference (``docs/configuration.md``), generated from the schema itself."""

from __future__ import annotations

import types
import typing
from typing import Any

from pydantic import BaseModel
from pydantic_core import PydanticUndefined

from appliance.config.schema import AppConfig


def _models_of(annotation: Any) -> list[type[BaseModel]]:
    out: list[type[BaseModel]] = []
    if isinstance(annotation, type) and issubclass(annotation, BaseModel):
        return [annotation]
    origin = typing.get_origin(annotation)
    if origin is typing.Annotated:
        return _models_of(typing.get_args(annotation)[0])
    if origin in (typing.Union, types.UnionType, dict, tuple, list):
        for arg in typing.get_args(annotation):
            out.extend(_models_of(arg))
    return out


def _type_name(annotation: Any) -> str:
    origin = typing.get_origin(annotation)
    args = typing.get_args(annotation)
    if origin is typing.Annotated:
        return _type_name(args[0])
    if origin in (typing.Union, types.UnionType):
        return " | ".join(_type_name(a) for a in args)
    if origin in (dict, tuple, list) and args:
        return f"{origin.__name__}[{', '.join('...' if a is Ellipsis else _type_name(a) for a in args)}]"
    if isinstance(annotation, type) and not issubclass(annotation, BaseModel):
        return annotation.__name__
    text = repr(annotation).replace("typing.", "").replace("pathlib.", "")
    for mod in ("appliance.config.schema.", "appliance.config.backends."):
        text = text.replace(mod, "")
    return text.replace("<class '", "").replace("'>", "")


def _default(field: Any) -> str:
    if field.default is not PydanticUndefined:
        return repr(field.default)
    if field.default_factory is not None:
        return "(see below)"
    return "required"


def _bounds(field: Any) -> str:
    parts = []
    for m in field.metadata:
        for key, sym in (("gt", ">"), ("ge", ">="), ("lt", "<"), ("le", "<=")):
            v = getattr(m, key, None)
            if v is not None:
                parts.append(f"{sym} {v}")
    return ", ".join(parts)


def configuration_reference() -> str:
    """Markdown tables of every section and option: type, default, bounds, description."""
    lines = ["# Configuration reference", "",
             "Generated from `appliance/config/schema.py` and `backends.py` (a test keeps it current).",
             "Unknown keys are errors. `config/appliance.yaml` is a commented example.", ""]
    seen: set[type[BaseModel]] = set()
    queue: list[tuple[str, type[BaseModel]]] = [("(top level)", AppConfig)]
    while queue:
        path, model = queue.pop(0)
        if model in seen:
            continue
        seen.add(model)
        lines += [f"## `{path}` — {model.__name__}", ""]
        if model.__doc__:
            lines += [model.__doc__.strip().splitlines()[0], ""]
        lines += ["| key | type | default | bounds | description |", "|---|---|---|---|---|"]
        for name, field in model.model_fields.items():
            desc = (field.description or "").replace("|", "\\|")
            tname = _type_name(field.annotation).replace("|", "\\|")
            lines.append(f"| `{name}` | `{tname}` | `{_default(field)}` | "
                         f"{_bounds(field)} | {desc} |")
            sub_path = name if path == "(top level)" else f"{path}.{name}"
            for sub in _models_of(field.annotation):
                queue.append((sub_path, sub))
        lines.append("")
    return "\n".join(lines)
