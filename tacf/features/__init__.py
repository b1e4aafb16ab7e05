"""Feature extractors: fHOG (31 channels) and Color Names (11 channels), both channel-first float32."""
from .colornames import color_names
from .fhog import fhog

__all__ = ["color_names", "fhog"]
