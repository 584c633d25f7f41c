"""Step: the comparison table of the pipeline's arms (mean ± std over training seeds, per task)."""

from __future__ import annotations

import statistics
from typing import Any

from tasks.caching import cached_step
from tasks.prefect_task import pipeline_task
from tasks.workspace import Workspace, provenance


def _mean_std(values: list[float]) -> dict[str, float]:
    return {
        "mean": statistics.fmean(values),
        "std": statistics.stdev(values) if len(values) > 1 else 0.0,
        "n": len(values),
    }


def trained_with(checkpoint_config: dict[str, Any], key: str) -> Any:
    """A setting of the training run that made a checkpoint (`lr`, `steps`, ...); None if unrecorded."""
    return checkpoint_config.get("train_step", {}).get("train", {}).get(key)


def comparison(workspace: Workspace, evaluations: dict[str, str]) -> dict[str, Any]:
    """`evaluations`: label "<arm>/seed<k>" -> evaluation id. Refuses mixed protocols.

    This is the report's content, so its id: only what the evaluated checkpoints and their scores
    determine. Measured speeds and wall times differ from one run, machine or load to the next, so they
    stay in the checkpoints' records (sidecars) and are read from there when a report is rendered
    (`timings`, `markdown_table(table, timings)`).
    """
    per_arm: dict[str, list[dict[str, Any]]] = {}
    fingerprints = set()
    for label, eval_id in sorted(evaluations.items()):
        arm = label.split("/")[0]
        record = workspace.api.get(eval_id)
        doc = workspace.api.store.open_json(eval_id)
        checkpoint = workspace.api.get(doc["checkpoint_id"])
        summary = checkpoint.config.get("summary", {})
        fingerprints.add(doc["fingerprint"])
        per_arm.setdefault(arm, []).append(
            {
                "label": label,
                "evaluation_id": eval_id,
                "checkpoint_id": checkpoint.id,
                "success_rates": record.config["success_rates"],
                "mean_success": record.config["mean_success"],
                "trainable_parameters": summary.get("trainable_parameters"),
                "lr": trained_with(checkpoint.config, "lr"),
                "active_ranks": summary.get("active_ranks"),
            }
        )
    if len(fingerprints) > 1:
        raise ValueError(f"evaluations use {len(fingerprints)} different protocols; refusing to compare them")
    arms = {}
    for arm, runs in per_arm.items():
        tasks = sorted(runs[0]["success_rates"])
        arms[arm] = {
            "overall": _mean_std([r["mean_success"] for r in runs]),
            "per_task": {t: _mean_std([r["success_rates"][t] for r in runs]) for t in tasks},
            "trainable_parameters": runs[0]["trainable_parameters"],
            "lr": runs[0]["lr"],
            "runs": runs,
        }
    return {"fingerprint": fingerprints.pop() if fingerprints else None, "arms": arms}


def timings(workspace: Workspace, table: dict[str, Any]) -> dict[str, dict[str, float | None]]:
    """arm -> `ms_per_step` and `train_wall_s`, medians over the arm's runs, from the training records
    (the checkpoints' sidecars): provenance, kept out of the report's content.

    Medians: a seed's checkpoint may be a cache hit trained under other load (a sweep cell)."""
    out = {}
    for arm, row in table["arms"].items():
        speeds, walls = [], []
        for run in row["runs"]:
            summary = workspace.api.get(run["checkpoint_id"]).config.get("summary", {})
            speed, steps = summary.get("steps_per_s"), summary.get("steps")
            if speed:
                speeds.append(speed)
                if steps:
                    walls.append(steps / speed)
        out[arm] = {
            "ms_per_step": 1000.0 / statistics.median(speeds) if speeds else None,
            "train_wall_s": statistics.median(walls) if walls else None,
        }
    return out


def markdown_table(table: dict[str, Any], timings: dict[str, dict[str, float | None]] | None = None) -> str:
    """The comparison as Markdown; with `timings` (see `timings`), two columns of measured speed."""
    arms = table["arms"]
    if not arms:
        return "(no evaluations)\n"
    tasks = sorted(next(iter(arms.values()))["per_task"])
    measured = ["ms/step (median)", "training s (median)"] if timings is not None else []
    head = ["arm", "overall", *tasks, *measured, "trainable params", "lr", "seeds"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for arm, row in arms.items():
        cells = [arm, _pct(row["overall"])] + [_pct(row["per_task"][t]) for t in tasks]
        if timings is not None:
            ms, wall = (timings.get(arm, {}).get(k) for k in ("ms_per_step", "train_wall_s"))
            cells += [f"{ms:.1f}" if ms else "-", f"{wall:.0f}" if wall else "-"]
        cells += [
            f"{row['trainable_parameters'] or '-'}",
            f"{row['lr']:g}" if row.get("lr") else "-",
            str(row["overall"]["n"]),
        ]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + f"\n\nProtocol fingerprint: `{table['fingerprint']}`\n"


def _pct(stat: dict[str, float]) -> str:
    return f"{100 * stat['mean']:.1f} ± {100 * stat['std']:.1f}"


def run_report(workspace: Workspace, step: str, inputs: dict[str, str], config: dict[str, Any]) -> str:
    def produce(key: str) -> str:
        table = comparison(workspace, inputs)
        table["markdown"] = markdown_table(table)
        record = workspace.api.register_json(
            table,
            kind="report",
            name=step,
            config={**config, "cache_key": key},
            parents=[(eval_id, "evaluation") for eval_id in dict.fromkeys(inputs.values())],
            **provenance(),
        )
        return record.id

    return cached_step(workspace, "report", inputs, config, produce)


@pipeline_task("report")
def report_task(home: str, step: str, inputs: dict[str, str], config: dict[str, Any]) -> str:
    return run_report(Workspace(home), step, inputs, config)
