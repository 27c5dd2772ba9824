"""The base of every configuration model: unknown keys, NaN and infinity refused; integers and booleans typed.

pydantic's lax mode reads ``steps: true`` as 1, ``bit_depth: 12.0`` as 12 and ``shot_noise: 1`` as true, and
accepts ``.inf`` and ``.nan`` for any float. A YAML file is typed already, so the configuration takes what it
says: a whole number where an integer is wanted, ``true``/``false`` where a boolean is, and finite numbers.
"""

from __future__ import annotations

import numbers
import types
from typing import Annotated, Any, Union, get_args, get_origin

from pydantic import BaseModel, ConfigDict, model_validator
from pydantic_core import PydanticCustomError


def _is_bool(value: Any) -> bool:
    return isinstance(value, bool) or type(value).__name__ == "bool_"  # numpy's too


def type_problem(value: Any, annotation: Any) -> tuple[tuple[int, ...], str] | None:
    """Where and why ``value`` (from YAML) does not fit the integer/boolean parts of ``annotation``.

    Only ``int``, ``bool``, ``float`` (no booleans), optionals, unions and tuples of them are looked at;
    everything else is left to pydantic.

    Returns
    -------
    ((int, ...), str) or None
        The item indices down to the offending value (empty for the value itself) and the rule; None when
        it fits.
    """
    origin = get_origin(annotation)
    if annotation is bool:
        return None if _is_bool(value) else ((), "must be true or false")
    if annotation is int:
        if _is_bool(value) or not isinstance(value, numbers.Integral):
            return (), "must be a whole number (no fraction, no quotes, not true/false)"
        return None
    if annotation is float:
        return ((), "must be a number, not true/false") if _is_bool(value) else None
    if origin is Annotated:
        return type_problem(value, get_args(annotation)[0])
    if origin is Union or origin is types.UnionType:
        members = [a for a in get_args(annotation) if a is not type(None)]
        if value is None:
            return None
        problems = [type_problem(value, a) for a in members]
        return None if any(p is None for p in problems) else problems[0]
    if origin is tuple and isinstance(value, list | tuple):
        args = get_args(annotation)
        if len(args) == 2 and args[1] is Ellipsis:
            pairs = [(v, args[0]) for v in value]
        elif len(args) == len(value):
            pairs = list(zip(value, args, strict=True))
        else:
            return None  # pydantic says the length is wrong
        for i, (v, a) in enumerate(pairs):
            problem = type_problem(v, a)
            if problem is not None:
                return (i, *problem[0]), problem[1]
    return None


STRICT_TYPE = "strict_type"
"""The error type of a wrongly typed integer or boolean; its context holds the ``field``, the ``items`` down to
the value (list indices) and the ``rule``."""


class StrictModel(BaseModel):
    """Unknown keys refused, frozen, finite floats, strictly typed integers and booleans."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)

    @model_validator(mode="before")
    @classmethod
    def _typed(cls, data: Any) -> Any:
        # a model-level check: a field-level "before" validator is not allowed on a union's discriminator
        if isinstance(data, dict):
            for name, field in cls.model_fields.items():
                key = field.alias or name
                if key in data:
                    problem = type_problem(data[key], field.annotation)
                    if problem is not None:
                        items, rule = problem
                        where = ".".join([key, *map(str, items)])
                        raise PydanticCustomError(STRICT_TYPE, "{where}: {rule}",
                                                  {"field": key, "items": list(items), "rule": rule, "where": where})
        return data
