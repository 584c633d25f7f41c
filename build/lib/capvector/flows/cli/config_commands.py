"""`capvector config show`: a preset resolved with its `--set` overrides, each field with its description.

The pydantic models are the one declaration of every option; this prints them as a user edits them
(dotted paths, the values `--set` takes) with the description the model carries, so the meaning of a
preset's field is one command away.
"""

from __future__ import annotations

import json
from collections.abc import Iterator
from typing import Annotated, Any

import typer
from pydantic import BaseModel


def describe(model: BaseModel, prefix: str = "") -> Iterator[tuple[str, Any, str]]:
    """(dotted path, value, description) of every leaf field of `model`, nested models expanded."""
    fields = type(model).model_fields
    for name, info in fields.items():
        value = getattr(model, name)
        path = f"{prefix}{name}"
        if isinstance(value, BaseModel):
            yield from describe(value, f"{path}.")
            continue
        text = info.description or _docstring_line(type(model), name)
        if isinstance(value, list):
            value = [v.model_dump(mode="json") if isinstance(v, BaseModel) else v for v in value]
        yield path, value, text


def _docstring_line(cls: type, field: str) -> str:
    """A field documented in its class's `Args:` block (LeRobot's style) when it has no description:
    its line and the more-indented lines that continue it, joined."""
    lines = (cls.__doc__ or "").splitlines()
    marker = f"{field}:"
    for i, line in enumerate(lines):
        stripped = line.strip()
        if not stripped.startswith(marker):
            continue
        indent = len(line) - len(line.lstrip())
        parts = [stripped[len(marker) :].strip()]
        for more in lines[i + 1 :]:
            if not more.strip() or len(more) - len(more.lstrip()) <= indent:
                break
            parts.append(more.strip())
        return " ".join(parts)
    return ""


def show(
    preset: Annotated[str, typer.Option(help="a preset name or a YAML path")] = "quick",
    overrides: Annotated[
        list[str] | None, typer.Option("--set", help="override a config key: a.b=value")
    ] = None,
    as_json: Annotated[bool, typer.Option("--json", help="print machine-readable JSON")] = False,
) -> None:
    """The resolved config of a preset (pipeline, study or calibration), every field with its description."""
    import yaml

    from capvector.flows.calibration.config import load_calibration
    from capvector.flows.recipe.config import load_config, preset_kind, preset_path
    from capvector.flows.study.config import load_study

    kind = preset_kind(yaml.safe_load(preset_path(preset).read_text()) or {})
    loaders = {"pipeline": load_config, "study": load_study, "calibration": load_calibration}
    config = loaders[kind](preset, overrides)
    rows = list(describe(config))
    if as_json:
        typer.echo(json.dumps([{"field": p, "value": v, "description": d} for p, v, d in rows], indent=1))
        return
    typer.echo(f"# {kind} preset {preset} ({len(rows)} fields)")
    width = max(len(p) for p, _, _ in rows)
    for path, value, text in rows:
        shown = json.dumps(value, ensure_ascii=False)
        typer.echo(f"{path:<{width}} = {shown}" + (f"    # {text}" if text else ""))


config_app = typer.Typer(no_args_is_help=True, help="Resolved configurations and what each field means.")
config_app.command("show")(show)
