"""Evaluation protocols by name, for `--fingerprint`: `test`, `validation` or a fingerprint prefix.

A protocol's fingerprint hashes everything that decides its scores, the goal seeds among them. Its
seeds start at its seed base (episode i runs goal seed_base + i), and the project's two protocols
are told apart by theirs: `test` starts at capvector.core.simulation.demos.EVAL_SEED_BASE, `validation` (model
selection) at VALIDATION_SEED_BASE. The seed base is read from the evaluations' own episodes (the
smallest seed), so it holds for every evaluation document, whatever its sidecar says.

The constants are repeated here, not imported: capvector.core.simulation.demos loads mujoco, and the read-only
commands stay light (tests/test_scores.py checks that the values agree).
"""

from __future__ import annotations

import string
from typing import Any, NamedTuple

TEST_SEED_BASE = 100_000  # capvector.core.simulation.demos.EVAL_SEED_BASE
VALIDATION_SEED_BASE = 50_000  # capvector.core.simulation.demos.VALIDATION_SEED_BASE
NAMES = {"test": TEST_SEED_BASE, "validation": VALIDATION_SEED_BASE}
MIN_PREFIX = 6  # as for artifact ids
SHOWN = 12  # characters of a fingerprint in tables and messages


class Protocol(NamedTuple):
    fingerprint: str
    seed_base: int | None  # None: no episode recorded
    evaluations: int

    @property
    def name(self) -> str | None:
        return next((n for n, base in NAMES.items() if base == self.seed_base), None)

    def describe(self) -> str:
        """`1a2b3c4d5e6f test (goal seeds from 100000, 3 evaluations)`."""
        kind = self.name or "unnamed"
        seeds = "no episodes" if self.seed_base is None else f"goal seeds from {self.seed_base}"
        return f"{self.fingerprint[:SHOWN]} {kind} ({seeds}, {self.evaluations} evaluations)"


def protocols(api: Any, fingerprints: set[str] | list[str]) -> list[Protocol]:
    """The protocols of these fingerprints, test first, then validation, then the others."""
    fps = sorted(set(fingerprints))
    if not fps:
        return []
    _, rows = api.query_rows(
        "SELECT fingerprint, min(seed), count(DISTINCT evaluation_id) FROM eval_episodes "
        "WHERE fingerprint IN (SELECT unnest(?::VARCHAR[])) GROUP BY fingerprint",
        [fps],
    )
    found = {fp: Protocol(fp, int(base), int(n)) for fp, base, n in rows}
    out = [found.get(fp, Protocol(fp, None, 0)) for fp in fps]
    order = list(NAMES)
    return sorted(out, key=lambda p: (order.index(p.name) if p.name else len(order), p.fingerprint))


def listing(choices: list[Protocol]) -> str:
    return "; ".join(p.describe() for p in choices)


def resolve(choice: str, choices: list[Protocol], what: str) -> str:
    """The one fingerprint among `choices` that `choice` names: `test`, `validation`, a whole
    fingerprint or a unique prefix of at least MIN_PREFIX hex characters. `what`: whose protocols
    these are, for the error, which lists them."""
    key = choice.strip().lower()
    hint = (
        f"give --fingerprint test, validation or {MIN_PREFIX}+ characters of one of {what}'s "
        f"{len(choices)} evaluation protocols: {listing(choices) or 'none (nothing evaluated)'}"
    )
    exact = [p for p in choices if p.fingerprint == choice.strip()]
    if exact:
        return exact[0].fingerprint
    if key in NAMES:
        matches = [p for p in choices if p.seed_base == NAMES[key]]
        if len(matches) == 1:
            return matches[0].fingerprint
        found = "none" if not matches else f"{len(matches)} (other tasks or settings)"
        raise ValueError(
            f"--fingerprint {key}: {found} of {what}'s protocols start at the {key} goal seeds "
            f"({NAMES[key]}); {hint}"
        )
    if len(key) < MIN_PREFIX or any(c not in string.hexdigits for c in key):
        raise ValueError(f"--fingerprint {choice!r} is not a protocol name or fingerprint prefix; {hint}")
    matches = [p for p in choices if p.fingerprint.lower().startswith(key)]
    if len(matches) == 1:
        return matches[0].fingerprint
    found = "no" if not matches else f"{len(matches)}"
    raise ValueError(f"--fingerprint {choice!r} matches {found} evaluation protocols of {what}; {hint}")
