"""capvector: capability vectors for vision-language-action policies.

Installed, every part of the project lives under this one name: `capvector.core` (the library: Meta-World,
policies, training, evaluation, vector arithmetic), `capvector.stats` (a study's statistics),
`capvector.artifacts` (the store and the DuckDB catalogue), `capvector.tasks` (cached steps) and
`capvector.flows` (flows and the `capvector` command line). Importing this package imports none of them.

The library API for your own training loop (docs/guide/own-loop.md) is importable from here, each name
loaded on first use: `extract`, `merge`, `mean`, `stats` (streaming vector arithmetic on safetensors
checkpoints), `OrthogonalRegularizer` (λ·Σ|γ ⊙ (θ − θ_meta)| as an `nn.Module`), `apply_lora` and
`LoraConfig` (LoRA through peft), `apply_lora_sp` and `LoraSPConfig` (rank-adaptive LoRA-SP),
`load_policy` and `save_policy` (this project's policies).

In a checkout the design keeps those folders at the repository's top level (`capvector_core/`, `flows/`,
…); a wheel puts them under `capvector/` (pyproject's package-dir). The finder below maps the five names
onto the folders beside this package, so that any checkout (a git worktree, a CI clone) imports its own
code rather than wherever an editable install points.
"""

from __future__ import annotations

import importlib
import importlib.util
import sys
from pathlib import Path

_FOLDERS = {
    "capvector.core": "capvector_core",
    "capvector.stats": "capvector_stats",
    "capvector.artifacts": "artifacts",
    "capvector.tasks": "tasks",
    "capvector.flows": "flows",
}
_CHECKOUT = Path(__file__).resolve().parent.parent


class _CheckoutFinder:
    """Finds `capvector.<part>` in the checkout's top-level folder; deeper modules follow its __path__."""

    @staticmethod
    def find_spec(fullname, path=None, target=None):
        folder = _FOLDERS.get(fullname)
        if folder is None:
            return None
        location = _CHECKOUT / folder
        return importlib.util.spec_from_file_location(
            fullname, location / "__init__.py", submodule_search_locations=[str(location)]
        )


_PUBLIC = {
    "extract": "capvector.core.vectors.vector_ops",
    "merge": "capvector.core.vectors.vector_ops",
    "mean": "capvector.core.vectors.vector_ops",
    "stats": "capvector.core.vectors.vector_ops",
    "OrthogonalRegularizer": "capvector.core.training.orthogonal",
    "apply_lora": "capvector.core.adapters.lora",
    "LoraConfig": "capvector.core.adapters.lora",
    "apply_lora_sp": "capvector.core.adapters.lora_sp",
    "LoraSPConfig": "capvector.core.adapters.lora_sp",
    "load_policy": "capvector.core.policies.base",
    "save_policy": "capvector.core.policies.base",
}
__all__ = sorted(_PUBLIC)


def __getattr__(name: str):
    """The public names, imported when first used (so `import capvector` loads no torch)."""
    if name not in _PUBLIC:
        raise AttributeError(f"module 'capvector' has no attribute {name!r}")
    value = getattr(importlib.import_module(_PUBLIC[name]), name)
    globals()[name] = value
    return value


if not (Path(__file__).parent / "core").is_dir() and (_CHECKOUT / "capvector_core").is_dir():
    sys.meta_path.insert(0, _CheckoutFinder())
