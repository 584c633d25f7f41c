"""``flow``: a π0-style policy, a flow-matching action expert beside the token backbone.

The backbone runs over the prefix only (language, obs, proprio). A separate action expert, with its
own weights and as many layers as the backbone, processes K action tokens; at layer i they attend to
their own keys/values and to the prefix's keys/values computed by backbone layer i's own projections
(π0's shared attention with a block mask: the prefix never attends to the actions).

Training (π0's conditional flow matching, in normalized action space): τ ~ Beta(1.5, 1) scaled to
[0.001, 1], ε ~ N(0, I), x_τ = τ·ε + (1 − τ)·a, target velocity u = ε − a, loss = MSE(v_θ(x_τ, τ), u).
τ, ε and dropout masks are drawn from the policy's `generator` (the trainer's per-run one), so an
auxiliary head's initialisation or anything else using torch's global RNG leaves them unchanged.
Inference integrates dx/dτ = v from τ = 1 (noise) to 0 with `integration_steps` Euler steps; the
prefix keys/values are computed once per call. The noise is one fixed draw (`inference_seed`), so an
evaluation is deterministic and does not depend on how episodes are batched.

Parameter names: the token backbone's plus::

    action_expert.action_in.{weight,bias}          action_expert.time_mlp_{in,out}.{weight,bias}
    action_expert.position                         action_expert.norm.*
    action_expert.layers.<i>.{norm1,norm2}.*       action_expert.layers.<i>.attn.{q,k,v,o}_proj.*
    action_expert.layers.<i>.mlp.{fc1,fc2}.*       action_head.proj.{weight,bias}   (the velocity)
"""

from __future__ import annotations

import math
from collections.abc import Collection

import torch
import torch.nn.functional as F
from pydantic import Field, PositiveFloat
from torch import nn

from capvector.core.policies.base import Batch, PolicyOutput, register_policy
from capvector.core.policies.token_backbone import ActionHead, Block, TokenBackboneConfig, TokenPolicy


class FlowConfig(TokenBackboneConfig):
    """The token backbone with a flow-matching action expert (noise to action chunks)."""

    type: str = Field(
        "flow",
        description="registered policy type: flow (a flow-matching action expert) or l1_chunk "
        "(OpenVLA-OFT-style chunks, L1 loss); it decides which other fields exist",
    )
    integration_steps: int = Field(10, gt=0, description="Euler steps from noise to actions at inference")
    inference_seed: int = Field(
        0, description="seed of the one fixed noise draw actions start from at inference (deterministic)"
    )
    time_beta: tuple[PositiveFloat, PositiveFloat] = Field(
        (1.5, 1.0), description="Beta(a, b) for the training time τ (finite, > 0)"
    )


def time_embedding(
    t: torch.Tensor, dim: int, min_period: float = 4e-3, max_period: float = 4.0
) -> torch.Tensor:
    """π0's sine-cosine embedding of τ ∈ [0, 1] (B,) -> (B, dim)."""
    fraction = torch.linspace(0.0, 1.0, dim // 2, device=t.device, dtype=torch.float32)
    period = min_period * (max_period / min_period) ** fraction
    angle = t.float()[:, None] * (2 * math.pi / period)[None, :]
    return torch.cat([angle.sin(), angle.cos()], dim=-1)


class ActionExpert(nn.Module):
    def __init__(self, config: FlowConfig):
        super().__init__()
        d = config.d_model
        self.action_in = nn.Linear(config.action_dim, d)
        self.time_mlp_in = nn.Linear(2 * d, d)
        self.time_mlp_out = nn.Linear(d, d)
        self.position = nn.Parameter(torch.randn(config.chunk_size, d) * 0.02)
        self.layers = nn.ModuleList(Block(config) for _ in range(config.n_layers))
        self.norm = nn.LayerNorm(d)


@register_policy("flow", FlowConfig)
class FlowPolicy(TokenPolicy):
    config: FlowConfig

    def __init__(self, config: FlowConfig):
        super().__init__(config)
        self.action_expert = ActionExpert(config)
        self.action_head = ActionHead(config)

    def encode_prefix(self, batch: Batch) -> tuple[list[torch.Tensor], list[tuple], torch.Tensor]:
        """Per-layer prefix states, per-layer prefix keys/values (for the expert) and the key mask."""
        x, mask = self.embed_inputs(batch)
        x = x + self.embeddings.position + self.embeddings.token_type(self._type_ids)
        hidden, kv = [], []
        for layer in self.backbone.layers:
            kv.append(layer.attn.keys_values(layer.norm1(x)))
            x = layer(x, mask, generator=self.generator)
            hidden.append(x)
        return hidden, kv, mask

    def velocity(
        self, x_t: torch.Tensor, t: torch.Tensor, kv: list[tuple], mask: torch.Tensor
    ) -> torch.Tensor:
        """v_θ(x_τ, τ) (B, K, A) given the prefix keys/values."""
        expert = self.action_expert
        d = self.config.d_model
        tau = time_embedding(t, d)[:, None].expand(-1, x_t.shape[1], -1)
        a = expert.time_mlp_in(torch.cat([expert.action_in(x_t), tau], dim=-1))
        a = expert.time_mlp_out(F.silu(a)) + expert.position
        full_mask = torch.cat([mask, torch.ones(a.shape[:2], dtype=torch.bool, device=a.device)], dim=1)
        for layer, prefix_kv in zip(expert.layers, kv, strict=True):
            a = layer(a, full_mask, prefix_kv, generator=self.generator)
        return self.action_head.proj(expert.norm(a))

    def compute_loss(self, batch: Batch, features: Collection[str] = ()) -> PolicyOutput:
        hidden, kv, mask = self.encode_prefix(batch)
        actions = self.normalizer.normalize("action", batch["actions"])
        t, noise = self.sample_time_and_noise(actions)
        x_t = t[:, None, None] * noise + (1.0 - t[:, None, None]) * actions
        flow = F.mse_loss(self.velocity(x_t, t, kv, mask), noise - actions)
        return PolicyOutput(flow, {"action": flow}, self.prefix_features(hidden, features))

    def sample_time_and_noise(self, actions: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Training's τ (B,) and ε (like `actions`), from `self.generator` (on the policy's device);
        without one, from torch's global RNG (τ on the CPU, ε on the actions' device)."""
        generator = self.generator
        device = generator.device if generator is not None else torch.device("cpu")
        concentration = torch.tensor(self.config.time_beta, device=device)  # [a, b]: Beta(a, b)
        # Beta(a, b) = the first coordinate of Dirichlet([a, b]): torch.distributions.Beta's own
        # sampler, which takes no generator
        beta = torch._sample_dirichlet(concentration.expand(actions.shape[0], 2), generator=generator)
        t = beta[:, 0].to(actions.device) * 0.999 + 0.001
        noise = torch.randn(actions.shape, generator=generator, dtype=actions.dtype, device=actions.device)
        return t, noise

    def sample_actions(self, batch: Batch) -> torch.Tensor:
        _, kv, mask = self.encode_prefix(batch)
        cfg = self.config
        b = mask.shape[0]
        generator = torch.Generator().manual_seed(cfg.inference_seed)
        x = torch.randn(cfg.chunk_size, cfg.action_dim, generator=generator).to(mask.device)
        x = x.expand(b, -1, -1).contiguous()
        dt = 1.0 / cfg.integration_steps
        for i in range(cfg.integration_steps):
            t = torch.full((b,), 1.0 - i * dt, device=x.device)
            x = x - dt * self.velocity(x, t, kv, mask)
        return x
