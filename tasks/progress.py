"""Progress lines for long steps that run inside Prefect tasks (possibly several at once).

Rich live bars from concurrent threads overwrite each other, so steps print a short line at
every 10% instead; the trainer's own bar is used when one step runs alone.
"""

from __future__ import annotations

import os
import sys
from collections.abc import Callable


def quiet() -> bool:
    return os.environ.get("CAPVECTOR_QUIET", "") not in ("", "0")


def progress_printer(step: str, unit: str) -> Callable[[int, int], None] | None:
    if quiet():
        return None
    last = {"decile": -1}

    def report(done: int, total: int) -> None:
        decile = (10 * done) // max(total, 1)
        if decile != last["decile"]:
            last["decile"] = decile
            print(f"[{step}] {done}/{total} {unit}", file=sys.stderr, flush=True)

    return report
