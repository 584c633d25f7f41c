"""The built-in policy types; importing this package registers them (see `capvector_core.policy`)."""

from capvector_core.policies.flow import FlowConfig, FlowPolicy
from capvector_core.policies.l1_chunk import L1ChunkConfig, L1ChunkPolicy

__all__ = ["FlowConfig", "FlowPolicy", "L1ChunkConfig", "L1ChunkPolicy"]
