"""A step's code hash (`step_code`), part of every cache key: a hash of the source a step actually runs.

Not the `source_revision` of a sidecar (capvector.artifacts.provenance: `git describe` of the checkout, which
says where an artifact came from but decides no cache hit): two names for two different things.

Prefect's default cache policy hashes only the task's own source; a change in a helper it calls
(a loss, a data loader) would silently reuse stale results. Hashing every file of the project
would be safe but would throw away all cached demos whenever, say, the report code changes. So a
step's version hashes the transitive closure of the project modules its module imports (found by
parsing `import` statements), and nothing else.
"""

from __future__ import annotations

import functools
import hashlib
import importlib.util
import re
from pathlib import Path

# The packages whose code decides an artifact's content (the store and catalogue only keep it).
PROJECT_PACKAGES = ("capvector.core", "capvector.stats", "capvector.tasks")


def is_project_module(name: str) -> bool:
    """Whether a dotted name lies in one of the packages whose code decides an artifact's content."""
    return any(name == package or name.startswith(f"{package}.") for package in PROJECT_PACKAGES)


@functools.cache
def _source_path(module: str) -> Path | None:
    """The module's .py file; None for names that are not modules (`from pkg.mod import Class`)."""
    try:
        spec = importlib.util.find_spec(module)
    except (ImportError, AttributeError, ValueError):
        return None
    return Path(spec.origin) if spec and spec.origin and spec.origin.endswith(".py") else None


# An import statement: `from a.b import (c as d, e)` (parenthesized, or continued with backslashes) or
# `import a.b as c, d`, at any indentation (imports inside functions count). Scanning the text is ~20×
# faster than parsing it (a warm run hashes ~40 files). tests/test_step_code.py checks that it misses
# nothing `ast` finds in any file and adds no project module to a hashed one (text in strings could).
IMPORT_STATEMENT = re.compile(
    r"^[ \t]*(?:from[ \t]+([\w.]+)[ \t]+import[ \t]+(\([^)]*\)|(?:\\\n|[^\n])*)|import[ \t]+([^\n]+))",
    re.MULTILINE,
)


def imported_names(source: str) -> list[str]:
    """Every absolute module name an import statement in `source` names, and `module.name` for each
    name a `from module import name` takes (it may be a module itself)."""
    names = []
    for match in IMPORT_STATEMENT.finditer(source):
        module, taken, plain = match.groups()
        if module is not None:
            if module.startswith("."):
                continue
            aliases = re.sub(r"#[^\n]*", "", taken).strip().strip("()").replace("\\\n", " ").split(",")
            names.append(module)
            names += [f"{module}.{alias.split(' as ')[0].strip()}" for alias in aliases if alias.strip()]
        else:
            plain = re.sub(r"#.*", "", plain)
            names += [alias.split(" as ")[0].strip() for alias in plain.split(",") if alias.strip()]
    return names


@functools.cache
def _imports(path: Path, module: str) -> frozenset[str]:
    """Project modules imported by a file (absolute imports, and `from package import module`); each
    file is read once per process, however many step modules' closures include it."""
    found = {
        name
        for name in imported_names(path.read_text())
        if is_project_module(name) and _source_path(name) is not None
    }
    return frozenset(found - {module})


@functools.cache
def module_closure(module: str) -> tuple[str, ...]:
    """`module` and every project module it imports, directly or not (sorted)."""
    seen, todo = set(), [module]
    while todo:
        name = todo.pop()
        if name in seen:
            continue
        seen.add(name)
        path = _source_path(name)
        if path is not None:
            todo.extend(_imports(path, name) - seen)
    return tuple(sorted(seen))


@functools.cache
def step_code(module: str) -> str:
    """sha256 (16 hex chars) over the names and bytes of the sources in `module`'s closure."""
    digest = hashlib.sha256()
    for name in module_closure(module):
        path = _source_path(name)
        if path is not None:
            digest.update(f"{name}\0".encode() + path.read_bytes() + b"\0")
    return digest.hexdigest()[:16]
