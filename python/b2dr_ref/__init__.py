"""PyTorch reference modules of the Bench2Drive-R renderer (docs/b2dr_controlnet.md).

The model classes are imported lazily, so that `b2dr_ref.dataset` (numpy + safetensors) works without torch.
"""

__all__ = ["B2DRControlNetModel", "ConfigError", "ReferenceInputs", "References"]


def __getattr__(name):
    if name in __all__:
        from . import controlnet

        return getattr(controlnet, name)
    raise AttributeError(f"module 'b2dr_ref' has no attribute {name!r}")
