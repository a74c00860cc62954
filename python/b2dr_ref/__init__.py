"""PyTorch reference modules of the Bench2Drive-R renderer (docs/b2dr_controlnet.md)."""

from .controlnet import B2DRControlNetModel, ConfigError, ReferenceInputs, References  # noqa: F401

__all__ = ["B2DRControlNetModel", "ConfigError", "ReferenceInputs", "References"]
