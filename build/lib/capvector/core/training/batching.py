"""Training batches from a demonstration dataset: index tables built once, batches by index.

Policies build their batcher from this (`Policy.make_batcher`), so the trainer only draws indices
(its seeded generator keeps resume exact) and never needs to know a policy's inputs.
"""

from __future__ import annotations

from collections.abc import Collection, Mapping
from typing import Any

import torch

from capvector.core.policies import tokenizer


class SampleTable:
    """Per-sample index tables: the action chunk rows (N, K) and the row `horizon` steps ahead (N,).

    Neither crosses an episode end: past it, the episode's last row repeats.
    """

    def __init__(self, tensors: Mapping[str, torch.Tensor], chunk_size: int, horizon: int | None):
        episode, step = tensors["episode"].cpu(), tensors["step"].cpu()
        n = episode.shape[0]
        new_episode = torch.ones(n, dtype=torch.bool)
        new_episode[1:] = episode[1:] != episode[:-1]
        bad = (~new_episode[1:]) & (step[1:] != step[:-1] + 1)
        if bad.any():
            i = int(bad.nonzero()[0]) + 1
            raise ValueError(
                f"dataset rows must be grouped by episode in step order; row {i} (episode {int(episode[i])}, "
                f"step {int(step[i])}) does not follow row {i - 1} (step {int(step[i - 1])})"
            )
        run = torch.cumsum(new_episode.long(), 0) - 1
        starts = new_episode.nonzero().squeeze(1)
        ends = torch.cat([starts[1:] - 1, torch.tensor([n - 1])])
        last = ends[run]
        rows = torch.arange(n)
        self.chunk = torch.minimum(rows[:, None] + torch.arange(chunk_size)[None, :], last[:, None])
        self.future = torch.minimum(rows + horizon, last) if horizon else None


def instructions(meta: Any) -> list[str]:
    """The dataset's instruction per task index (meta.instructions: a list or a task -> text map)."""
    tasks = list(meta.tasks)
    instr = meta.instructions
    if isinstance(instr, Mapping):
        missing = [t for t in tasks if t not in instr]
        if missing:
            raise ValueError(f"dataset meta has no instruction for task(s) {missing}")
        return [instr[t] for t in tasks]
    if len(instr) != len(tasks):
        raise ValueError(f"dataset meta has {len(instr)} instructions for {len(tasks)} tasks")
    return list(instr)


class DemoBatcher:
    """index (B,) -> {"tokens", <obs fields>, "actions" (B, K, A), <extra fields>[, <field>_future]}."""

    def __init__(
        self,
        dataset: Any,
        obs_fields: Collection[str],
        chunk_size: int,
        vocab_size: int,
        max_instruction_tokens: int,
        device: torch.device,
        fields: Collection[str] = (),
        horizon: int | None = None,
    ):
        tensors = dataset.tensors
        table = SampleTable(tensors, chunk_size, horizon)
        self.n = tensors["action"].shape[0]
        tokens = tokenizer.encode_batch(instructions(dataset.meta), vocab_size, max_instruction_tokens)
        self._tokens = tokens.to(device)
        self._task = tensors["task"].to(device)
        self._obs = {k: tensors[k].to(device) for k in obs_fields}
        self._action = tensors["action"].to(device)
        self._chunk = table.chunk.to(device)
        self._extra = {k: tensors[k].to(device) for k in fields}
        self._future = table.future.to(device) if table.future is not None else None

    def __call__(self, idx: torch.Tensor) -> dict[str, torch.Tensor]:
        idx = idx.to(self._action.device)
        batch = {"tokens": self._tokens[self._task[idx]], "actions": self._action[self._chunk[idx]]}
        batch.update({k: v[idx] for k, v in self._obs.items()})
        for k, v in self._extra.items():
            batch[k] = v[idx]
            if self._future is not None:
                batch[f"{k}_future"] = v[self._future[idx]]
        return batch
