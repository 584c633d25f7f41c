"""Settings that say where or how fast a step runs, never what it computes: not part of its cache key.

A config field is marked by `ExecutionOnly` in its annotation, on the model that declares it (the one
place that says so); `result_config` dumps a config without the marked fields, and a step's content
key (capvector.tasks.runtime.caching) hashes that dump. The fields marked now, and why each cannot change the
result:

- `TrainConfig.device` (where the run trains) and `TrainConfig.num_threads` (torch CPU threads): the
  same run on a CPU, a GPU or with another thread count computes the same thing, up to float rounding
  (the order of reductions differs). That rounding is accepted: with `device: auto` the key could
  never tell a CPU- from a GPU-trained run anyway, and asking for `cuda:0` (a cluster placing a step
  on a GPU) must not make a cached run a miss. What a run actually used goes into the checkpoint's
  record instead (`config.execution`: the resolved device, GPU name, thread count, torch and CUDA).
- `TrainConfig.checkpoint_every` and `TrainConfig.keep_checkpoints`: how often resumable checkpoints
  are written and how many stay on disk. Resume is exact (capvector.core.training.trainer), so the weights
  are the same bit for bit whatever they are.
- `DemoConfig.workers`: processes recording demonstrations; the units are merged in (task, unit)
  order, so the dataset and its hash do not depend on it (tests/test_demos.py).
- `EvalConfig.batch_size`: environments stepped together; every episode's record is the one a
  one-env-at-a-time loop gives (tests/test_evaluation.py), and it is not in the protocol fingerprint.

Kept in the key on purpose: `TrainConfig.log_every` (the loss-curve rows and `final_loss` in the
checkpoint's record depend on it), `EvalConfig.record_video` and `EvalConfig.video_size` (they
register video artifacts), every seed, and everything else.

A field left out of the key is still in the config a step is given and in the record it registers (the
record of the run that computed the artifact: a later hit asked with another device gets that one).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from pydantic import BaseModel
from pydantic.fields import FieldInfo


@dataclass(frozen=True)
class ExecutionOnly:
    """Annotation marker (`Annotated[int, ExecutionOnly("why")]`): the field says where or how fast a
    step runs and is left out of its cache key. `why`: why it cannot change the step's result."""

    why: str


def is_execution_only(field: FieldInfo) -> bool:
    return any(isinstance(m, ExecutionOnly) for m in field.metadata)


def execution_only_fields(model: type[BaseModel]) -> dict[str, str]:
    """Name -> why, for the fields of `model` itself (not of the models nested in it) marked ExecutionOnly."""
    return {
        name: next(m.why for m in field.metadata if isinstance(m, ExecutionOnly))
        for name, field in model.model_fields.items()
        if is_execution_only(field)
    }


def result_config(config: BaseModel) -> dict[str, Any]:
    """`config.model_dump(mode="json")` without its ExecutionOnly fields, at any depth (nested models,
    lists and dicts of them): what the result of a step with this config depends on."""
    return _prune(config, config.model_dump(mode="json"))


def _prune(value: Any, dumped: Any) -> Any:
    if isinstance(value, BaseModel) and isinstance(dumped, dict):
        out = dict(dumped)
        for name, field in type(value).model_fields.items():
            key = field.serialization_alias or name
            if key not in out:  # left out by the model's own serializer
                continue
            if is_execution_only(field):
                del out[key]
            else:
                out[key] = _prune(getattr(value, name), out[key])
        return out
    if isinstance(value, list | tuple) and isinstance(dumped, list) and len(value) == len(dumped):
        return [_prune(v, d) for v, d in zip(value, dumped, strict=True)]
    if isinstance(value, dict) and isinstance(dumped, dict):
        by_key = {str(k): v for k, v in value.items()}
        return {k: _prune(by_key[k], d) if k in by_key else d for k, d in dumped.items()}
    return dumped
