"""The built-in policy types; importing this package registers them (see `capvector.core.policies.base`)."""

from capvector.core.policies.flow_matching import FlowConfig, FlowPolicy
from capvector.core.policies.l1_chunk import L1ChunkConfig, L1ChunkPolicy

__all__ = ["FlowConfig", "FlowPolicy", "L1ChunkConfig", "L1ChunkPolicy"]
