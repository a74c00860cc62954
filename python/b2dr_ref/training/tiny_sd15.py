"""A tiny Stable-Diffusion-1.5-shaped diffusers folder, written offline (tests and smoke runs of the sd15 recipe):
the real classes (UNet2DConditionModel, AutoencoderKL, CLIPTextModel, CLIPTokenizer, PNDMScheduler as SD1.5
ships it) with tiny configs and seeded random weights, each written with save_pretrained.

    python -m b2dr_ref.training.tiny_sd15 OUT_DIR

The tokenizer is a byte-level BPE built here (the 256 byte symbols, each also with CLIP's end-of-word mark
``</w>``, a few merges, CLIP's special tokens): nothing is downloaded.
"""

from __future__ import annotations

import json
import os
import sys

import torch

UNET = dict(sample_size=8, in_channels=4, out_channels=4, block_out_channels=[16, 16, 32], layers_per_block=1,
            down_block_types=["CrossAttnDownBlock2D", "CrossAttnDownBlock2D", "DownBlock2D"],
            up_block_types=["UpBlock2D", "CrossAttnUpBlock2D", "CrossAttnUpBlock2D"], cross_attention_dim=32,
            attention_head_dim=4, norm_num_groups=8)
VAE = dict(in_channels=3, out_channels=3, block_out_channels=[8, 16, 16, 16], layers_per_block=1,
           down_block_types=["DownEncoderBlock2D"] * 4, up_block_types=["UpDecoderBlock2D"] * 4,
           latent_channels=4, norm_num_groups=4, sample_size=32)
# SD1.5's scheduler/scheduler_config.json (PNDMScheduler, scaled_linear 0.00085 .. 0.012)
SCHEDULER = dict(beta_start=0.00085, beta_end=0.012, beta_schedule="scaled_linear", num_train_timesteps=1000,
                 set_alpha_to_one=False, skip_prk_steps=True, steps_offset=1, prediction_type="epsilon")
MERGES = [("t", "h"), ("th", "e</w>"), ("a", "r</w>"), ("c", "a"), ("ca", "m"), ("e", "r</w>")]


def bytes_to_unicode():
    """GPT-2 / CLIP's reversible byte -> printable unicode map."""
    bs = list(range(ord("!"), ord("~") + 1)) + list(range(ord("¡"), ord("¬") + 1)) + \
        list(range(ord("®"), ord("ÿ") + 1))
    cs = bs[:]
    n = 0
    for b in range(256):
        if b not in bs:
            bs.append(b)
            cs.append(256 + n)
            n += 1
    return dict(zip(bs, [chr(c) for c in cs]))


def write_tokenizer(folder: str):
    from transformers import CLIPTokenizer

    os.makedirs(folder, exist_ok=True)
    base = list(bytes_to_unicode().values())
    vocab_list = base + [b + "</w>" for b in base] + ["".join(m).replace("</w>", "") + ("</w>" if m[1].endswith("</w>") else "")
                                                      for m in MERGES] + ["<|startoftext|>", "<|endoftext|>"]
    vocab = {}
    for v in vocab_list:
        vocab.setdefault(v, len(vocab))
    with open(os.path.join(folder, "vocab.json"), "w", encoding="utf-8") as f:
        json.dump(vocab, f, ensure_ascii=False)
    with open(os.path.join(folder, "merges.txt"), "w", encoding="utf-8") as f:
        f.write("#version: 0.2\n" + "".join(f"{a} {b}\n" for a, b in MERGES))
    tok = CLIPTokenizer(os.path.join(folder, "vocab.json"), os.path.join(folder, "merges.txt"), model_max_length=77)
    tok.save_pretrained(folder)
    return tok


def write_tiny_sd15(out: str, seed: int = 0) -> str:
    from diffusers import AutoencoderKL, PNDMScheduler, UNet2DConditionModel
    from transformers import CLIPTextConfig, CLIPTextModel

    torch.manual_seed(seed)
    tok = write_tokenizer(os.path.join(out, "tokenizer"))
    UNet2DConditionModel(**UNET).save_pretrained(os.path.join(out, "unet"))
    AutoencoderKL(**VAE).save_pretrained(os.path.join(out, "vae"))
    cfg = CLIPTextConfig(vocab_size=len(tok.get_vocab()), hidden_size=32, intermediate_size=64, num_hidden_layers=2,
                         num_attention_heads=4, max_position_embeddings=77, projection_dim=32,
                         bos_token_id=tok.bos_token_id, eos_token_id=tok.eos_token_id, pad_token_id=tok.pad_token_id)
    CLIPTextModel(cfg).save_pretrained(os.path.join(out, "text_encoder"))
    PNDMScheduler(**SCHEDULER).save_pretrained(os.path.join(out, "scheduler"))
    with open(os.path.join(out, "model_index.json"), "w") as f:
        json.dump({"_class_name": "StableDiffusionPipeline", "unet": ["diffusers", "UNet2DConditionModel"],
                   "vae": ["diffusers", "AutoencoderKL"], "text_encoder": ["transformers", "CLIPTextModel"],
                   "tokenizer": ["transformers", "CLIPTokenizer"], "scheduler": ["diffusers", "PNDMScheduler"]}, f,
                  indent=2)
    return out


if __name__ == "__main__":
    print(write_tiny_sd15(sys.argv[1]))
