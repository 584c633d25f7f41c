"""The catalogue operations every step makes: indexing an artifact, and its cache lookup by key. Each the
way the catalogue does it now (the file attached to the process's in-memory DuckDB) against the way it
did before (a DuckDB connection of its own per operation; for the lookup, the guarded path for foreign
SQL), alternating in one process on the same catalogue.

Run: .venv/bin/python benchmarks/bench_catalogue_ops.py [--artifacts 300] [--reps 60]
Writes benchmarks/results/catalogue_ops.{md,json}.

The catalogue is a real one: `--artifacts` JSON artifacts registered through `ArtifactsAPI` in a temporary
home, each with a cache key in its config, about a study-smoke home's size (220 artifacts). An index
write adds one new artifact's rows (a copy of a registered record under a new id), as a registration does.
"""

import argparse
import json
import os
import platform
import statistics
import tempfile
import time
import uuid
from collections.abc import Callable
from pathlib import Path

import duckdb

from capvector.artifacts.api import ArtifactsAPI
from capvector.artifacts.catalogue import WRITE_CONFIG, Catalogue, rows_for

RESULTS = Path(__file__).resolve().parent / "results"
LOOKUP_SQL = (
    "SELECT id FROM artifacts WHERE json_extract_string(config, '$.cache_key') = ? "
    "ORDER BY created_at DESC LIMIT 1"
)


def connected_write(path: Path, fn: Callable[[duckdb.DuckDBPyConnection], None]) -> None:
    """The write as the catalogue made it before: a database of its own, one transaction, closed."""
    con = duckdb.connect(str(path), config=WRITE_CONFIG)
    try:
        con.execute("BEGIN")
        fn(con)
        con.execute("COMMIT")
    finally:
        con.close()


def timed(fn: Callable[[], object]) -> tuple[float, float]:
    """(CPU ms, wall ms) of one call."""
    c0, t0 = time.process_time(), time.perf_counter()
    fn()
    return 1e3 * (time.process_time() - c0), 1e3 * (time.perf_counter() - t0)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--artifacts", type=int, default=300)
    parser.add_argument("--reps", type=int, default=60)
    args = parser.parse_args()

    with tempfile.TemporaryDirectory(prefix="bench-catalogue-") as tmp:
        api = ArtifactsAPI(Path(tmp) / "home")
        keys = []
        for i in range(args.artifacts):
            key = uuid.uuid4().hex
            keys.append(key)
            api.register_json({"i": i}, kind="metrics", name=f"step {i}", config={"cache_key": key})
        api.query_rows("SELECT 1")  # the pending rows written
        catalogue: Catalogue = api.catalogue
        template = api.store.get(api.query_rows("SELECT id FROM artifacts LIMIT 1")[1][0][0])

        def new_rows() -> Callable[[duckdb.DuckDBPyConnection], None]:
            rows = rows_for(template.model_copy(update={"id": uuid.uuid4().hex + uuid.uuid4().hex}))
            return lambda con: Catalogue._insert(con, rows, "OR IGNORE")

        ways = {
            "index write": {
                "attached (now)": lambda: catalogue._write(new_rows()),
                "own connection (before)": lambda: catalogue._retrying(
                    lambda fn=new_rows(): connected_write(catalogue.path, fn)
                ),
            },
            "cache lookup": {
                "attached (now)": lambda: catalogue.cached_result(keys[len(keys) // 2]),
                "guarded query (before)": lambda: catalogue.query_rows(LOOKUP_SQL, [keys[len(keys) // 2]]),
            },
        }
        assert catalogue.cached_result(keys[0]) == catalogue.query_rows(LOOKUP_SQL, [keys[0]])[1][0][0]
        samples: dict[str, dict[str, list[tuple[float, float]]]] = {
            op: {way: [] for way in w} for op, w in ways.items()
        }
        load_start = os.getloadavg()[0]
        for op, w in ways.items():
            for fn in w.values():
                fn()  # warm: imports, the host database
            for rep in range(args.reps):
                order = list(w.items()) if rep % 2 == 0 else list(reversed(w.items()))
                for way, fn in order:
                    samples[op][way].append(timed(fn))

    record = {
        "date": time.strftime("%Y-%m-%dT%H:%M:%S+00:00", time.gmtime()),
        "machine": f"{platform.machine()}, {os.cpu_count()} cores",
        "load_average": [round(load_start, 1), round(os.getloadavg()[0], 1)],
        "artifacts": args.artifacts,
        "reps": args.reps,
        "median_ms": {
            op: {
                way: {
                    "cpu": round(statistics.median(c for c, _ in s), 2),
                    "wall": round(statistics.median(t for _, t in s), 2),
                }
                for way, s in by_way.items()
            }
            for op, by_way in samples.items()
        },
    }
    lines = [
        "# Catalogue operations of a step (bench_catalogue_ops.py)",
        "",
        f"{record['date']}; {record['machine']}, load average {record['load_average'][0]} at the start, "
        f"{record['load_average'][1]} at the end. A catalogue of {args.artifacts} artifacts; medians of "
        f"{args.reps} calls each, the two ways alternating.",
        "",
        "| operation | way | CPU ms | wall ms |",
        "|---|---|---|---|",
    ]
    for op, by_way in record["median_ms"].items():
        for way, m in by_way.items():
            lines.append(f"| {op} | {way} | {m['cpu']} | {m['wall']} |")
    lines.append("")
    for op, by_way in record["median_ms"].items():
        now, before = list(by_way.values())
        cpu, wall = now["cpu"] / before["cpu"], now["wall"] / before["wall"]
        record.setdefault("ratio", {})[op] = {"cpu": round(cpu, 2), "wall": round(wall, 2)}
        lines.append(f"{op}: now / before **{cpu:.2f}×** CPU, **{wall:.2f}×** wall.")
    RESULTS.mkdir(exist_ok=True)
    (RESULTS / "catalogue_ops.json").write_text(json.dumps(record, indent=2) + "\n")
    (RESULTS / "catalogue_ops.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
