"""The import scan behind every step's code hash finds exactly what Python's parser finds."""

import ast
from pathlib import Path

import pytest

from capvector.tasks.runtime.step_code import (
    PROJECT_PACKAGES,
    imported_names,
    is_project_module,
    module_closure,
)

REPO = Path(__file__).resolve().parent.parent
PACKAGES = (
    "capvector",
    "capvector_core",
    "capvector_stats",
    "tasks",
    "flows",
    "artifacts",
    "scripts",
    "benchmarks",
    "tests",
)


def parsed_names(source: str) -> set[str]:
    names = set()
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Import):
            names |= {alias.name for alias in node.names}
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            names |= {node.module} | {f"{node.module}.{alias.name}" for alias in node.names}
    return names


@pytest.mark.parametrize("package", PACKAGES)
def test_the_scan_misses_no_import_in_any_project_file(package: str) -> None:
    """Missing one would leave a step's hash blind to a module it runs: a stale cache."""
    files = sorted((REPO / package).rglob("*.py"))
    assert files
    for path in files:
        source = path.read_text()
        assert parsed_names(source) <= set(imported_names(source)), path


@pytest.mark.parametrize("package", PROJECT_PACKAGES)
def test_the_scan_adds_no_project_module_to_a_hashed_file(package: str) -> None:
    """Text that only looks like an import (a docstring's example) may not widen a step's closure."""
    folders = {"capvector.core": "capvector_core", "capvector.stats": "capvector_stats"}
    folder = REPO / folders.get(package, "tasks")
    files = sorted(folder.rglob("*.py"))
    assert files, folder
    for path in files:
        source = path.read_text()
        project = {n for n in imported_names(source) if is_project_module(n)}
        assert project == {n for n in parsed_names(source) if is_project_module(n)}, path


def test_every_import_form() -> None:
    source = """
import a.b as c, d
from e import (f as g,
    h,  # a comment
)
from i.j import k, \\
    l
def inner():
    from m import n  # noqa: E402
from . import relative
"""
    assert (
        set(imported_names(source))
        == parsed_names(source)
        == {"a.b", "d", "e", "e.f", "e.h", "i.j", "i.j.k", "i.j.l", "m", "m.n"}
    )


def test_a_lazy_import_is_in_the_closure() -> None:
    """capvector.tasks.steps.evaluation imports Prefect's artifacts inside a function; project modules
    imported that way (capvector.tasks.steps.held_out_loss via capvector.core.training.held_out_loss) must
    count too."""
    assert "capvector.core.training.held_out_loss" in module_closure("capvector.tasks.steps.held_out_loss")
    assert "capvector.core.simulation.demos" in module_closure("capvector.tasks.steps.held_out_loss")
