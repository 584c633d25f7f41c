"""A policy type from outside capvector_core: an MLP over state, proprio and a bag of instruction words.

It exists to prove the plugin path: registered through the `capvector.policies` entry point (see the
dist-info beside this package), it is trained, merged, regularized and evaluated by `capvector run`
with nothing in capvector changed. It uses only the public interface (`capvector.core.policies.base`) and
the shared batching helper.
"""

from __future__ import annotations

from collections.abc import Collection, Mapping

import numpy as np
import torch
import torch.nn.functional as F
from pydantic import Field
from torch import nn

from capvector.core.policies import tokenizer
from capvector.core.policies.base import FeatureSpec, Policy, PolicyConfig, PolicyOutput, register_policy
from capvector.core.training.batching import DemoBatcher


class MLPConfig(PolicyConfig):
    type: str = "mlp"
    hidden: int = Field(64, gt=0)
    n_layers: int = Field(2, gt=0)
    chunk_size: int = Field(4, gt=0)
    vocab_size: int = 128


@register_policy("mlp", MLPConfig)
class MLPPolicy(Policy):
    config: MLPConfig

    def __init__(self, config: MLPConfig):
        super().__init__(config)
        if config.obs_mode != "state":
            raise ValueError("the mlp policy reads the state vector only (obs_mode=state)")
        self.words = nn.EmbeddingBag(config.vocab_size, config.hidden, mode="mean", padding_idx=0)
        self.inputs = nn.Linear(39 + 4, config.hidden)
        self.layers = nn.ModuleList(nn.Linear(config.hidden, config.hidden) for _ in range(config.n_layers))
        self.head = nn.Linear(config.hidden, config.chunk_size * 4)
        for key, dim in (("obs", 43), ("action", 4)):
            self.register_buffer(f"{key}_mean", torch.zeros(dim))
            self.register_buffer(f"{key}_std", torch.ones(dim))
        self.register_buffer("fitted", torch.zeros(()))

    def required_fields(self) -> list[str]:
        return ["state", "proprio", "action", "episode", "step", "task"]

    @property
    def normalizer_fitted(self) -> bool:
        return bool(self.fitted)

    def fit_normalizer(self, tensors: Mapping[str, torch.Tensor]) -> None:
        obs = torch.cat([tensors["state"], tensors["proprio"]], dim=1).double()
        self.obs_mean.copy_(obs.mean(0).float())
        self.obs_std.copy_(obs.std(0).clamp_min(1e-2).float())
        self.action_mean.copy_(tensors["action"].double().mean(0).float())
        self.action_std.copy_(tensors["action"].double().std(0).clamp_min(1e-2).float())
        self.fitted.fill_(1.0)

    def make_batcher(self, dataset, device, fields: Collection[str] = (), horizon: int | None = None):
        batcher = DemoBatcher(
            dataset,
            ["state", "proprio"],
            self.config.chunk_size,
            self.config.vocab_size,
            12,
            device,
            fields,
            horizon,
        )
        return batcher.n, batcher

    def feature_specs(self) -> dict[str, FeatureSpec]:
        return {"tokens": FeatureSpec(self.config.n_layers, self.config.hidden, 1)}

    def _forward(self, batch) -> tuple[torch.Tensor, list[torch.Tensor]]:
        obs = (torch.cat([batch["state"], batch["proprio"]], dim=1) - self.obs_mean) / self.obs_std
        x = F.gelu(self.inputs(obs) + self.words(batch["tokens"]))
        hidden = []
        for layer in self.layers:
            x = x + F.gelu(layer(x))
            hidden.append(x[:, None])
        return self.head(x).view(-1, self.config.chunk_size, 4), hidden

    def compute_loss(self, batch, features: Collection[str] = ()) -> PolicyOutput:
        predicted, hidden = self._forward(batch)
        loss = F.l1_loss(predicted, (batch["actions"] - self.action_mean) / self.action_std)
        return PolicyOutput(loss, {"action": loss}, {"tokens": hidden} if "tokens" in features else {})

    @torch.no_grad()
    def predict_action_chunk(self, obs, task_names: list[str]) -> np.ndarray:
        from capvector.core.simulation.metaworld_tasks import INSTRUCTIONS

        tokens = tokenizer.encode_batch([INSTRUCTIONS[t] for t in task_names], self.config.vocab_size, 12)
        batch = {k: torch.as_tensor(np.asarray(obs[k])).to(self.device) for k in ("state", "proprio")}
        predicted, _ = self._forward({**batch, "tokens": tokens.to(self.device)})
        actions = predicted * self.action_std + self.action_mean
        return actions.clamp(-1.0, 1.0).cpu().numpy().astype(np.float32)
