"""A study of fine-tuning forms (issue 40's rank study): each arm's endpoint with its interval, and how much
a form's success depends on its capacity ("robust to rank").

Variants (`study.variants`, capvector.flows.study.variants) are arms from θ_pt, each one form (`sft_lora`,
`sft_lora_sp`, `sft_adalora`, or full `sft`) at one setting. A form's *spread* is the difference between
its best and its worst variant at the primary endpoint, max − min of their endpoint means, with the
interval of that paired difference (capvector.stats.paired_differences: mean ± t_df·√V̂, paired by seed
and goal). Which two variants are best and worst is read from the same data, so when the variants truly
tie the spread is still above 0 on average: an interval well above 0 says capacity matters for that form,
one that includes 0 says this design saw no dependence on it (not that there is none).
"""

from __future__ import annotations

import pandas as pd
from pydantic import BaseModel

from capvector.stats.paired_differences import (
    ENDPOINT,
    Comparison,
    CurvePoint,
    paired_difference,
    success_curve,
)


class RankSpread(BaseModel):
    """One form's spread over its variants at the primary endpoint: best − worst, with its interval."""

    form: str
    """The variants' arm (sft_lora, sft_lora_sp, sft_adalora, sft)."""
    variants: list[str]
    best: str
    worst: str
    comparison: Comparison
    """best − worst at the endpoint; its `difference` is the spread (max − min of the endpoint means)."""


def endpoints(episodes: pd.DataFrame, arms: list[str], n_boot: int) -> dict[str, CurvePoint]:
    """Arm -> its mean success at the primary endpoint with a 95 % interval (the curve's statistics)."""
    present = set(episodes["arm"])
    return {
        arm: success_curve(episodes, arm, budgets=[ENDPOINT], n_boot=n_boot)[0]
        for arm in arms
        if arm in present
    }


def rank_spreads(
    episodes: pd.DataFrame, variants: dict[str, dict], means: dict[str, CurvePoint], n_boot: int
) -> list[RankSpread]:
    """Each form with 2 or more variants that ran: its spread over them (see the module docstring)."""
    forms: dict[str, list[str]] = {}
    for name, declared in variants.items():
        if name in means:
            forms.setdefault(declared["arm"], []).append(name)
    out = []
    for form, names in forms.items():
        if len(names) < 2:
            continue
        ordered = sorted(names, key=lambda n: means[n].mean)
        worst, best = ordered[0], ordered[-1]
        comparison = paired_difference(episodes, best, worst, ENDPOINT, n_boot=n_boot)
        out.append(RankSpread(form=form, variants=names, best=best, worst=worst, comparison=comparison))
    return out
