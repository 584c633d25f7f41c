"""Wall time of `make install` on a fresh clone, with no download cache, and the CPU an import costs in what
it installed: this revision's recipe against earlier revisions', in the same session (each in a clone of
its own, one after the other).

Run: python3 benchmarks/bench_install.py [--before REV ...] [--rounds N]
Writes benchmarks/results/install.{md,json}.

`make test` starts with this install on every CI run (a clean clone, a new machine), so its time counts
against the suite's 15-minute budget as much as any test. pip's and uv's caches are switched off
(PIP_NO_CACHE_DIR, UV_NO_CACHE) as on a new machine; the system packages of
scripts/install_system_deps.sh are already present after the first install and cost both recipes the
same check. Each install is then checked: the same packages (names normalised) and torch's build.

What an install leaves behind costs again in every process: with PYTHONDONTWRITEBYTECODE set, as on our
machines, a module with no bytecode is compiled from source at each import and never cached. So each
venv's share of modules with bytecode is counted, and the CPU of importing the stack every step process
imports (torch, Prefect, DuckDB, s3fs, Meta-World) is measured in it, in the environment the revision's
Makefile gives its commands (PYTHONDONTWRITEBYTECODE=1 unless it unexports it): the first fresh process,
and the median of 3 after it.
"""

import argparse
import json
import os
import platform
import re
import resource
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


STACK = "import torch, prefect, duckdb, s3fs, metaworld"


def _bytecode_share(venv: Path) -> float:
    """Of the venv's installed modules, the share with bytecode beside them."""
    site = next(venv.glob("lib/python3*/site-packages"))
    sources = sum(1 for _ in site.rglob("*.py"))
    return round(sum(1 for _ in site.rglob("*.pyc")) / sources, 3)


def _cpu_of(argv: list, env: dict[str, str]) -> float:
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    subprocess.run(argv, env=env, check=True, capture_output=True)
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    return after.ru_utime - before.ru_utime + after.ru_stime - before.ru_stime


def _import_cpu(clone: Path) -> tuple[float, float]:
    """CPU seconds (user + system) of a fresh process importing STACK in the clone's venv, as its
    Makefile's commands run it: the first process, and the median of 3 after it."""
    env = {**os.environ, "PYTHONDONTWRITEBYTECODE": "1", "MUJOCO_GL": "egl"}
    if "unexport PYTHONDONTWRITEBYTECODE" in (clone / "Makefile").read_text():
        del env["PYTHONDONTWRITEBYTECODE"]
    argv = [clone / ".venv/bin/python", "-c", STACK]
    first = _cpu_of(argv, env)
    return round(first, 2), round(statistics.median(_cpu_of(argv, env) for _ in range(3)), 2)


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
    venv = clone / ".venv"
    packages, bytecode = _packages(venv), _bytecode_share(venv)
    first, later = _import_cpu(clone)
    shutil.rmtree(clone)
    return {
        "rev": rev,
        "seconds": round(seconds, 1),
        "packages": packages,
        "bytecode": bytecode,
        "first_import_cpu_s": first,
        "import_cpu_s": later,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--before",
        nargs="+",
        default=["56d40ee", "e6001b8"],
        help="revisions to compare with (defaults: pip for everything; uv, every process compiling)",
    )
    parser.add_argument("--rounds", type=int, default=1)
    args = parser.parse_args()
    head = subprocess.run(
        ["git", "-C", str(REPO), "rev-parse", "--short", "HEAD"], capture_output=True, text=True, check=True
    ).stdout.strip()
    revs = [*args.before, head]
    load_start = os.getloadavg()[0]
    rounds = []
    with tempfile.TemporaryDirectory(prefix="bench-install-") as tmp:
        for i in range(args.rounds):
            order = revs[i % len(revs) :] + revs[: i % len(revs)]  # each recipe first in turn
            results = {r["rev"]: r for r in (_install(rev, Path(tmp) / str(i)) for rev in order)}
            rounds.append(results)
            print(
                f"round {i + 1}: "
                + "; ".join(
                    f"{rev} {r['seconds']} s, imports {r['first_import_cpu_s']} / {r['import_cpu_s']} CPU s"
                    for rev, r in results.items()
                ),
                flush=True,
            )

    def median(rev: str, field: str) -> float:
        return round(statistics.median(r[rev][field] for r in rounds), 2)

    base = args.before[0]
    old, new = rounds[0][base]["packages"], rounds[0][head]["packages"]
    only_old, only_new = sorted(set(old) - set(new)), sorted(set(new) - set(old))
    other_version = sorted(f"{k} {old[k]} → {new[k]}" for k in set(old) & set(new) if old[k] != new[k])
    recipes = {
        rev: {
            "seconds": median(rev, "seconds"),
            "rounds": [r[rev]["seconds"] for r in rounds],
            "bytecode_share": rounds[0][rev]["bytecode"],
            "first_import_cpu_s": median(rev, "first_import_cpu_s"),
            "import_cpu_s": median(rev, "import_cpu_s"),
            "torch": rounds[0][rev]["packages"].get("torch"),
            "packages": len(rounds[0][rev]["packages"]),
        }
        for rev in revs
    }
    record = {
        "date": time.strftime("%Y-%m-%dT%H:%M:%S+00:00", time.gmtime()),
        "machine": f"{platform.machine()}, {os.cpu_count()} cores",
        "load_average": [round(load_start, 1), round(os.getloadavg()[0], 1)],
        "head": head,
        "recipes": recipes,
        "only_before": only_old,
        "only_head": only_new,
        "other_version": other_version,
    }
    RESULTS.mkdir(exist_ok=True)
    (RESULTS / "install.json").write_text(json.dumps(record, indent=2) + "\n")
    h = recipes[head]
    lines = [
        "# `make install` on a fresh clone (bench_install.py)",
        "",
        f"{record['date']}; {record['machine']}, load average {record['load_average'][0]} at the start, "
        f"{record['load_average'][1]} at the end. No pip or uv cache; median of {args.rounds} round(s), "
        "recipes taking turns to go first. *Import CPU*: `" + STACK + "` in a fresh process of the new venv, "
        "in the environment the revision's Makefile gives its commands (our machines set "
        "PYTHONDONTWRITEBYTECODE=1; a Makefile may unexport it): the first process, then the median of 3.",
        "",
        "| revision | install s | rounds | modules with bytecode after install | first import CPU s "
        "| later imports CPU s | install, HEAD / this | later imports, HEAD / this |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for rev, r in recipes.items():
        lines.append(
            f"| {rev}{' (HEAD)' if rev == head else ''} | {r['seconds']} | "
            f"{', '.join(map(str, r['rounds']))} | "
            f"{r['bytecode_share']:.0%} | {r['first_import_cpu_s']} | {r['import_cpu_s']} | "
            f"{round(h['seconds'] / r['seconds'], 2)} | "
            f"{round(h['import_cpu_s'] / r['import_cpu_s'], 2)} |"
        )
    lines += [
        "",
        f"torch: {', '.join(str(r['torch']) for r in recipes.values())}; packages: "
        f"{', '.join(str(r['packages']) for r in recipes.values())}. Against {base}: only before "
        f"{', '.join(only_old) or 'none'}; only at {head} {', '.join(only_new) or 'none'}; other versions "
        f"{', '.join(other_version) or 'none'}.",
    ]
    (RESULTS / "install.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
