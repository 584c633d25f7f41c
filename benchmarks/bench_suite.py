"""What CI measures: `.ci/run` (the README's `make test`: install, ruff, the suite) on a fresh clone of HEAD
with no pip or uv download cache, timed as a whole, and each test file's share of the suite.

Run: python3 benchmarks/bench_suite.py
Writes benchmarks/results/suite.{md,json}.

CI gives `make test` 15 minutes on 2 cores; this is the same command on this machine, so run it with
nothing else on the cores (the load average at the start and the end is recorded). Per-file seconds are
the sum of pytest's per-test durations (setup, call and teardown) of that file: worker seconds, which two
pytest-xdist workers share, not wall time.
"""

import argparse
import json
import os
import platform
import re
import subprocess
import tempfile
import time
from collections import Counter
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
RESULTS = REPO / "benchmarks" / "results"
DURATION = re.compile(r"^([0-9.]+)s (?:call|setup|teardown)\s+(tests/[^:]+)::", re.MULTILINE)
SUMMARY = re.compile(r"(\d+) passed.* in ([0-9.]+)s")
TOP = 12


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--log", type=Path, help="also keep .ci/run's whole output (per-test durations) here")
    args = ap.parse_args()
    head = subprocess.run(
        ["git", "-C", str(REPO), "rev-parse", "--short", "HEAD"], capture_output=True, text=True, check=True
    ).stdout.strip()
    load_start = os.getloadavg()[0]
    with tempfile.TemporaryDirectory(prefix="bench-suite-") as tmp:
        clone = Path(tmp) / "clone"
        subprocess.run(["git", "clone", "-q", str(REPO), str(clone)], check=True)
        env = {**os.environ, "PIP_NO_CACHE_DIR": "1", "UV_NO_CACHE": "1", "PYTEST_ADDOPTS": "--durations=0"}
        started = time.monotonic()
        proc = subprocess.run([str(clone / ".ci/run")], cwd=clone, env=env, capture_output=True, text=True)
        total_s = time.monotonic() - started
    out = proc.stdout + proc.stderr
    if args.log:
        args.log.write_text(out)
    summary = SUMMARY.search(out)
    if proc.returncode != 0 or summary is None:
        raise SystemExit(f".ci/run failed ({proc.returncode}):\n{out[-4000:]}")
    per_file: Counter[str] = Counter()
    for seconds, path in DURATION.findall(out):
        per_file[path] += float(seconds)
    suite_s = float(summary.group(2))
    record = {
        "date": time.strftime("%Y-%m-%dT%H:%M:%S+00:00", time.gmtime()),
        "machine": f"{platform.machine()}, {os.cpu_count()} cores",
        "load_average": [round(load_start, 1), round(os.getloadavg()[0], 1)],
        "head": head,
        "total_s": round(total_s, 1),
        "suite_s": suite_s,
        "before_suite_s": round(total_s - suite_s, 1),
        "passed": int(summary.group(1)),
        "worker_s": round(sum(per_file.values()), 1),
        "per_file_s": {path: round(s, 1) for path, s in per_file.most_common()},
    }
    RESULTS.mkdir(exist_ok=True)
    (RESULTS / "suite.json").write_text(json.dumps(record, indent=2) + "\n")
    lines = [
        "# `.ci/run` on a fresh clone (bench_suite.py)",
        "",
        f"{record['date']}, {head}; {record['machine']}, load average {record['load_average'][0]} at the "
        f"start, {record['load_average'][1]} at the end. No pip or uv download cache.",
        "",
        f"**{record['total_s']} s in all** (CI's budget: 900 s): install and ruff "
        f"{record['before_suite_s']} s, the suite {suite_s} s; {record['passed']} passed. "
        f"The tests' durations add up to {record['worker_s']} worker-seconds on 2 workers.",
        "",
        "| test file | worker-seconds | share |",
        "|---|---|---|",
        *(
            f"| {path} | {s:.1f} | {s / record['worker_s']:.0%} |"
            for path, s in list(record["per_file_s"].items())[:TOP]
        ),
    ]
    (RESULTS / "suite.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
