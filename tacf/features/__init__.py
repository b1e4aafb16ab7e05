"""Feature extractors: fHOG (31 channels) and Color Names (11 channels), both channel-first float32."""
from .colornames import color_names
from .fhog import fhog, fhog_batch

__all__ = ["color_names", "fhog", "fhog_batch"]
