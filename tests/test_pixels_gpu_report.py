"""docs/studies/study_pixels_gpu.md is what scripts/pixels_gate_report.py makes of the committed episode
records: every table and the three headline differences are computed from them (the prose around them quotes
numbers read off those tables)."""

from pathlib import Path

import pytest

pytest.importorskip("matplotlib")
from scripts.pixels_gate_report import DOCS, main  # noqa: E402


def test_committed_report_is_recomputed_from_its_records(tmp_path: Path) -> None:
    regenerated = main(DOCS, tmp_path).read_text()
    assert regenerated == (DOCS / "study_pixels_gpu.md").read_text()
    assert "auxiliary SFT − SFT | -3.5 [" in regenerated  # run 1's endpoint, from the records


def test_a_changed_record_changes_the_report(tmp_path: Path) -> None:
    import gzip
    import shutil

    docs = tmp_path / "docs"
    shutil.copytree(DOCS / "data", docs / "data")
    path = docs / "data" / "pixels_gpu_long.jsonl.gz"
    rows = gzip.decompress(path.read_bytes()).decode()
    flipped = rows.replace('"success": 0', '"success": 1')  # every failure of run 3 becomes a success
    path.write_bytes(gzip.compress(flipped.encode()))
    assert main(docs, tmp_path).read_text() != (DOCS / "study_pixels_gpu.md").read_text()
