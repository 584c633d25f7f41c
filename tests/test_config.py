"""Pipeline configuration: presets validate, overrides are checked key by key."""

import re

import pytest
from pydantic import ValidationError

from capvector.flows.recipe.config import ARMS, PipelineConfig, load_config
from capvector.flows.recipe.overrides import ConfigKeyError


@pytest.mark.parametrize("preset", ["smoke", "quick", "hard", "paper", "paper-cpu"])
def test_presets_validate(preset):
    config = load_config(preset)
    assert config.splits.downstream
    assert not set(config.splits.downstream) & (set(config.splits.pretrain) | set(config.splits.extraction))
    assert all(arm in ARMS for arm in config.arms)


def test_override_sets_nested_value_with_its_type():
    config = load_config("smoke", ["downstream.steps=7", "alpha=0.5", "arms=[sft, capvector]"])
    assert config.downstream.steps == 7
    assert config.alpha == 0.5
    assert config.arms == ["sft", "capvector"]


def test_unknown_key_names_the_key_and_suggests():
    with pytest.raises(ConfigKeyError, match=r"'pretrain.stepz'.*did you mean 'pretrain.steps'"):
        load_config("smoke", ["pretrain.stepz=3"])


def test_key_below_a_leaf_is_refused():
    with pytest.raises(ConfigKeyError, match="'alpha' has no sub-keys"):
        load_config("smoke", ["alpha.x=1"])


def test_wrong_type_names_the_field():
    with pytest.raises(ValidationError, match=r"downstream\.steps"):
        load_config("smoke", ["downstream.steps=many"])


def test_unknown_preset_lists_known():
    with pytest.raises(ValueError, match="known presets: .*smoke"):
        load_config("nope")


def test_downstream_tasks_must_be_new():
    data = load_config("smoke").model_dump()
    data["splits"]["downstream"] = list(data["splits"]["extraction"])
    with pytest.raises(ValidationError, match="shares task"):
        PipelineConfig.model_validate(data)


def test_policy_and_data_modes_must_agree():
    with pytest.raises(ValidationError, match="obs_mode"):
        load_config("smoke", ["data.obs_mode=pixels"])


def test_override_below_a_defaulted_section_keeps_its_other_defaults():
    config = load_config("smoke", ["lora_sp.bank_size=16"])
    assert config.lora_sp.bank_size == 16
    assert config.lora_sp.target_modules == PipelineConfig.model_fields["lora_sp"].default.target_modules


def test_adapter_lr_applies_to_adapter_arms_only():
    config = load_config("smoke", ["adapter_lr=3e-3", "arms=[sft, sft_lora, capvector_lora_sp]"])
    assert config.downstream_step("sft", 0).train.lr == config.downstream.lr != 3e-3
    assert config.downstream_step("sft_lora", 0).train.lr == 3e-3
    assert config.downstream_step("capvector_lora_sp", 0).train.lr == 3e-3
    default = load_config("smoke")
    assert default.downstream_step("sft_lora", 0).train.lr == default.downstream.lr
    with pytest.raises(ValidationError, match="adapter_lr"):
        load_config("smoke", ["adapter_lr=0"])


def test_ood_camera_changes_only_the_camera_of_the_test_protocol():
    config = load_config("paper-cpu", ["evaluation.ood_camera=corner3"])
    test, ood = config.eval_config(), config.eval_config(camera="corner3")
    assert (test.camera, ood.camera) == ("corner2", "corner3")
    assert test.model_dump(exclude={"camera"}) == ood.model_dump(exclude={"camera"})


@pytest.mark.parametrize(
    ("preset", "camera", "message"),
    [
        ("paper-cpu", "corner9", "unknown camera 'corner9'"),
        ("paper-cpu", "corner2", r"camera other than data.camera \(corner2\)"),
        ("smoke", "corner3", "needs pixels observations"),
    ],
)
def test_bad_ood_camera_is_refused_with_the_reason(preset, camera, message):
    with pytest.raises(ValidationError, match=message):
        load_config(preset, [f"evaluation.ood_camera={camera}"])


def test_policy_type_override_checks_keys_against_that_type():
    config = load_config("smoke", ["policy.type=flow", "policy.integration_steps=5"])
    assert config.policy.type == "flow" and config.policy.integration_steps == 5
    assert config.policy.d_model == 32  # the preset's backbone settings carry over
    step = config.pretrain_step().model_dump(mode="json")
    assert step["policy"]["integration_steps"] == 5  # the cache key sees every field of the type
    with pytest.raises(ConfigKeyError, match=r"'policy.integration_steps'.*known here: .*d_model"):
        load_config("smoke", ["policy.integration_steps=5"])  # an l1_chunk policy has no such field
    with pytest.raises(ValueError, match=r"unknown policy type 'pi0'; known: \['flow', 'l1_chunk'"):
        load_config("smoke", ["policy.type=pi0"])


def test_switching_policy_type_drops_settings_the_new_type_lacks(monkeypatch):
    monkeypatch.syspath_prepend(str(__import__("conftest").REPO / "tests" / "policy_plugin"))
    monkeypatch.setattr("capvector.core.policies.base._entry_points_loaded", False)
    with pytest.warns(UserWarning, match=r"policy.type=mlp: d_model, n_heads do not apply"):
        config = load_config("smoke", ["policy.type=mlp", "policy.hidden=16"])
    assert config.policy.type == "mlp" and config.policy.hidden == 16 and config.policy.n_layers == 2


# ---------------------------------------------------------------------------- NaN and Inf
@pytest.mark.parametrize(
    ("override", "field"),
    [
        ("alpha=.nan", "alpha"),
        ("alpha=nan", "alpha"),  # a string that float() would take
        ("alpha=-.inf", "alpha"),
        ("adapter_lr=.inf", "adapter_lr"),
        ("sweep.alphas=[0.5, .nan]", "sweep.alphas.1"),
        ("sweep.lambdas_absolute=[.inf]", "sweep.lambdas_absolute.0"),
        ("orthogonal.lambda_absolute=.nan", "orthogonal.lambda_absolute"),
        ("orthogonal.lambda_relative=.inf", "orthogonal.lambda_relative"),
        ("aux.weight=.inf", "aux.weight"),
        ("downstream.lr=.inf", "downstream.lr"),
        ("pretrain.weight_decay=.inf", "pretrain.weight_decay"),
        ("extraction.grad_clip=.inf", "extraction.grad_clip"),
        ("lora.alpha=.nan", "lora.alpha"),
        ("lora_sp.alpha=.inf", "lora_sp.alpha"),
        ("lora_sp.spectral_weight=.nan", "lora_sp.spectral_weight"),
        ("lora_sp.router_weight=-.inf", "lora_sp.router_weight"),
    ],
)
def test_nan_and_inf_are_refused_at_validation_naming_the_field(override, field):
    """Before any step runs (NaN α used to fail only after training, in the merge)."""
    with pytest.raises(ValidationError, match=rf"(?m)^{re.escape(field)}\n.*finite number"):
        load_config("smoke", [override])


def test_step_configs_refuse_nan_and_inf():
    from capvector.core.adapters.lora import LoraConfig
    from capvector.core.adapters.lora_sp import LoraSPConfig
    from capvector.core.training.trainer import AuxConfig, TrainConfig
    from capvector.tasks.steps.training import OrthogonalSettings
    from capvector.tasks.steps.vectors import MergeConfig

    nan, inf = float("nan"), float("inf")
    cases = [
        (MergeConfig, {"alpha": nan}, "alpha"),
        (OrthogonalSettings, {"lambda_absolute": inf}, "lambda_absolute"),
        (OrthogonalSettings, {"lambda_relative": nan}, "lambda_relative"),
        (AuxConfig, {"name": "dynamics", "weight": inf}, "weight"),
        (TrainConfig, {"lr": inf}, "lr"),
        (TrainConfig, {"min_lr_ratio": nan}, "min_lr_ratio"),
        (LoraConfig, {"target_modules": ["q"], "alpha": inf}, "alpha"),
        (LoraSPConfig, {"target_modules": ["q"], "router_weight": nan}, "router_weight"),
    ]
    for model, data, field in cases:
        with pytest.raises(ValidationError, match=rf"(?m)^{field}\n.*finite number"):
            model.model_validate(data)


# ---------------------------------------------------------------------------- policy configs
@pytest.mark.parametrize(
    ("overrides", "field"),
    [
        (["policy.type=flow", "policy.time_beta=[.nan, 1.0]"], "policy.time_beta.0"),
        (["policy.type=flow", "policy.time_beta=[1.5, .inf]"], "policy.time_beta.1"),
        (["policy.dropout=.nan"], "policy.dropout"),
        (["policy.type=flow", "policy.dropout=.nan"], "policy.dropout"),
    ],
)
def test_policy_configs_refuse_nan_and_inf_naming_the_field(overrides, field):
    """NaN in the flow policy's time_beta used to load and fail only in training (torch's Beta)."""
    with pytest.raises(ValidationError, match=rf"(?m)^{re.escape(field)}\n.*finite number"):
        load_config("smoke", overrides)


def test_policy_configs_refuse_nan_and_inf_directly():
    from capvector.core.policies.flow_matching import FlowConfig
    from capvector.core.policies.l1_chunk import L1ChunkConfig

    for model, data, field in [
        (FlowConfig, {"time_beta": (float("nan"), 1.0)}, "time_beta.0"),
        (FlowConfig, {"dropout": float("inf")}, "dropout"),
        (L1ChunkConfig, {"dropout": float("nan")}, "dropout"),
    ]:
        with pytest.raises(ValidationError, match=rf"(?m)^{re.escape(field)}\n.*finite number"):
            model.model_validate(data)
    with pytest.raises(ValidationError, match=r"time_beta\.1\n.*greater than 0"):
        FlowConfig(time_beta=(1.5, 0.0))  # Beta(a, 0) is no distribution


def test_policy_type_override_is_independent_of_order():
    a = load_config("smoke", ["policy.type=flow", "policy.integration_steps=5"])
    b = load_config("smoke", ["policy.integration_steps=5", "policy.type=flow"])
    assert b.policy.type == "flow" and b.policy.integration_steps == 5 and a == b


def _flow_preset(tmp_path):
    text = (__import__("conftest").REPO / "flows" / "presets" / "smoke.yaml").read_text()
    assert "\npolicy: {" in text
    path = tmp_path / "smoke-flow.yaml"
    path.write_text(
        text.replace("\npolicy: {", "\npolicy: {type: flow, integration_steps: 3, time_beta: [2.0, 1.0], ")
    )
    return path


def test_switching_a_flow_preset_back_to_l1_chunk_drops_the_flow_keys(tmp_path):
    path = _flow_preset(tmp_path)
    assert load_config(str(path)).policy.integration_steps == 3
    for overrides in (
        ["policy.type=l1_chunk"],
        ["policy.type=l1_chunk", "policy.d_model=64"],
        ["policy.d_model=64", "policy.type=l1_chunk"],
    ):
        with pytest.warns(
            UserWarning, match=r"policy.type=l1_chunk: integration_steps, time_beta do not apply"
        ):
            config = load_config(str(path), overrides)
        assert config.policy.type == "l1_chunk" and config.policy.n_layers == 2
        assert config.policy.d_model == (64 if len(overrides) == 2 else 32)
    # A flow key set on the command line is checked against the final type, in either order.
    for overrides in (
        ["policy.type=l1_chunk", "policy.integration_steps=5"],
        ["policy.integration_steps=5", "policy.type=l1_chunk"],
    ):
        with (
            pytest.warns(UserWarning, match="were dropped"),
            pytest.raises(ConfigKeyError, match=r"'policy.in"),
        ):
            load_config(str(path), overrides)


def test_a_pipeline_and_a_study_share_the_recipes_settings_and_differ_only_in_what_each_adds():
    from capvector.flows.recipe.config import RecipeSettings
    from capvector.flows.study.config import StudyConfig

    shared = set(RecipeSettings.model_fields)
    assert set(PipelineConfig.model_fields) - shared == {"alpha", "arms", "sweep"}
    assert set(StudyConfig.model_fields) - shared == {"study"}
    assert {"orthogonal", "seeds", "evaluation", "splits"} <= shared


@pytest.mark.parametrize("field, value", [("alpha", 1.1), ("arms", ["sft", "capvector"]), ("sweep", {})])
def test_a_study_preset_that_sets_what_only_a_pipeline_takes_is_refused_naming_it(tmp_path, field, value):
    """A study chooses α from study.alphas, compares study.arms and has no sweep grid: a preset that sets
    them at top level would be silently ignored, so it is refused."""
    import yaml

    from capvector.flows.recipe.config import PRESET_DIR
    from capvector.flows.study.config import load_study

    data = yaml.safe_load((PRESET_DIR / "study-smoke.yaml").read_text())
    preset = tmp_path / "study-with-a-pipeline-field.yaml"
    preset.write_text(yaml.safe_dump({**data, field: value}))
    with pytest.raises(ValidationError) as refused:
        load_study(str(preset))
    (error,) = refused.value.errors()
    assert error["loc"] == (field,) and error["type"] == "extra_forbidden"
    assert re.search(rf"^{field}\n  Extra inputs are not permitted", str(refused.value), re.M)
    load_study("study-smoke")  # the preset itself loads
