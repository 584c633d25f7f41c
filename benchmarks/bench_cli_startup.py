"""Startup of a read-only command: `capvector sql "SELECT 1"` against plain DuckDB on the same file.

Run: .venv/bin/python benchmarks/bench_cli_startup.py [--home H] [--rounds 9]
Writes benchmarks/results/cli_startup.{md,json}. Scratch homes go to benchmarks/_work (git-ignored)
and are deleted afterwards.

Three commands, each in a fresh process, alternating round by round so a busy machine slows all alike:
- `capvector sql "SELECT 1"`: the console script, with this checkout's code;
- the same from the code before issue 22 made the read-only commands light (OLD_COMMIT, taken from
  git; it imported pandas, through the catalogue, for every command), on its own home built by that
  code (a catalogue of this code's schema is too new for it) with the same artifacts;
- the floor: `python -c "import duckdb; duckdb.connect(<catalogue>, read_only=True).execute('SELECT 1')
  .fetchall()"` on the new home's catalogue file.
The ratio new / floor is the measurement (target: within 3x).
"""

import argparse
import json
import os
import platform
import shutil
import statistics
import subprocess
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
REPO = HERE.parent
WORK = HERE / "_work" / "cli_startup"
RESULTS = HERE / "results"
OLD_COMMIT = "11af9ff"  # main before the read-only commands were made light (issue 22, item 3)
TARGET = 3.0

# Registers a small lineage (chains of checkpoints with evaluations) in a home, with whichever
# `artifacts` package comes first on sys.path (argv[1]).
BUILD = """
import sys
sys.path.insert(0, sys.argv[1])
from capvector.artifacts.api import ArtifactsAPI
api = ArtifactsAPI(sys.argv[2])
n = int(sys.argv[3])
parent = None
for i in range(n):
    parents = [(parent, "init")] if parent else []
    parent = api.register_json({"w": i}, "checkpoint", f"ckpt-{i}", parents=parents).id
    if i % 10 == 9:
        parent = None
print(api.query("SELECT count(*) AS n FROM artifacts")["n"][0])
"""

FLOOR = "import duckdb, sys; duckdb.connect(sys.argv[1], read_only=True).execute('SELECT 1').fetchall()"


def _old_code(root: Path) -> Path:
    """OLD_COMMIT's packages, extracted from git (the working tree is not touched)."""
    if root.exists():
        shutil.rmtree(root)
    root.mkdir(parents=True)
    archive = subprocess.run(
        ["git", "archive", OLD_COMMIT, "artifacts", "flows", "tasks", "capvector_core"],
        cwd=REPO, check=True, capture_output=True,
    ).stdout  # fmt: skip
    subprocess.run(["tar", "-x", "-C", str(root)], input=archive, check=True)
    return root


def _timed(cmd: list[str], cwd: Path, env: dict[str, str]) -> float:
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, cwd=cwd, env=env, capture_output=True, text=True)
    elapsed = time.perf_counter() - t0
    if proc.returncode != 0:
        raise RuntimeError(f"{cmd} failed: {proc.stderr}")
    return elapsed


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--home", help="an existing home (default: a fresh one with --artifacts artifacts)")
    parser.add_argument("--artifacts", type=int, default=200)
    parser.add_argument("--rounds", type=int, default=9)
    args = parser.parse_args()

    WORK.mkdir(parents=True, exist_ok=True)
    old_root = _old_code(WORK / "old")
    new_home = Path(args.home) if args.home else WORK / "home-new"
    old_home = WORK / "home-old"
    for home, root in ([] if args.home else [(new_home, REPO)]) + [(old_home, old_root)]:
        shutil.rmtree(home, ignore_errors=True)
        subprocess.run([sys.executable, "-c", BUILD, str(root), str(home), str(args.artifacts)],
                       cwd=root, check=True, capture_output=True)  # fmt: skip
    catalogue = new_home / "catalogue.duckdb"
    assert catalogue.exists(), catalogue

    console_script = Path(sys.executable).with_name("capvector")
    new_cmd = [str(console_script)] if console_script.exists() else [sys.executable, "-m", "capvector"]
    env = {k: v for k, v in os.environ.items() if k != "CAPVECTOR_HOME"}
    commands = {
        "new": (new_cmd + ["--home", str(new_home), "sql", "SELECT 1"], REPO),
        # `python -m` puts the working directory first on sys.path: the old packages win over the
        # editable install.
        "old": ([sys.executable, "-m", "capvector", "--home", str(old_home), "sql", "SELECT 1"], old_root),
        "floor": ([sys.executable, "-c", FLOOR, str(catalogue)], REPO),
    }
    for cmd, cwd in commands.values():  # warm the page cache and the bytecode caches
        _timed(cmd, cwd, env)
    times: dict[str, list[float]] = {name: [] for name in commands}
    for r in range(args.rounds):
        order = list(commands) if r % 2 == 0 else list(reversed(commands))
        for name in order:
            cmd, cwd = commands[name]
            times[name].append(_timed(cmd, cwd, env))

    med = {name: statistics.median(ts) for name, ts in times.items()}
    result = {
        "machine": f"{platform.machine()}, {os.cpu_count()} cores, Python {platform.python_version()}",
        "rounds": args.rounds,
        "artifacts": args.artifacts if not args.home else None,
        "median_s": med,
        "all_s": times,
        "ratio_new_to_floor": med["new"] / med["floor"],
        "ratio_old_to_floor": med["old"] / med["floor"],
        "speedup_old_to_new": med["old"] / med["new"],
        "target": TARGET,
        "old_commit": OLD_COMMIT,
        "date": time.strftime("%Y-%m-%d"),
    }
    rows = [
        ("`capvector sql \"SELECT 1\"` (this code)", "new"),
        (f"the same at {OLD_COMMIT} (pandas and more imported by every command)", "old"),
        ("plain `duckdb.connect(catalogue, read_only=True)` + `SELECT 1`", "floor"),
    ]
    md = [
        "# CLI startup: a read-only command against plain DuckDB",
        "",
        f"`benchmarks/bench_cli_startup.py`, {result['date']}, {result['machine']}; each command in a",
        f"fresh process, {args.rounds} rounds alternating the order, medians (the machine was shared with",
        "other jobs).",
        f"Home: {args.artifacts} checkpoints in chains of 10 (a real store and catalogue)."
        if not args.home
        else f"Home: {new_home}.",
        "",
        "| command | median | × plain DuckDB |",
        "|---|---|---|",
        *[f"| {label} | {med[k]:.3f} s | {med[k] / med['floor']:.2f}× |" for label, k in rows],
        "",
        f"**{result['ratio_new_to_floor']:.2f}× plain DuckDB** (target: within {TARGET:.0f}×; "
        f"{result['speedup_old_to_new']:.2f}× faster than at {OLD_COMMIT}).",
        "",
    ]
    RESULTS.mkdir(exist_ok=True)
    (RESULTS / "cli_startup.md").write_text("\n".join(md))
    (RESULTS / "cli_startup.json").write_text(json.dumps(result, indent=1) + "\n")
    print("\n".join(md))
    shutil.rmtree(WORK, ignore_errors=True)


if __name__ == "__main__":
    main()
