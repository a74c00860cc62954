#!/usr/bin/env python3
"""SD1.5-size B2D-R: parameter counts, FLOPs and saved-activation bytes per camera sample at 224x400, on the meta
device (nothing allocated). Used for docs/training.md "At the paper's scale" (an ESTIMATE).

    cd python && PYTHONPATH=. python ../tools/estimate_sd15.py
"""
import torch
from torch.utils.flop_counter import FlopCounterMode
from diffusers import UNet2DConditionModel, AutoencoderKL
from b2dr_ref.controlnet import B2DRControlNetModel
from b2dr_ref.pe import location_sizes

torch.set_num_threads(1)
H, W = 224, 400
h, w = H // 8, W // 8
with torch.device("meta"):
    unet = UNet2DConditionModel(cross_attention_dim=768, sample_size=64)
    cn = B2DRControlNetModel(cross_attention_dim=768)  # SD1.5 defaults + B2D-R (15 masks, PE 64 bins, refs)
    vae = AutoencoderKL(block_out_channels=[128, 256, 512, 512], down_block_types=["DownEncoderBlock2D"] * 4,
                        up_block_types=["UpDecoderBlock2D"] * 4, layers_per_block=2, latent_channels=4)
n = lambda m: sum(p.numel() for p in m.parameters())
b2dr_parts = sum(p.numel() for k, p in cn.named_parameters() if k.startswith(("ref_encoder", "ref_attn", "pos_embed", "noise_embedding")))
print(f"params: unet {n(unet)/1e6:.1f} M, controlnet {n(cn)/1e6:.1f} M (B2D-R parts {b2dr_parts/1e6:.1f} M), vae {n(vae)/1e6:.1f} M (encoder {n(vae.encoder)/1e6:.1f} M)")
cfg = cn.config
d3 = 3 * cfg.pe_depth_num
sizes = location_sizes(cfg.ref_attn, 4, (h, w))
B = 1
def inputs():
    return dict(x=torch.randn(B, 4, h, w, device="meta"), t=torch.tensor([500] * B, device="meta"),
                ctx=torch.randn(B, 77, 768, device="meta"), masks=torch.randn(B, 15, H, W, device="meta"),
                z=torch.randn(B, 4, h, w, device="meta"), nl=torch.tensor([200] * B, device="meta"),
                refl=torch.randn(B, 2, 4, h, w, device="meta"),
                pc=[torch.randn(B, d3, *s, device="meta") for s in sizes],
                pr=[torch.randn(B, 2, d3, *s, device="meta") for s in sizes])

def fwd(i):
    refs = cn.prepare_references(i["refl"], i["pc"], i["pr"])
    down, mid = cn(i["x"], i["t"], i["ctx"], i["masks"], i["z"], i["nl"], refs=refs)
    return unet(i["x"], i["t"], i["ctx"], down_block_additional_residuals=down, mid_block_additional_residual=mid).sample

i = inputs()
with FlopCounterMode(display=False) as fc:
    with torch.no_grad():
        fwd(i)
f_model = fc.get_total_flops()
with FlopCounterMode(display=False) as fc:
    with torch.no_grad():
        vae.encode(torch.randn(4 * B, 3, H, W, device="meta"))
f_vae = fc.get_total_flops()
print(f"forward FLOPs per camera sample: unet+controlnet {f_model/1e9:.1f} GFLOP; VAE encoder x4 images {f_vae/1e9:.1f} GFLOP")


def saved_gib(train_unet: bool) -> float:
    """Bytes autograd saves for backward in one training forward of one camera sample, in GiB."""
    unet.requires_grad_(train_unet)
    saved = [0]

    def pack(t):
        saved[0] += t.numel() * t.element_size()
        return t

    with torch.autograd.graph.saved_tensors_hooks(pack, lambda t: t):
        fwd(inputs())
    return saved[0] / 2**30


for train_unet in (True, False):
    print(f"saved activations per camera sample (f32, train_unet={train_unet}): {saved_gib(train_unet):.2f} GiB")
unet.enable_gradient_checkpointing(); cn.enable_gradient_checkpointing()
for train_unet in (True, False):
    print(f"saved activations per camera sample with gradient checkpointing (f32, train_unet={train_unet}): "
          f"{saved_gib(train_unet):.3f} GiB")
