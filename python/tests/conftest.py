import importlib.util
import os
import sys

import pytest
import torch

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
torch.set_num_threads(1)


@pytest.fixture
def models():
    from b2dr_ref.testing import build_models

    return build_models(seed=0, nontrivial=True)


@pytest.fixture(scope="session")
def tool():
    """A developer script of tools/ as a module: tool("vae_ceiling") loads tools/vae_ceiling.py."""
    root = os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "..")

    def load(name):
        spec = importlib.util.spec_from_file_location(name, os.path.join(root, "tools", f"{name}.py"))
        m = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(m)
        return m

    return load
