"""Random frame inputs for the tiny test config."""

import torch

from b2dr_ref.pe import location_sizes


def frame_inputs(controlnet, n=1, h=7, w=13, seed=0, factor=8):
    g = torch.Generator().manual_seed(seed)
    cfg = controlnet.config
    d3 = 3 * cfg.pe_depth_num
    sizes = location_sizes(cfg.ref_attn, len(cfg.block_out_channels), (h, w))
    H, W = h * factor, w * factor
    return dict(
        x_T=torch.randn((n, 4, h, w), generator=g),
        context=torch.randn((77, cfg.cross_attention_dim), generator=g),
        masks=(torch.rand((n, 15, H, W), generator=g) > 0.7).float(),
        prev=torch.rand((n, 3, H, W), generator=g),
        eps_prev=torch.randn((n, 4, h, w), generator=g),
        ref_images=torch.rand((n, 2, 3, H, W), generator=g),
        pe_cur=[torch.randn((n, d3) + s, generator=g) * 3 for s in sizes],
        pe_ref=[torch.randn((n, 2, d3) + s, generator=g) * 3 for s in sizes],
    )
