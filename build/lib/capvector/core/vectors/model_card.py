"""What a folder output of `vector_ops` holds besides its weights: the base's other files, and a card.

A merged (or extracted) folder should load wherever its base loaded: LeRobot's and Hugging Face's
`from_pretrained` read `config.json` (and `train_config.json`, processors, tokenizers) beside the weights.
`companion_files` lists those files of an input folder; `render_card` writes the README.md model card
(after mergekit's): the formula, the coefficients, each input by artifact id and sha256, the command that
makes it again and the library versions. The card holds no path and no time, so the same inputs give
the same bytes (hence the same artifact id) wherever they are stored.
"""

from __future__ import annotations

import fnmatch
import os
import platform
from collections.abc import Iterable, Mapping, Sequence
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path

from capvector.core.vectors.safetensors_io import INDEX_NAME, Checkpoint, CheckpointError

CARD_NAME = "README.md"
# Weight files that are not the checkpoint read (another format, another index): carried over, they would
# be loaded in place of the output's weights, or name shards that are not there.
STALE_WEIGHTS = (
    "model-*-of-*.safetensors",
    "*.safetensors.index.json",
    "pytorch_model*.bin",
    "pytorch_model.bin.index.json",
)
CARD_LIBRARIES = ("capvector", "numpy", "safetensors", "huggingface_hub")


def companion_files(folder: str | os.PathLike, weights: Iterable[str] | None = None) -> list[str]:
    """Relative paths (`/`-separated, sorted) of the files of a checkpoint folder that are not its weights:
    every regular file but its weight files (`weights`, relative paths; default: those its `Checkpoint`
    reads), its index, other weight files (`STALE_WEIGHTS`), README.md (the output gets its own card)
    and hidden files (`.git`, `.cache`, ...). A link whose target lies outside the folder is refused,
    naming it (the store refuses it too)."""
    folder = Path(folder)
    if weights is None:
        ckpt = Checkpoint(folder)
        weights = [f.relative_to(folder).as_posix() for f in ckpt.files]
    weights = set(weights)
    root = folder.resolve()
    found = []
    for dirpath, dirnames, filenames in os.walk(folder):
        dirnames[:] = sorted(d for d in dirnames if not d.startswith("."))
        for name in filenames:
            path = Path(dirpath) / name
            rel = path.relative_to(folder).as_posix()
            if name.startswith(".") or rel in (INDEX_NAME, CARD_NAME) or rel in weights:
                continue
            if any(fnmatch.fnmatch(name, p) for p in STALE_WEIGHTS):
                continue
            if not path.resolve().is_relative_to(root):
                raise CheckpointError(
                    f"{path} links outside its folder; it cannot be carried into the output"
                )
            if path.is_file():
                found.append(rel)
    return sorted(found)


def library_versions(names: Sequence[str] = CARD_LIBRARIES) -> dict[str, str]:
    found = {"python": platform.python_version()}
    for name in names:
        try:
            found[name] = version(name)
        except PackageNotFoundError:
            found[name] = "not installed"
    return found


def render_card(
    kind: str,
    formula: str,
    inputs: Sequence[Mapping[str, object]],
    command: str,
    settings: Mapping[str, object],
    carried: Sequence[str],
    versions: Mapping[str, str] | None = None,
) -> str:
    """README.md of an output folder. `inputs`: rows with `role`, `sha256`, and optionally `id` (artifact
    id) and `alpha`; `settings`: options that shaped the output (filters, dtypes, key map)."""
    title = {"merged": "Merged checkpoint", "vector": "Capability vector"}.get(kind, kind)
    lines = [
        "---",
        "library_name: capvector",
        "tags:",
        "- capvector",
        f"- {'merge' if kind == 'merged' else 'capability-vector'}",
        "---",
        "",
        f"# {title}",
        "",
        f"Made with capvector's `vector` arithmetic: `{formula}`.",
        "",
        "## Inputs",
        "",
        "| role | α | artifact id | sha256 of the weights |",
        "|---|---|---|---|",
    ]
    for row in inputs:
        alpha = "" if row.get("alpha") is None else row["alpha"]
        lines.append(f"| {row['role']} | {alpha} | `{row.get('id') or '-'}` | `{row['sha256']}` |")
    lines += [
        "",
        "The sha256 of a single file is the file's; of a sharded folder, the sha256 of the JSON "
        "`{shard: sha256}`. An artifact id is the id of the input in the capvector store "
        "(`capvector artifacts show <id>`).",
        "",
        "## Command",
        "",
        "```",
        command,
        "```",
        "",
    ]
    shown = {k: v for k, v in settings.items() if v not in (None, [], ())}
    if shown:
        lines += ["## Settings", ""] + [f"- `{k}`: `{v}`" for k, v in shown.items()] + [""]
    if carried:
        lines += ["## Files carried over from the base", ""] + [f"- `{f}`" for f in carried] + [""]
    versions = library_versions() if versions is None else versions
    lines += ["## Library versions", ""] + [f"- {k} {v}" for k, v in versions.items()] + [""]
    return "\n".join(lines)
