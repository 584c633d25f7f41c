"""``l1_chunk``: OpenVLA-OFT-style action chunking, the default policy type.

K learned action-query tokens follow the prefix in one sequence; the backbone's final states at those
queries go through a linear head to a chunk of K actions, decoded in parallel and trained with an L1
loss in normalized action space. Parameter names: the token backbone's (see `token_backbone`) plus
``embeddings.action_queries`` and ``action_head.proj.{weight,bias}``.
"""

from __future__ import annotations

from collections.abc import Collection

import torch
import torch.nn.functional as F
from pydantic import Field

from capvector.core.policies.base import Batch, PolicyOutput, register_policy
from capvector.core.policies.token_backbone import ActionHead, TokenBackboneConfig, TokenPolicy


class L1ChunkConfig(TokenBackboneConfig):
    """The token backbone with K action queries decoded in parallel, trained with an L1 loss."""

    type: str = Field(
        "l1_chunk",
        description="registered policy type: l1_chunk (OpenVLA-OFT-style chunks, L1 loss) or flow (a "
        "flow-matching action expert); it decides which other fields exist",
    )


@register_policy("l1_chunk", L1ChunkConfig)
class L1ChunkPolicy(TokenPolicy):
    config: L1ChunkConfig

    def __init__(self, config: L1ChunkConfig):
        super().__init__(config, extra_tokens=config.chunk_size)
        self.action_head = ActionHead(config)

    def forward(self, batch: Batch) -> tuple[torch.Tensor, list[torch.Tensor]]:
        """Normalized action chunks (B, K, A) and the per-layer hidden states over all tokens."""
        x, mask = self.embed_inputs(batch)
        b = x.shape[0]
        queries = self.embeddings.action_queries.expand(b, -1, -1)
        x = torch.cat([x, queries], dim=1)
        x = x + self.embeddings.position + self.embeddings.token_type(self._type_ids)
        mask = torch.cat([mask, torch.ones(b, queries.shape[1], dtype=torch.bool, device=x.device)], dim=1)
        hidden = []
        for layer in self.backbone.layers:
            x = layer(x, mask, generator=self.generator)
            hidden.append(x)
        actions = self.action_head.proj(self.backbone.norm(x[:, -self.config.chunk_size :]))
        return actions, hidden

    def compute_loss(self, batch: Batch, features: Collection[str] = ()) -> PolicyOutput:
        predicted, hidden = self(batch)
        action = F.l1_loss(predicted, self.normalizer.normalize("action", batch["actions"]))
        return PolicyOutput(action, {"action": action}, self.prefix_features(hidden, features))

    def sample_actions(self, batch: Batch) -> torch.Tensor:
        return self(batch)[0]
