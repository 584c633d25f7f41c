"""Cold and warm `capvector run` wall times, with Prefect's fixed overhead measured in the same run.

    python benchmarks/bench_pipeline.py [--presets smoke quick] [--work-dir DIR]

Cold: a fresh home and a fresh Prefect home. Warm: the same again (every step a cache hit).
Prefect's fixed overhead: a process that imports our flows and runs one empty flow on the embedded
API, against one that only imports them; their difference is what any flow run pays up front.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import subprocess
import sys
import tempfile
import time
from datetime import UTC, datetime
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
RESULTS = REPO / "benchmarks" / "results"

EMPTY_FLOW = """
import flows.pipeline
from prefect import flow
@flow
def empty():
    return 1
empty()
"""
IMPORT_ONLY = "import flows.pipeline"


def timed(cmd: list[str], env: dict[str, str]) -> float:
    start = time.perf_counter()
    subprocess.run(cmd, cwd=REPO, env=env, check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    return time.perf_counter() - start


def environment(work: Path, name: str) -> dict[str, str]:
    return {
        **os.environ,
        "CAPVECTOR_HOME": str(work / f"{name}-home"),
        "PREFECT_HOME": str(work / f"{name}-prefect"),
        "CAPVECTOR_QUIET": "1",
        "PREFECT_SERVER_ANALYTICS_ENABLED": "false",
        "DO_NOT_TRACK": "1",
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--presets", nargs="+", default=["smoke"])
    parser.add_argument("--work-dir", type=Path, default=None)
    args = parser.parse_args()
    work = args.work_dir or Path(tempfile.mkdtemp(prefix="capvector-bench-pipeline-"))
    shutil.rmtree(work, ignore_errors=True)
    work.mkdir(parents=True)

    overhead_env = environment(work, "overhead")
    import_only = timed([sys.executable, "-c", IMPORT_ONLY], overhead_env)
    first_flow = timed([sys.executable, "-c", EMPTY_FLOW], overhead_env)  # new Prefect DB: migrations
    later_flow = timed([sys.executable, "-c", EMPTY_FLOW], overhead_env)
    rows = []
    for preset in args.presets:
        env = environment(work, preset)
        cmd = [sys.executable, "-m", "flows.cli", "run", "--preset", preset, "--json"]
        cold = timed(cmd, env)
        warm = timed(cmd, env)
        rows.append({"preset": preset, "cold_s": cold, "warm_s": warm, "warm_over_cold": warm / cold})
        print(f"{preset}: cold {cold:.1f} s, warm {warm:.1f} s ({warm / cold:.0%} of cold)", flush=True)
    overhead = {
        "import_only_s": import_only,
        "empty_flow_new_prefect_db_s": first_flow,
        "empty_flow_s": later_flow,
        "prefect_fixed_overhead_s": later_flow - import_only,
    }
    print(json.dumps(overhead, indent=1))
    load = os.getloadavg()
    result = {
        "date": datetime.now(UTC).isoformat(timespec="seconds"),
        "machine": f"{platform.machine()}, {os.cpu_count()} cores, load average {load[0]:.1f} at the end",
        "runs": rows,
        "prefect": overhead,
    }
    (RESULTS / "pipeline.json").write_text(json.dumps(result, indent=1) + "\n")
    lines = [
        "# Pipeline wall time (bench_pipeline.py)",
        "",
        f"{result['date']}; {result['machine']}. Each run is a fresh `python -m flows.cli run` process.",
        "",
        "| preset | cold s | warm s (all cache hits) | warm / cold | warm minus Prefect fixed overhead s |",
        "|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(
            f"| {r['preset']} | {r['cold_s']:.1f} | {r['warm_s']:.1f} | {r['warm_over_cold']:.2f} | "
            f"{r['warm_s'] - overhead['prefect_fixed_overhead_s']:.1f} |"
        )
    lines += [
        "",
        "Prefect's fixed overhead, same run: importing our flows takes "
        f"{import_only:.1f} s; a process that also runs one empty flow takes {later_flow:.1f} s "
        f"({first_flow:.1f} s with a brand-new Prefect database), so a flow run pays about "
        f"**{overhead['prefect_fixed_overhead_s']:.1f} s** up front (embedded API server start).",
        "",
    ]
    (RESULTS / "pipeline.md").write_text("\n".join(lines))
    shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()
