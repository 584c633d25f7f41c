"""The GPU gate runs' report from their committed episode records (docs/studies/data/pixels_gpu_*.jsonl.gz).

`scripts/pixels_gate_gpu.py` ran on lent H200 machines (and once on a workstation); its per-episode
records and run summaries were copied into docs/studies/data/. This script recomputes every number of
docs/studies/study_pixels_gpu.md from them with the study's own statistics (paired t intervals on a
conservative moments variance since issue 41, MDD) and draws the figure.

    python scripts/pixels_gate_report.py
"""

from __future__ import annotations

import json
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import pandas as pd  # noqa: E402

from capvector.stats.paired_differences import ENDPOINT, endpoint_rows, paired_difference, success_curve  # noqa: E402

DOCS = Path(__file__).resolve().parent.parent / "docs" / "studies"
RUNS = {
    "gate": "run 1: the gate phase (5 demos per downstream task, 400 steps, aux weight 0.5)",
    "scarce": "run 2: 2 demos per downstream task, aux weights 0.1 / 0.5 / 2 chosen on validation goals",
    "long": "run 3: 2 demos per task, 1000 steps, aux weight 2 (run 2's validation choice), 4 seeds",
    "hard_spatial": "run 4: the six hardest calibrated tasks downstream, the 9-d xyz `spatial` objective, "
    "weights 0.5 / 2 chosen on validation goals",
    "hard_depth": "run 5: run 4's tasks and design with `spatial_depth`",
    "hard_spatial_cpu": "run 6: run 4 replicated with fresh seeds 3-8 and its chosen weight 0.5, "
    "on a 2-core workstation (no extraction)",
    "state_large": "run 7: the control testbed (state through random features, the `spatial` objective) "
    "with the larger policy, 6000-step extraction, 3 draws × 4 seeds, weights 0.5 / 2 chosen on "
    "validation goals",
    "state_large_hard": "run 8: run 7 on `study-control-hard`'s tasks (cut short by the session's "
    "device time)",
}
TITLES = {
    "gate": "run 1: 5 demos/task",
    "scarce": "run 2: 2 demos/task",
    "long": "run 3: 2 demos, 1000 steps",
    "hard_spatial": "run 4: hard tasks, xyz objective",
    "hard_depth": "run 5: hard tasks, depth objective",
    "hard_spatial_cpu": "run 6: run 4, seeds 3-8 (CPU)",
    "state_large": "run 7: state features, larger policy",
    "state_large_hard": "run 8: run 7, hard tasks",
}
COLOURS = {"sft": "#4c72b0", "aux": "#dd8452", "sft_from_ao": "#55a868", "sft_from_ft": "#8c8c8c"}


def load(docs: Path, name: str) -> tuple[pd.DataFrame, dict]:
    episodes = pd.read_json(docs / "data" / f"pixels_gpu_{name}.jsonl.gz", lines=True)
    if "split" not in episodes:  # run 1 predates the column: D_ext rows (ao, ft) are validation goals
        episodes["split"] = episodes["arm"].map(lambda a: "validation" if a in ("ao", "ft") else "test")
    return episodes, json.loads((docs / "data" / f"pixels_gpu_{name}_runs.json").read_text())


def with_endpoint(episodes: pd.DataFrame, budgets: list[int]) -> pd.DataFrame:
    trained = episodes[episodes["budget"].isin(budgets)]
    return pd.concat([episodes, endpoint_rows(trained, budgets)], ignore_index=True)


def cell(c) -> str:
    return f"{c.difference:+.1f} [{c.ci_low:+.1f}, {c.ci_high:+.1f}] (MDD {c.mdd:.1f})"


def chosen_weight(episodes: pd.DataFrame, budgets: list[int]) -> str:
    """The aux arm with the highest mean validation success at the endpoint (ties: the first listed)."""
    valid = episodes[(episodes["split"] == "validation") & episodes["budget"].isin(budgets)]
    means = valid[valid["arm"].str.startswith("aux")].groupby("arm", sort=False)["success"].mean()
    return str(means.idxmax())


def complete_draws(test: pd.DataFrame, arms: list[str]) -> pd.DataFrame:
    """`test` without the draws some (arm, seed, budget) run of `arms` lacks: a run cut short by its time
    limit loses its last-queued evaluations, which depend on queue order, not on their outcome."""
    runs = test[test["arm"].isin(arms)].groupby(["draw", "arm", "seed", "budget"]).size()
    per_draw = runs.groupby(level="draw").size()
    whole = per_draw[per_draw == per_draw.max()].index
    return test[~test["arm"].isin(arms) | test["draw"].isin(whole)]


def convergence(runs: dict) -> str | None:
    """Precondition (a): each extraction run's held-out action loss change over its second half."""
    changes = []
    for name, run in sorted(runs["runs"].items()):
        losses = list(run.get("heldout_loss", {}).values())
        if len(losses) == 2:
            changes.append(f"θ_{name[:2]}^{name[2:]} {100 * (losses[1] - losses[0]) / losses[0]:+.1f} %")
    return ", ".join(changes) or None


def curve_rows(test: pd.DataFrame, arms: list[str], budgets: list[int]) -> list[str]:
    lines = ["| arm | " + " | ".join(str(b) for b in budgets) + " |", "|---" * (len(budgets) + 1) + "|"]
    for arm in arms:
        points = success_curve(test, arm, budgets, n_boot=1000)
        cells = [f"{p.mean:.1f} [{p.ci_low:.1f}, {p.ci_high:.1f}]" for p in points]
        lines.append(f"| {arm} | " + " | ".join(cells) + " |")
    return lines


def main(docs: Path = DOCS, out: Path = DOCS) -> Path:
    """Reads `docs`/data, writes the report and its figure into `out`; returns the report's path."""
    sections, figure_data = [], {}
    headline = {}
    for name, title in RUNS.items():
        episodes, runs = load(docs, name)
        budgets = runs["settings"]["budgets"]
        test = with_endpoint(episodes[(episodes["split"] == "test") & (episodes["arm"] != "pt")], budgets)
        several = episodes["arm"].str.startswith("aux@").any()
        aux = chosen_weight(episodes, budgets) if several else "aux"
        lines = [f"### {title}", ""]
        if several:
            lines += [f"Chosen on D_down validation goals (mean over budgets): **{aux}**.", ""]
        rows = [("auxiliary SFT − SFT", aux, "sft")]
        if "sft_from_ao" in set(test["arm"]):
            complete = complete_draws(test, ["sft_from_ao", "sft_from_ft"])
            label = "SFT from θ_ao − SFT from θ_ft (c)"
            if len(complete) < len(test):
                kept = sorted(set(complete[complete["arm"] == "sft_from_ao"]["draw"]))
                label += f", complete draws {', '.join(map(str, kept))}"
            test = complete
            rows.append((label, "sft_from_ao", "sft_from_ft"))
        lines += [
            "| comparison | endpoint (mean over budgets) | " + " | ".join(f"@ {b}" for b in budgets) + " |"
        ]
        lines += ["|---" * (len(budgets) + 2) + "|"]
        for label, arm, base in rows:
            cells = [cell(paired_difference(test, arm, base, b, n_boot=2000)) for b in [ENDPOINT, *budgets]]
            lines.append(f"| {label} | " + " | ".join(cells) + " |")
            if label.startswith("auxiliary"):
                headline[name] = paired_difference(test, arm, base, ENDPOINT, n_boot=2000)
        if "ao" in set(episodes["arm"]):
            ext = episodes[episodes["arm"].isin(["ao", "ft"])]
            b = cell(paired_difference(ext, "ao", "ft", 0))
            lines.append(f"| θ_ao − θ_ft on D_ext validation goals (b) | {b} |")
        if convergence(runs):
            lines += [
                "",
                "(a) held-out action loss change over the extraction runs' second half: "
                f"{convergence(runs)}.",
            ]
        arms = ["sft", *sorted(a for a in set(test["arm"]) if a != "sft")]
        lines += ["", "Success on test goals (mean % [95 % CI]) by downstream steps:", ""]
        lines += curve_rows(test, arms, budgets)
        pt = episodes[episodes["arm"] == "pt"]["success"].mean() * 100
        procs = runs.get("train_procs", 1)
        trainers = f", {procs} training processes sharing the GPU and 9" if procs > 1 else " with 14"
        where = f"one {runs['cuda']}{trainers} CPU rollout workers" if runs["cuda"] else "2 CPU cores"
        wall = f"Wall {runs['wall_s'] / 60:.1f} min on {where}."
        lines += ["", f"θ_pt before downstream training: {pt:.1f} %. {wall}", ""]
        sections += lines
        figure_data[name] = (test, arms, budgets, aux)
    draw(figure_data, out / "study_pixels_gpu_curves.png")
    text = TEMPLATE.format(**{name: cell(c) for name, c in headline.items()})
    report = out / "study_pixels_gpu.md"
    report.write_text(text + "\n".join(sections) + "\n")
    print(f"wrote {report}")
    return report


def draw(data: dict, path: Path) -> None:
    columns = 3
    rows = -(-len(data) // columns)
    fig, axes = plt.subplots(rows, columns, figsize=(4.2 * columns, 3.4 * rows), sharey=True, squeeze=False)
    for ax, (name, (test, arms, budgets, chosen)) in zip(axes.flat, data.items(), strict=False):
        for arm in arms:
            points = success_curve(test, arm, budgets, n_boot=500)
            style = "-" if arm in ("sft", chosen) else ":"
            colour = COLOURS.get(arm.split("@")[0])
            ax.plot(budgets, [p.mean for p in points], style, marker="o", label=arm, color=colour)
            if arm in ("sft", chosen):
                lows, highs = [p.ci_low for p in points], [p.ci_high for p in points]
                ax.fill_between(budgets, lows, highs, alpha=0.15, color=colour)
        ax.set_title(TITLES[name], fontsize=10)
        ax.set_xlabel("downstream steps")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7, loc="lower right")
    for ax in axes.flat[len(data) :]:
        ax.axis("off")
    for ax in axes[:, 0]:
        ax.set_ylabel("test success (%)")
    fig.suptitle(
        "GPU gate runs (1-6 pixels, 7-8 state through random features): auxiliary SFT against SFT",
        fontsize=10,
    )
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


TEMPLATE = """# The GPU gate runs: no positive control (eight runs, all reported)

Issue 26 asks for a testbed where the auxiliary objective helps before asking whether γ carries that
help. The state testbed with random-feature observations gave +4.1 points
(docs/studies/study_control_10000.md).
The faithful analogue of Spatial Forcing is pixels with the `spatial_depth` objective (each vision
token regresses its own image patch's back-projected world xyz from MuJoCo's depth render). It is
GPU-sized, so it ran when a GPU machine was lent (one NVIDIA H200 with 16 CPU cores, 15 minutes of
device time per session, three sessions). The machine has no Prefect or DuckDB, so the recipe ran through
`scripts/pixels_gate_gpu.py`, which calls `capvector_core` directly: the same demos, policies, trainer,
objectives and evaluation as the flows, but without the catalogue or cache. Training ran on the GPU.
Rollouts ran in a pool of 14 CPU processes with EGL rendering, started as each checkpoint was written.
Every episode came back as a record (`docs/studies/data/pixels_gpu_*.jsonl.gz`).
This page is computed from those
records by `scripts/pixels_gate_report.py`.

**Answer: on pixels, and on the state testbed with the larger policy (runs 7-8), the auxiliary
objective helps by a few points at most, never by 10 with an interval above 0, so CapVector is
untestable here too.** Auxiliary SFT − SFT at the primary endpoint (mean
success over the budgets, paired by seed, task and goal, 95 % t intervals of issue 41's statistics):

- run 1 (the gate phase, 5 demos per task, `spatial_depth`): **{gate}**: the objective *hurts* early
  (−5.7 at 100 steps) and ties at 400;
- run 2 (2 demos per task, weight chosen on validation goals): **{scarce}**;
- run 3 (2 demos per task, 1000 steps, 4 seeds): **{long}**;
- run 4 (the six hardest calibrated tasks downstream, the 9-d xyz `spatial` objective): **{hard_spatial}**;
- run 5 (run 4's tasks with `spatial_depth`): **{hard_depth}**;
- run 6 (run 4 replicated with 6 fresh seeds on a workstation's CPUs): **{hard_spatial_cpu}**;
- run 7 (not pixels: the control testbed, state through random features with the `spatial`
  objective, and the larger policy, d_model 128 × 4 layers): **{state_large}**;
- run 8 (run 7 on `study-control-hard`'s tasks): **{state_large_hard}**.

Run 4 came closest to the target (+9.7 at 100 steps, +12.5 at 200), but with 3 seeds its interval is
±40 points. Run 6 was declared after reading run 4's results as its replication: the same design and
the weight run 4 chose on validation goals (0.5), with seeds 3-8. It shrank to +3.6 at the endpoint,
with an interval that includes 0 (MDD 7.9). At the final budget it is +7.5 [+0.1, +15.7], a secondary
endpoint. This is the state testbed's +4 again, not a positive control. Run 4 was the better of the
two runs made in that batch, so some of its size was the luck of the pick.

**Runs 7 and 8: the larger policy on the state testbed, with longer extraction and more seeds.**
They test the lever docs/studies/positive_control.md named as closest to passing the gate: the larger policy
(where (b) and (c) had each held in some 2-core design) with converged extraction runs and more test
goals. Extraction ran 6000 steps (three times the 2-core studies' longest), 3 draws, 4 downstream
seeds, 20 test goals per task, θ_ao's weight 2 (the larger-policy studies' validation choice). The
script trained six runs at once on the GPU (`--train-procs 6`, about 60 steps/s each). Neither run
gives a positive control. Auxiliary SFT − SFT is +2.6 on the calibrated tasks, where SFT reaches 92 %
by 200 steps, and +4.3 [−0.3, +9.6] on the hard tasks. That is the same few points as every state
design before. The hard tasks' +7.1 [+3.2, +10.9] at the final budget is a secondary endpoint. (a) still
fails: held-out loss fell 15-28 % over the second half even at 6000 steps. (b) fails in both runs
(−2.8 and +1.1): θ_ao and θ_ft are at 88-98 % on the extraction tasks' validation goals, with no room
between them. (c) holds on the calibrated tasks, +4.5 [+1.9, +7.3] (MDD 3.6), as it did in the
2-core larger-policy studies. Run 8 was stopped by the session's device-time limit, with 136
evaluations still queued. It lost SFT from θ_ao for draw 0 seeds 1-3, the last runs queued, so its
(c) uses the two complete draws (df 1, uninformative). Its `runs.json` was written on the workstation
from the command's settings and log, because the script writes that file only at its end. A first
attempt at run 8 on the same warm machine reused run 7's work folder, and the trainer resumed run 7's
finished checkpoints as if they were run 8's. Its records were discarded unread. The trainer now
refuses a checkpoint from other data or another start (see `capvector_core/training/trainer.py`), and the
script refuses a non-empty `--work`.

None of the eight reaches the 10-point target with its interval above 0. The gate's other
preconditions were never both shown: runs 7 and 8 are above, and in the pixels runs that measured
them (1, 4 and 5) neither was. (b) θ_ao against θ_ft on
D_ext validation goals: +5.8 in run 1 (two draws, uninformative), −1.7 [−7.2, +3.9] in run 4 and
+0.0 [−10.4, +10.4] in run 5. In runs 4 and 5 the extraction tasks are at 82-91 % for both, near
the ceiling. (c) SFT from θ_ao − SFT from θ_ft: +2.7 (MDD ~30), +4.0 [−7.5, +17.3] and +4.1 [−0.3,
+8.3]. So the gate would stop in every run.

**Setup of the pixels runs (1-6).** Runs 1-3 use the control studies' splits (docs/studies/calibration.md):
θ_pt is trained on 8 pretraining tasks; D_ext has 6 tasks and D_down 7. Their difficulty was calibrated
on state observations, not on pixels: SFT reaches 94 % at 400 steps here, so the tasks are easier in
this mode than in the calibration's. Runs 4-6 use `study-control-hard`'s splits (its preset states the
rule): the six calibrated tasks with the lowest SFT mean (dial-turn, door-unlock, door-lock,
door-close, plate-slide-back, window-close) downstream and the other nine for extraction. There, SFT
reaches 47-52 % at 400 steps. Observations are 64×64 corner2 images plus proprioception. The policy is
`study-pixels`' d_model 128 × 4 layers with a 4×4 token grid. The design is the script's, declared in
`scripts/pixels_gate_gpu.py` before any rollout, and differs from the `study-pixels` preset: other
splits, 2 draws rather than 3, 20 test goals per task rather than 84, 1000 extraction steps rather than
600, budgets 100/200/400, and no lr selection. Settings: θ_pt 2000 steps on 10 demos per task; θ_ft and
θ_ao 1000 steps on 10 demos per task with draws 0 and 1 (same seed and batch order within a draw;
θ_ao's weight 0.5); downstream runs at batch 64 and lr 1e-3 over 3 seeds (run 3: 4 seeds, run 6: 6).
Test goals are 20 per task (seeds 100000+), validation goals 10 per task (seeds 50000+), horizon 150, 4
actions executed per call. The auxiliary weight was 0.5 (the preset's) in run 1. In runs 2, 4 and 5 it
was chosen on D_down validation goals (among 0.1, 0.5 and 2, then 0.5 and 2) before the test rows were
read. Runs 3 and 6 used their predecessor's choice. Run 6 retrained θ_pt on the CPU (same seed, other
numerics), and its θ_pt is a different model: 9.2 % on the test goals against run 4's 0.0 %. So run 6
replicates run 4's design, not its starting point.

**What was tried, in order, and why.** Run 1 is the gate phase of the script's declared design. It showed SFT
near the ceiling after 400 steps. Scarcer data (2 demos per task) is the textbook setting where a
dense auxiliary target should help, so run 2 tried it at three weights. Run 2's chosen weight gained
most at its last budget (+5.2 at 400 steps), so run 3 trained longer with one more seed. That design
choice was made after reading run 2's test results; it is a follow-up, not a confirmatory test. The
gain did not hold (−0.5 at 1000 steps). In the next session two untried levers ran together: harder
tasks (run 5) and, in run 4, also an objective whose targets are the object and goal positions (the
`spatial` objective of the state testbed, here read from vision tokens). Run 6 is run 4's
replication. All six runs are reported; none was dropped.

**What it says.** Dense 3D targets do not change visuomotor learning on these tasks at this scale:
per-patch depth gave nothing (runs 1, 3, 5). Object and goal positions gave about 4 points (run 6), as
they do on the state testbed. The remaining levers are a larger policy (the representation has
more room to be shaped), multi-stage tasks, and distractors that change between demonstrations and
test goals (docs/studies/positive_control.md).

Speed: on the H200 (d_model 128, batch 64, with the rollout pool sharing the CPUs), SFT trained at
51-107 steps/s and auxiliary SFT at 46-77 steps/s, in Python-bound small-model steps. Run 6 trained at
1.2-3.3 steps/s on 2 shared CPU cores, which is 41 minutes for 12 runs plus θ_pt. These figures are
not a clean cost comparison; `benchmarks/results/step_cost.md` is.

![Success vs downstream steps, six pixels runs](study_pixels_gpu_curves.png)

**To rerun on a lent GPU machine** (no package index there): download the wheels the image lacks
for Python 3.12 manylinux into an ignored `.whl/` (pydantic 2.14.4, pydantic-core 2.50.5,
annotated-types, typing-inspection, typing-extensions, mujoco 3.3.0, metaworld 3.1.1, gymnasium 1.4.0,
farama-notifications, glfw, pyopengl, etils, importlib-resources: 48 MB) and the EGL loader debs
into `.gl/`, carry both, and run `pip install --no-index --no-deps --target /tmp/site .whl/*.whl`,
`export PYTHONPATH=/tmp/site:$PWD MUJOCO_GL=egl`, then `python3 scripts/pixels_gate_gpu.py --out
$OUT/gate` (add `--no-extraction --downstream-episodes 2 --aux-weights 0.1 0.5 2.0` for run 2,
`--downstream-episodes 2 --aux-weights 2.0 --downstream-steps 1000 --seeds 0 1 2 3
--no-extraction` for run 3, `--tasks hard --objective spatial --aux-weights 0.5 2` for run 4,
`--tasks hard --objective spatial_depth --aux-weights 0.5 2` for run 5; `--observation
state_features --objective spatial --train-procs 6 --workers 9 --aux-weights 0.5 2
--extraction-aux-weight 2 --extraction-steps 6000 --downstream-steps 200 --draws 0 1 2 --seeds 0 1 2 3
--test-goals 20` for run 7, adding `--tasks hard` for run 8). Run 6 needs no GPU:
`MUJOCO_GL=egl python scripts/pixels_gate_gpu.py --out OUT --tasks hard --objective spatial
--aux-weights 0.5 --no-extraction --seeds 3 4 5 6 7 8 --workers 1` (41 minutes on 2 cores). Copy
`episodes.jsonl` (gzipped) and `runs.json` into `docs/studies/data/` and run this page's script.

## The runs

"""


if __name__ == "__main__":
    main()
