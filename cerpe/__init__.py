"""CERPE: communication-efficient multi-robot relative pose estimation."""
__version__ = "0.1.0"
