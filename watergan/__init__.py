"""watergan: learning and physics for underwater survey colour correction."""

__version__ = "0.1.0"
