"""Wall time of `make install` on a fresh clone, with no download cache: this revision's recipe against
an earlier revision's, in the same session (each in a clone of its own, one after the other).

Run: python3 benchmarks/bench_install.py [--before REV] [--rounds N]
Writes benchmarks/results/install.{md,json}.

`make test` starts with this install on every CI run (a clean clone, a new machine), so its time counts
against the suite's 15-minute budget as much as any test. pip's and uv's caches are switched off
(PIP_NO_CACHE_DIR, UV_NO_CACHE) as on a new machine; the system packages of
scripts/install_system_deps.sh are already present after the first install and cost both recipes the
same check. Each install is then checked: the same packages (names normalised) and torch's build.
"""

import argparse
import json
import os
import platform
import re
import shutil
import statistics
import subprocess
import tempfile
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
REPO = HERE.parent
RESULTS = HERE / "results"


def _normalised(name: str) -> str:
    return re.sub(r"[-_.]+", "-", name).lower()


def _packages(venv: Path) -> dict[str, str]:
    """{normalised name: version} of what the venv holds, by its own interpreter (no pip or uv needed)."""
    code = (
        "import importlib.metadata as m, json; "
        "print(json.dumps({d.metadata['Name']: d.version for d in m.distributions()}))"
    )
    out = subprocess.run([venv / "bin/python", "-c", code], capture_output=True, text=True, check=True)
    return {_normalised(k): v for k, v in json.loads(out.stdout).items()}


def _install(rev: str, root: Path) -> dict:
    """A clone of `rev`, its `make install` timed; what it installed."""
    clone = root / rev
    subprocess.run(["git", "clone", "-q", str(REPO), str(clone)], check=True)
    subprocess.run(["git", "-C", str(clone), "checkout", "-q", rev], check=True)
    env = {**os.environ, "PIP_NO_CACHE_DIR": "1", "UV_NO_CACHE": "1"}
    started = time.monotonic()
    proc = subprocess.run(["make", "install"], cwd=clone, env=env, capture_output=True, text=True)
    seconds = time.monotonic() - started
    if proc.returncode != 0:
        raise SystemExit(f"make install at {rev} failed:\n{proc.stderr[-3000:]}")
    packages = _packages(clone / ".venv")
    shutil.rmtree(clone)
    return {"rev": rev, "seconds": round(seconds, 1), "packages": packages}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--before", default="56d40ee", help="the revision to compare with (pip alone)")
    parser.add_argument("--rounds", type=int, default=1)
    args = parser.parse_args()
    head = subprocess.run(
        ["git", "-C", str(REPO), "rev-parse", "--short", "HEAD"], capture_output=True, text=True, check=True
    ).stdout.strip()
    load_start = os.getloadavg()[0]
    rounds = []
    with tempfile.TemporaryDirectory(prefix="bench-install-") as tmp:
        for i in range(args.rounds):
            order = (args.before, head) if i % 2 == 0 else (head, args.before)
            results = {r["rev"]: r for r in (_install(rev, Path(tmp) / str(i)) for rev in order)}
            rounds.append(results)
            print(
                f"round {i + 1}: {args.before} {results[args.before]['seconds']} s, "
                f"{head} {results[head]['seconds']} s",
                flush=True,
            )
    before_s = round(statistics.median(r[args.before]["seconds"] for r in rounds), 1)
    after_s = round(statistics.median(r[head]["seconds"] for r in rounds), 1)
    old, new = rounds[0][args.before]["packages"], rounds[0][head]["packages"]
    only_old = sorted(set(old) - set(new))
    only_new = sorted(set(new) - set(old))
    other_version = sorted(f"{k} {old[k]} → {new[k]}" for k in set(old) & set(new) if old[k] != new[k])
    record = {
        "date": time.strftime("%Y-%m-%dT%H:%M:%S+00:00", time.gmtime()),
        "machine": f"{platform.machine()}, {os.cpu_count()} cores",
        "load_average": [round(load_start, 1), round(os.getloadavg()[0], 1)],
        "before": args.before,
        "head": head,
        "rounds": [{rev: r["seconds"] for rev, r in rd.items()} for rd in rounds],
        "before_s": before_s,
        "head_s": after_s,
        "ratio": round(after_s / before_s, 2),
        "torch": [old.get("torch"), new.get("torch")],
        "packages": [len(old), len(new)],
        "only_before": only_old,
        "only_head": only_new,
        "other_version": other_version,
    }
    RESULTS.mkdir(exist_ok=True)
    (RESULTS / "install.json").write_text(json.dumps(record, indent=2) + "\n")
    lines = [
        "# `make install` on a fresh clone (bench_install.py)",
        "",
        f"{record['date']}; {record['machine']}, load average {record['load_average'][0]} at the start, "
        f"{record['load_average'][1]} at the end. No pip or uv cache; median of {args.rounds} round(s), "
        "recipes alternating.",
        "",
        "| recipe | seconds | rounds |",
        "|---|---|---|",
        f"| {args.before} (pip for everything) | {before_s} | "
        + ", ".join(str(r[args.before]["seconds"]) for r in rounds)
        + " |",
        f"| {head} (pip for uv and torch, uv for the project) | {after_s} | "
        + ", ".join(str(r[head]["seconds"]) for r in rounds)
        + " |",
        "",
        f"{head} / {args.before}: **{record['ratio']}×**. torch: {old.get('torch')} / {new.get('torch')}; "
        f"{len(old)} / {len(new)} packages. Only before: {', '.join(only_old) or 'none'}. Only at {head}: "
        f"{', '.join(only_new) or 'none'}. Other versions: {', '.join(other_version) or 'none'}.",
    ]
    (RESULTS / "install.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
