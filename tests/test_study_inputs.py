"""The analysis reads its inputs back as the typed keys the flow wrote them with: a key round-trips,
and a malformed or unknown one is an error naming it rather than a silently mis-split row."""

from __future__ import annotations

import pytest

from capvector.tasks.study_inputs import HeldOutLoss, Selection, TestEvaluation, inputs_of


def test_a_key_round_trips_through_its_text():
    key = TestEvaluation(arm="sft_from_ao", draw=-1, seed=3, budget=200)
    assert key.key == "test/sft_from_ao/-1/3/200"
    assert TestEvaluation.parse(key.key) == key
    assert Selection.parse(Selection(name="α and λ / weight").key).name == "α and λ / weight"


def test_inputs_of_one_kind_come_back_typed_and_in_key_order():
    inputs = {
        HeldOutLoss(which="standard", draw=1, budget=400).key: "m2",
        TestEvaluation(arm="sft", draw=-1, seed=0, budget=50).key: "e1",
        HeldOutLoss(which="auxiliary", draw=0, budget=200).key: "m1",
    }
    losses = inputs_of(inputs, HeldOutLoss)
    assert [(k.which, k.draw, k.budget, v) for k, v in losses] == [
        ("auxiliary", 0, 200, "m1"),
        ("standard", 1, 400, "m2"),
    ]


@pytest.mark.parametrize(
    ("key", "needles"),
    [
        ("test/sft/x/0/50", ["test/sft/x/0/50", "test/<arm>/<draw>/<seed>/<budget>", "draw"]),
        ("test/sft/-1/0", ["test/sft/-1/0", "3 parts"]),
    ],
)
def test_a_malformed_key_names_itself_and_the_expected_shape(key, needles):
    with pytest.raises(ValueError) as err:
        inputs_of({key: "e"}, TestEvaluation)
    assert all(n in str(err.value) for n in needles), err.value


def test_an_input_of_no_known_kind_is_named():
    with pytest.raises(ValueError, match="tset/sft/-1/0/50"):
        inputs_of({"tset/sft/-1/0/50": "e"}, TestEvaluation)
