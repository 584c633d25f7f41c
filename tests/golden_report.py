"""study-smoke's golden report numbers (tests/data/study_smoke_report.json) and the one comparison of a
study report with them, shared by the study flow's test and the killed-and-resumed study's."""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

GOLDEN = Path(__file__).parent / "data" / "study_smoke_report.json"


def report_numbers(report: Any) -> dict:
    """A StudyReport's numbers as the golden file holds them: ids left out (they embed code hashes)."""
    return json.loads(json.dumps(report.model_dump(mode="json", exclude={"final_checkpoints", "selections"})))


def same_numbers(actual: object, golden: object, path: str = "") -> list[str]:
    """Where `actual` differs from `golden`: floats within 1e-4 relative (another CPU's kernels may
    round differently; a changed step moves them far more), NaN equal to NaN, everything else exact."""
    if isinstance(golden, dict) and isinstance(actual, dict):
        keys = sorted(set(golden) | set(actual))
        missing = [
            f"{path}/{k}: only in {'golden' if k in golden else 'this run'}"
            for k in keys
            if (k in golden) != (k in actual)
        ]
        return missing + [
            d
            for k in keys
            if k in golden and k in actual
            for d in same_numbers(actual[k], golden[k], f"{path}/{k}")
        ]
    if isinstance(golden, list) and isinstance(actual, list):
        if len(golden) != len(actual):
            return [f"{path}: {len(actual)} items, golden {len(golden)}"]
        return [
            d
            for i, (a, g) in enumerate(zip(actual, golden, strict=True))
            for d in same_numbers(a, g, f"{path}[{i}]")
        ]
    if isinstance(golden, float) or isinstance(actual, float):
        a, g = float(actual), float(golden)
        if (math.isnan(a) and math.isnan(g)) or math.isclose(a, g, rel_tol=1e-4, abs_tol=1e-7):
            return []
    elif actual == golden:
        return []
    return [f"{path}: {actual!r}, golden {golden!r}"]


def golden_differences(report: Any) -> list[str]:
    """Where a study-smoke StudyReport's numbers differ from the golden ones (empty: none)."""
    return same_numbers(report_numbers(report), json.loads(GOLDEN.read_text()))
