"""Code and library versions recorded with every artifact, so a score can be traced to what produced it."""

import functools
import subprocess
from collections.abc import Iterable
from importlib import metadata
from pathlib import Path

REPO_ROOT = Path(__file__).resolve().parent.parent


@functools.cache
def code_version() -> str:
    """`git describe --always --dirty` of this checkout, else the installed capvector version.

    Cached: a registration must not pay a subprocess each time, and the code cannot change under
    a running process.
    """
    if (REPO_ROOT / ".git").exists():
        try:
            out = subprocess.run(
                ["git", "-C", str(REPO_ROOT), "describe", "--always", "--dirty", "--tags"],
                capture_output=True,
                text=True,
                timeout=10,
                check=True,
            )
            return f"git:{out.stdout.strip()}"
        except (OSError, subprocess.SubprocessError):
            pass
    try:
        return f"capvector=={metadata.version('capvector')}"
    except metadata.PackageNotFoundError:
        return "unknown"


def installed_versions(distributions: Iterable[str]) -> dict[str, str | None]:
    """Installed version of each named distribution (None when absent), for `library_versions`."""
    out: dict[str, str | None] = {}
    for name in distributions:
        try:
            out[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            out[name] = None
    return out
