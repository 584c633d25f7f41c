"""What a Prefect API client costs to create, as a step creates two: Prefect's default (a verifying TLS
context built from the whole CA bundle, also for a plain-http API) against the one-certificate bundle
the CLI names for a plain-http API (capvector.flows.runtime.prefect_server._no_ca_bundle_for_plain_http).

Run: .venv/bin/python benchmarks/bench_prefect_client.py [--clients 40] [--rounds 3]
Writes benchmarks/results/prefect_client.{md,json}. No server is needed: creating a client opens no
connection. Each variant runs in a fresh process (Prefect reads its settings at import), and the two
alternate round by round; the figure is CPU time per client (process time), the median of the rounds.
"""

import argparse
import json
import os
import platform
import statistics
import subprocess
import sys
import tempfile
from datetime import UTC, datetime
from pathlib import Path

HERE = Path(__file__).resolve().parent
REPO = HERE.parent
RESULTS = HERE / "results"
sys.path.insert(0, str(REPO))

from capvector.flows.runtime.prefect_server import _no_ca_bundle_for_plain_http  # noqa: E402

CREATE = """
import sys, time
from prefect.client.orchestration import get_client
get_client(sync_client=True)  # the first one imports what clients need
start = time.process_time()
for _ in range(int(sys.argv[1])):
    get_client(sync_client=True)
print((time.process_time() - start) / int(sys.argv[1]))
"""


def plain_http_env(prefect_home: Path) -> dict[str, str]:
    """This environment with a plain-http API and no certificate file of its own."""
    env = {k: v for k, v in os.environ.items() if k != "PREFECT_API_SSL_CERT_FILE"}
    return env | {"PREFECT_HOME": str(prefect_home), "PREFECT_API_URL": "http://127.0.0.1:9/api"}


def one_certificate_bundle(env: dict[str, str]) -> str:
    """The bundle the CLI names for `env`, made by the CLI's own function (in this script's environment)."""
    os.environ.clear()
    os.environ.update(env)
    _no_ca_bundle_for_plain_http()
    return os.environ["PREFECT_API_SSL_CERT_FILE"]


def per_client_s(clients: int, env: dict[str, str]) -> float:
    """CPU seconds per client created, in a fresh process with `env`."""
    command = [sys.executable, "-c", CREATE, str(clients)]
    out = subprocess.run(command, env=env, capture_output=True, text=True)
    if out.returncode:
        raise SystemExit(out.stderr)
    return float(out.stdout.strip().splitlines()[-1])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--clients", type=int, default=40)
    parser.add_argument("--rounds", type=int, default=3)
    args = parser.parse_args()
    with tempfile.TemporaryDirectory(prefix="capvector-bench-client-") as home:
        default_env = plain_http_env(Path(home))
        one_env = {**default_env, "PREFECT_API_SSL_CERT_FILE": one_certificate_bundle(default_env)}
        default, one = [], []
        for _ in range(args.rounds):
            default.append(per_client_s(args.clients, default_env))
            one.append(per_client_s(args.clients, one_env))
    result = {
        "date": datetime.now(UTC).isoformat(timespec="seconds"),
        "machine": f"{platform.machine()}, {os.cpu_count()} cores, load average {os.getloadavg()[0]:.1f}",
        "clients_per_round": args.clients,
        "default_ms": [1000 * s for s in default],
        "one_certificate_ms": [1000 * s for s in one],
        "ratio": statistics.median(default) / statistics.median(one),
    }
    print(json.dumps(result, indent=1))
    RESULTS.mkdir(exist_ok=True)
    (RESULTS / "prefect_client.json").write_text(json.dumps(result, indent=1) + "\n")
    d, o = statistics.median(result["default_ms"]), statistics.median(result["one_certificate_ms"])
    (RESULTS / "prefect_client.md").write_text(
        "# Creating a Prefect API client (bench_prefect_client.py)\n\n"
        f"{result['date']}; {result['machine']}. CPU time per `get_client(sync_client=True)` for a "
        f"plain-http API, median of {args.rounds} rounds of {args.clients} clients, each variant in a "
        "fresh process.\n\n"
        "| CA bundle | ms per client | per round |\n|---|---|---|\n"
        f"| Prefect's default (certifi, the whole bundle) | {d:.1f} | "
        + ", ".join(f"{x:.1f}" for x in result["default_ms"])
        + f" |\n| one certificate (what the CLI names for http://) | {o:.1f} | "
        + ", ".join(f"{x:.1f}" for x in result["one_certificate_ms"])
        + f" |\n\nThe default costs **{result['ratio']:.0f}×** as much. A step creates two clients in its "
        "worker (its task run's context and the engine's client), so this is about "
        f"{2 * (d - o):.0f} ms of CPU saved per step.\n"
    )


if __name__ == "__main__":
    main()
