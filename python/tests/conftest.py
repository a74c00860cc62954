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
