"""A value chosen on validation goals is an artifact whose parents are the evaluations it was chosen
from, and a step using the value names it as a parent: lineage shows why a number was used."""

import pytest

from capvector.tasks.runtime.workspace import Workspace
from capvector.tasks.steps.selection import chosen, run_select

REACH = "reach-v3"


def _evaluation(ws: Workspace, name: str, successes: list[bool], fp: str = "f" * 64) -> str:
    checkpoint = ws.api.register_json({"w": name}, "checkpoint", name).id
    episodes = [
        {"task": REACH, "seed": 7000 + i, "success": ok, "steps": 5, "return": float(ok)}
        for i, ok in enumerate(successes)
    ]
    doc = {"checkpoint_id": checkpoint, "fingerprint": fp, "episodes": episodes}
    return ws.api.register_evaluation(doc, name=f"validate {name}").id


def _config(lrs):
    return {
        "name": "extraction lr",
        "context": {"arm": "sft"},
        "candidates": [{"values": {"lr": lr}, "evaluations": [f"lr {lr}"]} for lr in lrs],
    }


def test_the_best_candidate_on_validation_is_chosen_and_its_evaluations_are_parents(tmp_path):
    ws = Workspace(str(tmp_path / "home"))
    evals = {
        "lr 0.0001": _evaluation(ws, "a", [True, False, False, False]),
        "lr 0.001": _evaluation(ws, "b", [True, True, True, False]),
        "lr 0.01": _evaluation(ws, "c", [True, True, True, False]),  # a tie: the earlier one wins
    }
    selection = run_select(ws, "select lr", evals, _config([0.0001, 0.001, 0.01]))
    assert chosen(ws, selection) == {"lr": 0.001}
    doc = ws.api.store.open_json(selection)
    assert [row["validation_success"] for row in doc["grid"]] == [0.25, 0.75, 0.75]
    assert doc["arm"] == "sft" and doc["selected_on"] == "validation goals"
    parents = {(p.id, p.role) for p in ws.api.get(selection).parents}
    assert parents == {(e, "validation") for e in evals.values()}
    assert ws.api.get(selection).kind == "selection"
    assert run_select(ws, "select lr", evals, _config([0.0001, 0.001, 0.01])) == selection  # cached


def test_a_candidate_with_several_budgets_is_judged_on_their_mean(tmp_path):
    """The study's endpoint is the mean over its budgets: a candidate that is best only at the last
    budget loses to one that is better on average."""
    ws = Workspace(str(tmp_path / "home"))
    evals = {
        "a @ 1": _evaluation(ws, "a1", [False, False, False, False]),
        "a @ 2": _evaluation(ws, "a2", [True, True, True, True]),
        "b @ 1": _evaluation(ws, "b1", [True, True, True, False]),
        "b @ 2": _evaluation(ws, "b2", [True, True, True, False]),
    }
    config = {
        "name": "aux weight",
        "candidates": [{"values": {"w": w}, "evaluations": [f"{w} @ 1", f"{w} @ 2"]} for w in ("a", "b")],
    }
    selection = run_select(ws, "select w", evals, config)
    assert chosen(ws, selection) == {"w": "b"}
    doc = ws.api.store.open_json(selection)
    assert [row["validation_success"] for row in doc["grid"]] == [0.5, 0.75]
    assert {p.id for p in ws.api.get(selection).parents} == set(evals.values())


def test_bad_selections_are_refused_naming_the_problem(tmp_path):
    ws = Workspace(str(tmp_path / "home"))
    one = _evaluation(ws, "a", [True])
    with pytest.raises(ValueError, match=r"no input for candidate evaluation\(s\) \['lr 0.01'\]"):
        run_select(ws, "s", {"lr 0.001": one}, _config([0.001, 0.01]))
    other_protocol = _evaluation(ws, "b", [True], fp="e" * 64)
    with pytest.raises(ValueError, match="2 protocols"):
        run_select(ws, "s", {"lr 0.001": one, "lr 0.01": other_protocol}, _config([0.001, 0.01]))
    duplicate = {"name": "x", "candidates": [{"values": {"lr": 1}, "evaluations": ["e"]}] * 2}
    with pytest.raises(ValueError, match="share an evaluation label"):
        run_select(ws, "s", {"e": one}, duplicate)


def test_a_step_using_a_chosen_value_names_the_selection_as_its_parent(tmp_path):
    import torch
    from safetensors.torch import save_file

    from capvector.tasks.steps.vectors import run_merge

    ws = Workspace(str(tmp_path / "home"))
    evals = {f"α {a}": _evaluation(ws, f"m{a}", [a > 1]) for a in (0.5, 1.1)}
    candidates = [{"values": {"alpha": a}, "evaluations": [f"α {a}"]} for a in (0.5, 1.1)]
    config = {"name": "α", "candidates": candidates}
    selection = run_select(ws, "select α", evals, config)
    files = {}
    for name, value in (("base", 1.0), ("vector", 0.5)):
        save_file({"w": torch.full((2, 2), value)}, tmp_path / f"{name}.safetensors")
        files[name] = ws.api.register_file(tmp_path / f"{name}.safetensors", kind="checkpoint", name=name).id
    merged = run_merge(
        ws, "merge θ_meta", {**files, "selection α": selection}, {"alpha": chosen(ws, selection)["alpha"]}
    )
    roles = {(p.id, p.role) for p in ws.api.get(merged).parents}
    assert (selection, "selected_by") in roles and (files["vector"], "vector") in roles
    lineage = {node.id for node in ws.api.ancestors(merged)}
    assert set(evals.values()) <= lineage  # from θ_meta back to the validation runs behind α


def test_a_tie_on_validation_goes_to_the_lower_held_out_loss(tmp_path):
    ws = Workspace(tmp_path / "home")
    same = [True, False]
    inputs = {f"lr {lr}": _evaluation(ws, f"lr {lr}", same) for lr in (1e-4, 1e-3)}
    losses = {1e-4: 0.9, 1e-3: 0.4}  # the later candidate fits the held-out demonstrations better
    for lr, value in losses.items():
        inputs[f"loss {lr}"] = ws.api.register_json({"action_loss": value}, "measurement", f"loss {lr}").id
    config = _config([1e-4, 1e-3])
    for c in config["candidates"]:
        c["tiebreak"] = f"loss {c['values']['lr']}"
    selection = run_select(ws, "select lr", inputs, config)
    assert chosen(ws, selection) == {"lr": 1e-3}
    roles = ws.api.query("SELECT role FROM edges WHERE child = $c", {"c": selection})["role"].tolist()
    assert sorted(roles) == ["tiebreak", "tiebreak", "validation", "validation"]
    config["candidates"][0].pop("tiebreak")
    with pytest.raises(ValueError, match="some candidates have a tiebreak"):
        run_select(ws, "select lr", inputs, config)
