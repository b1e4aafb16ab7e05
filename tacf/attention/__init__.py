"""The three attentions of TACF: contextual (CA), dimensional (DA) and spatiotemporal (SA)."""
from tacf.attention.contextual import ContextualAttention, context_offsets, pme
from tacf.attention.dimensional import DimensionalAttention
from tacf.attention.spatiotemporal import SpatiotemporalAttention

__all__ = ["ContextualAttention", "DimensionalAttention", "SpatiotemporalAttention", "context_offsets", "pme"]
