"""The house rules of the layout: one installed name, folders of capabilities, imports flowing downward."""

import ast
import tomllib
from pathlib import Path

import pytest

from capvector.tasks.runtime.step_code import imported_names

REPO = Path(__file__).resolve().parent.parent
PYPROJECT = tomllib.loads((REPO / "pyproject.toml").read_text())
FOLDERS = PYPROJECT["tool"]["setuptools"]["package-dir"]
# What each installed part may import of the project (besides itself): the layers of docs/architecture.md.
MAY_IMPORT = {
    "capvector.core": {"capvector.durable"},
    "capvector.stats": set(),
    "capvector.artifacts": {"capvector.durable"},
    "capvector.tasks": {
        "capvector.durable",
        "capvector.parent_death",
        "capvector.core",
        "capvector.stats",
        "capvector.artifacts",
    },
}
MAX_MODULES_PER_FOLDER = 15


def _package_folders() -> dict[str, Path]:
    """Every package a wheel must hold, by its installed name, found from the folders themselves."""
    found = {"capvector": REPO / "capvector"}
    for name, folder in FOLDERS.items():
        if name == "capvector":
            continue
        for init in (REPO / folder).rglob("__init__.py"):
            rel = init.parent.relative_to(REPO / folder)
            found[".".join([name, *rel.parts])] = init.parent
    return found


def test_the_wheel_lists_every_package_and_nothing_else() -> None:
    """A subpackage missing from pyproject's list would be absent from an installed capvector."""
    assert set(PYPROJECT["tool"]["setuptools"]["packages"]) == set(_package_folders())


def test_installed_the_project_claims_one_top_level_name() -> None:
    assert {name.split(".")[0] for name in PYPROJECT["tool"]["setuptools"]["packages"]} == {"capvector"}
    assert PYPROJECT["project"]["scripts"]["capvector"].startswith("capvector.")


@pytest.mark.parametrize("package", sorted(_package_folders()))
def test_no_folder_holds_more_than_15_modules(package: str) -> None:
    modules = sorted((_package_folders()[package]).glob("*.py"))
    assert len(modules) <= MAX_MODULES_PER_FOLDER, [m.name for m in modules]


@pytest.mark.parametrize("package", sorted(MAY_IMPORT))
def test_imports_flow_downward(package: str) -> None:
    allowed = MAY_IMPORT[package] | {package}
    for path in sorted((REPO / FOLDERS[package]).rglob("*.py")):
        for name in imported_names(path.read_text()):
            if name.startswith("capvector"):
                assert any(name == a or name.startswith(f"{a}.") for a in allowed), (path, name)


def test_no_product_function_is_longer_than_80_lines() -> None:
    long = []
    for folder in FOLDERS.values():
        for path in sorted((REPO / folder).rglob("*.py")):
            for node in ast.walk(ast.parse(path.read_text())):
                if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
                    lines = node.end_lineno - node.lineno + 1
                    if lines > 80:
                        long.append(f"{path.relative_to(REPO)}:{node.lineno} {node.name} ({lines} lines)")
    assert not long, long


def test_no_function_of_the_store_takes_more_than_8_parameters() -> None:
    """Artifact metadata travels as one value (records.ArtifactMeta), not threaded positionally."""
    wide = []
    for path in sorted((REPO / "artifacts").rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
                a = node.args
                names = [x.arg for x in a.posonlyargs + a.args + a.kwonlyargs]
                count = len(names) - (names[:1] in (["self"], ["cls"])) + bool(a.vararg) + bool(a.kwarg)
                if count > 8:
                    wide.append(f"{path.name}:{node.lineno} {node.name} ({count})")
    assert not wide, wide
