"""Dotted `--set key.path=value` overrides applied to a preset before validation.

Keys are checked against the pydantic model's fields (not only against the preset file), so a
typo fails with the full key path and a suggestion instead of being silently ignored.
"""

from __future__ import annotations

import difflib
import types
import typing
import warnings
from typing import Any

import yaml
from pydantic import BaseModel


class ConfigKeyError(ValueError):
    """An override names a key the configuration does not have."""


def _model_in(annotation: Any) -> type[BaseModel] | None:
    """The pydantic model inside an annotation such as `Model`, `Model | None`, `Annotated[Model, ...]`."""
    if isinstance(annotation, type) and issubclass(annotation, BaseModel):
        return annotation
    origin = typing.get_origin(annotation)
    if origin is typing.Annotated:
        return _model_in(typing.get_args(annotation)[0])
    if origin in (typing.Union, types.UnionType):
        for arg in typing.get_args(annotation):
            found = _model_in(arg)
            if found is not None:
                return found
    return None


def _concrete(model: type[BaseModel], node: dict[str, Any]) -> type[BaseModel]:
    """A polymorphic config (a policy's) is checked against the class its data's `type` names."""
    class_for = getattr(model, "class_for", None)
    return class_for(node) if class_for is not None else model


def _check_key(model: type[BaseModel] | None, path: list[str], depth: int) -> None:
    full_key = ".".join(path)
    if model is None:
        prefix = ".".join(path[:depth])
        raise ConfigKeyError(f"unknown config key {full_key!r}: {prefix!r} has no sub-keys")
    fields = model.model_fields
    part = path[depth]
    renamed = getattr(model, "renamed", {})  # old key -> what it became, declared on the model
    if part in renamed:
        raise ConfigKeyError(f"config key {full_key!r} was renamed: {renamed[part]}")
    if part not in fields:
        hint = difflib.get_close_matches(part, list(fields), n=1)
        suggestion = f" (did you mean {'.'.join(path[:depth] + hint)!r}?)" if hint else ""
        known = ", ".join(sorted(fields))
        raise ConfigKeyError(f"unknown config key {full_key!r}{suggestion}; known here: {known}")


def parse_override(text: str) -> tuple[list[str], Any]:
    """`a.b=3` -> (['a', 'b'], 3); the value is parsed as YAML so numbers, lists and bools work."""
    if "=" not in text:
        raise ConfigKeyError(f"override {text!r} must look like key.path=value")
    key, raw = text.split("=", 1)
    key = key.strip()
    if not key or any(not part for part in key.split(".")):
        raise ConfigKeyError(f"override {text!r} has an empty key segment")
    try:
        value = yaml.safe_load(raw) if raw.strip() else ""
    except yaml.YAMLError as e:  # a tag such as !!python/object, an unclosed bracket
        problem = " ".join(str(getattr(e, "problem", None) or e).split())
        raise ValueError(f"override {text!r}: the value is not valid YAML: {problem}") from None
    return key.split("."), value


def apply_overrides(data: dict[str, Any], overrides: list[str], model: type[BaseModel]) -> dict[str, Any]:
    """Return a copy of `data` with every override set, after checking its key path on `model`.

    `...type=` overrides (a polymorphic config's class, e.g. `policy.type=flow`) are applied first, in
    their given order, and every other key after them, so a key is always checked against the type the
    config ends up with: `policy.integration_steps=5 policy.type=flow` means what the other order means.
    A model's `one_of` fields are alternatives: `orthogonal.lambda_relative=0.1` clears lambda_absolute.
    """
    result: dict[str, Any] = _deep_copy(data)
    parsed = [parse_override(text) for text in overrides]
    parsed = [o for o in parsed if o[0][-1] == "type"] + [o for o in parsed if o[0][-1] != "type"]
    for path, value in parsed:
        node, current = result, model
        for depth, part in enumerate(path):
            if current is not None:
                current = _concrete(current, node)
            _check_key(current, path, depth)
            if depth == len(path) - 1:
                break
            field = current.model_fields[part]
            child = node.get(part)
            if not isinstance(child, dict):
                # Start from the field's default, so `lora_sp.bank_size=16` keeps the other defaults.
                default = field.get_default(call_default_factory=True)
                child = default.model_dump() if isinstance(default, BaseModel) else {}
                node[part] = child
            node, current = child, _model_in(field.annotation)
        node[path[-1]] = value
        one_of = getattr(current, "one_of", ())  # fields of which one is set: setting one clears the rest
        if path[-1] in one_of:
            node.update({sibling: None for sibling in one_of if sibling != path[-1]})
        if path[-1] == "type" and current is not None:
            _drop_fields_of_other_type(node, _concrete(current, node), ".".join(path[:-1]))
    return result


def _drop_fields_of_other_type(node: dict[str, Any], model: type[BaseModel], where: str) -> None:
    """A new `type` takes the settings it shares with the old one; the rest no longer apply (said once)."""
    dropped = sorted(k for k in node if k not in model.model_fields)
    for key in dropped:
        del node[key]
    if dropped:
        warnings.warn(
            f"{where}.type={node['type']}: {', '.join(dropped)} do not apply to this type and were dropped",
            stacklevel=3,
        )


def _deep_copy(data: dict[str, Any]) -> dict[str, Any]:
    return {k: _deep_copy(v) if isinstance(v, dict) else v for k, v in data.items()}
