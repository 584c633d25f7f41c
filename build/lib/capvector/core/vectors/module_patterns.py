"""The one pattern syntax for choosing modules or tensors by dotted name (LoRA and LoRA-SP targets, vector
include/exclude filters, the orthogonal regularizer's filters), and its translation to peft.

A pattern matches a dotted name when
- it matches the whole name as a shell glob (`fnmatch`, `*` crossing dots): `backbone.layers.*.attn.q_proj`;
- or it matches the name's trailing dotted components, peft style: `q_proj` matches
  `backbone.layers.0.attn.q_proj`, `attn.*_proj.weight` matches `backbone.layers.0.attn.q_proj.weight`
  (but `proj` does not match `q_proj`);
- `re:` prefixes a Python regular expression that must match the whole name:
  `re:backbone\\.layers\\.[0-3]\\..*`.

Why one syntax: the same list (e.g. `["attn.*_proj", "mlp.fc*"]`) can pick LoRA targets and the matching
`.weight` tensors of a capability vector, and `to_peft_regex` writes it as the single regex peft expects in
`adapter_config.json` (peft full-matches a `target_modules` string against module names), so a peft user
selects exactly the modules we did.
"""

from __future__ import annotations

import fnmatch
import re
from collections.abc import Iterable, Sequence
from functools import lru_cache

REGEX_PREFIX = "re:"
_GLOBAL_FLAGS = re.compile(r"\(\?([aiLmsux]+)\)")


class PatternError(ValueError):
    """A pattern that is malformed, matches nothing, or a selection that is empty."""


def _glob_regex(glob: str) -> str:
    """A regex (no anchors) full-matching what `fnmatch.fnmatchcase(name, glob)` matches."""
    if "[" in glob:  # character classes: reuse fnmatch's exact translation (anchored with \\Z, harmless)
        return fnmatch.translate(glob)
    return "".join(".*" if c == "*" else "." if c == "?" else re.escape(c) for c in re.sub(r"\*+", "*", glob))


def _scoped(regex: str) -> str:
    """Leading global inline flags `(?i)` become scoped `(?i:...)`, so the regex can sit inside another."""
    m = _GLOBAL_FLAGS.match(regex)
    return f"(?{m.group(1)}:{regex[m.end() :]})" if m else regex


@lru_cache(maxsize=4096)
def pattern_regex(pattern: str) -> str:
    """One pattern as a regex that full-matches exactly the names the pattern matches."""
    if pattern.startswith(REGEX_PREFIX):
        body = f"(?:{_scoped(pattern[len(REGEX_PREFIX) :])})"
    else:  # no top-level `|` in a translated glob, so it needs no group of its own
        body = r"(?:.*\.)?" + _glob_regex(pattern)
    try:
        re.compile(body)
    except re.error as e:
        raise PatternError(f"bad pattern {pattern!r}: {e}") from None
    return body


@lru_cache(maxsize=4096)
def _compiled(pattern: str) -> re.Pattern:
    if pattern.startswith(REGEX_PREFIX):  # the user's regex as written (flags and all)
        try:
            return re.compile(pattern[len(REGEX_PREFIX) :])
        except re.error as e:
            raise PatternError(f"bad pattern {pattern!r}: {e}") from None
    return re.compile(pattern_regex(pattern))


def matches(name: str, pattern: str) -> bool:
    """Whether `pattern` matches the dotted `name` (see the module docstring)."""
    return _compiled(pattern).fullmatch(name) is not None


def matches_any(name: str, patterns: Iterable[str]) -> bool:
    return any(matches(name, p) for p in patterns)


def dead_patterns(names: Iterable[str], patterns: Iterable[str]) -> list[str]:
    """The patterns that match none of `names` (almost always a typo)."""
    names = list(names)
    return [p for p in patterns if not any(matches(n, p) for n in names)]


def describe(patterns: Sequence[str], k: int = 5) -> str:
    shown = ", ".join(repr(p) for p in patterns[:k])
    return shown + (f" (+{len(patterns) - k} more)" if len(patterns) > k else "")


def select(
    names: Iterable[str],
    include: Sequence[str] | None = None,
    exclude: Sequence[str] | None = None,
    what: str = "name",
) -> list[str]:
    """Names matched by some include pattern (all, if none) and no exclude pattern, in their order.

    A pattern that matches none of `names`, or an empty selection, is a `PatternError` naming it;
    `what` names the kind of thing in the message ("tensor", "nn.Linear module").
    """
    names = list(names)
    for label, patterns in (("include", include), ("exclude", exclude)):
        dead = dead_patterns(names, patterns or ())
        if dead:
            raise PatternError(f"{label} pattern(s) match no {what}: {describe(dead)}")
    chosen = [
        n for n in names if (not include or matches_any(n, include)) and not matches_any(n, exclude or ())
    ]
    if not chosen:
        raise PatternError(f"the filter (include={include}, exclude={exclude}) selects no {what}")
    return chosen


def to_peft_regex(patterns: Sequence[str]) -> str:
    """One regex string that, full-matched (peft's rule for a string `target_modules`), matches exactly the
    names some pattern in `patterns` matches. (Back-references inside `re:` patterns are not supported.)"""
    if not patterns:
        raise PatternError("no patterns to translate")
    if len(patterns) == 1 and patterns[0].startswith(REGEX_PREFIX):  # as given: round trips stay the same
        regex = _scoped(patterns[0][len(REGEX_PREFIX) :])
    else:
        regex = "|".join(pattern_regex(p) for p in patterns)
    try:
        re.compile(regex)
    except re.error as e:
        raise PatternError(f"patterns {list(patterns)} do not combine into one regex: {e}") from None
    return regex


def exact_regex(names: Iterable[str]) -> str:
    """A regex full-matching exactly `names` (for a selection no shorter pattern list describes)."""
    return "|".join(re.escape(n) for n in names)


def from_peft(target_modules: str | Iterable[str]) -> list[str]:
    """peft's `target_modules` as patterns here: a string is a full-match regex (`re:`); a list of plain
    names keeps peft's meaning (exact name or trailing components), which is this syntax's too."""
    if isinstance(target_modules, str):
        return [REGEX_PREFIX + target_modules]
    return list(target_modules)
