"""The one pattern syntax: globs on the whole name or its trailing components, `re:`, dead patterns, and
its peft regex (equivalent to `matches` over real module names)."""

import fnmatch
import random
import re

import pytest
import torch

from capvector.core.policies.base import build_policy
from capvector.core.vectors.module_patterns import (
    PatternError,
    dead_patterns,
    from_peft,
    matches,
    select,
    to_peft_regex,
)

NAME = "backbone.layers.0.attn.q_proj"


@pytest.mark.parametrize(
    "pattern, hit",
    [
        ("backbone.layers.*.attn.q_proj", True),  # whole-name glob
        ("*q_proj", True),
        ("q_proj", True),  # trailing components, peft style
        ("attn.q_proj", True),
        ("attn.*_proj", True),
        ("layers.?.attn.[pq]_proj", True),
        ("proj", False),  # a component must match whole: `proj` is not `q_proj`
        ("_proj", False),
        ("attn", False),
        ("backbone", False),
        ("layers.1.*", False),
        (r"re:backbone\.layers\.[0-3]\..*", True),
        (r"re:layers\..*", False),  # a regex matches the whole name, not a suffix
        ("re:(?i)BACKBONE.*", True),
    ],
)
def test_matches(pattern, hit):
    assert matches(NAME, pattern) is hit
    assert matches(NAME + ".weight", "attn.*_proj.weight") and not matches(
        NAME + ".bias", "attn.*_proj.weight"
    )


def test_select_and_dead_patterns():
    names = ["backbone.layers.0.attn.q_proj.weight", "backbone.layers.0.attn.q_proj.bias", "head.proj.weight"]
    assert select(names, include=["weight"]) == [names[0], names[2]]
    assert select(names, exclude=["attn.*"]) == [names[2]]
    assert select(names, include=["backbone.*"], exclude=["bias"]) == [names[0]]
    with pytest.raises(PatternError, match="include pattern\\(s\\) match no tensor: 'nothing', 're:x'"):
        select(names, include=["weight", "nothing", "re:x"], what="tensor")
    with pytest.raises(PatternError, match="exclude pattern\\(s\\) match no name: 'gone'"):
        select(names, exclude=["gone"])
    with pytest.raises(PatternError, match="selects no"):
        select(names, include=["weight"], exclude=["*"])
    with pytest.raises(PatternError, match="bad pattern 're:\\('"):
        select(names, include=["re:("])
    assert dead_patterns(names, ["bias", "fc1"]) == ["fc1"]


def _module_names():
    torch.manual_seed(0)
    policy = build_policy({"type": "l1_chunk", "d_model": 16, "n_layers": 3, "n_heads": 2}, device="cpu")
    return [n for n, _ in policy.named_modules()]


@pytest.mark.parametrize(
    "patterns",
    [
        ["attn.*_proj", "mlp.fc*", "action_head.*"],
        ["q_proj", "v_proj"],
        ["backbone.layers.[01].attn.?_proj", "proj"],
        [r"re:backbone\.layers\.(0|2)\.mlp\.fc1", "fc2"],
        ["re:(?i).*Q_PROJ", "state.proj.*"],
        ["*"],
    ],
)
def test_peft_regex_equals_matches_over_module_names(patterns):
    names = _module_names()
    regex = re.compile(to_peft_regex(patterns))
    want = [n for n in names if any(matches(n, p) for p in patterns)]
    assert want and [n for n in names if regex.fullmatch(n)] == want
    assert [n for n in names if any(matches(n, p) for p in from_peft(to_peft_regex(patterns)))] == want
    assert to_peft_regex(from_peft(to_peft_regex(patterns))) == to_peft_regex(patterns)  # saved, read, saved


def test_globs_agree_with_fnmatch_on_random_names():
    """Whole-name or trailing-component glob matching, exactly as fnmatch defines globs."""
    rng = random.Random(0)
    parts = ["a", "b", "ab", "q_proj", "0", "1", "x.y"]
    names = {".".join(rng.choice(parts) for _ in range(rng.randint(1, 4))) for _ in range(300)}
    globs = ["a", "*b", "a.*", "?", "q_*", "*.0.*", "[ab]", "[!a]*", "b.a?", "**", "x.y"]
    for p in globs:
        for n in names:
            want = fnmatch.fnmatchcase(n, p) or fnmatch.fnmatchcase(n, "*." + p)
            assert matches(n, p) is want, (p, n)
            assert (re.fullmatch(to_peft_regex([p]), n) is not None) is want, (p, n)


def test_peft_list_targets_keep_their_meaning():
    assert from_peft(["q_proj", "v_proj"]) == ["q_proj", "v_proj"]
    names = ["m.q_proj", "m.xq_proj", "q_proj"]  # peft: exact name or `.q_proj` suffix
    assert [n for n in names if matches(n, "q_proj")] == ["m.q_proj", "q_proj"]
