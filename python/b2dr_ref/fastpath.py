"""Training fast paths (docs/training.md "Throughput"): what can make a diffusion step cheaper without changing
what it computes beyond rounding.

- ``channels_last``: NHWC memory for the UNet / ControlNet weights and 4-D inputs (oneDNN's preferred layout);
- ``compile``: ``torch.compile`` (inductor) of the UNet and ControlNet forward; on the CPU it fuses GroupNorm +
  SiLU and the elementwise chains into generated C++ loops, the convolutions stay oneDNN calls;
- ``autocast``: ``bf16`` / ``fp16`` autocast around the forward (the loss and the optimizer stay f32);
- ``Prefetcher``: the next batch is prepared (VAE encodes of uncached samples, PE, stacking) on a background
  thread while the current step runs backward and the optimizer.

A fast path must give the eager f32 step's loss and gradients within the tolerances of
python/tests/test_fastpath.py; ``train bench`` measures what each buys (``b2dr_ref.train_bench``).
"""

from __future__ import annotations

import contextlib
import threading
from dataclasses import dataclass
from typing import Callable, Optional

import torch

AUTOCASTS = ("none", "bf16", "fp16")


@dataclass(frozen=True)
class FastPath:
    channels_last: bool = False
    compile: bool = False
    autocast: str = "none"

    def __post_init__(self):
        if self.autocast not in AUTOCASTS:
            raise ValueError(f"autocast {self.autocast!r} (one of {', '.join(AUTOCASTS)})")

    @property
    def plain(self) -> bool:
        return not (self.channels_last or self.compile or self.autocast != "none")

    def describe(self) -> str:
        parts = [p for p, on in (("channels_last", self.channels_last), ("compile", self.compile),
                                 (f"autocast {self.autocast}", self.autocast != "none")) if on]
        return " + ".join(parts) or "eager f32"

    def prepare(self, unet, controlnet):
        """Applies the memory format in place and returns the modules to CALL (compiled wrappers or the modules
        themselves). Keep the originals for ``state_dict`` (a compiled wrapper prefixes its keys)."""
        if self.channels_last:
            unet.to(memory_format=torch.channels_last)
            controlnet.to(memory_format=torch.channels_last)
        if self.compile:
            return torch.compile(unet, dynamic=False), torch.compile(controlnet, dynamic=False)
        return unet, controlnet

    def inputs(self, x: torch.Tensor) -> torch.Tensor:
        """A 4-D input in the memory format of the modules."""
        if self.channels_last and x.dim() == 4:
            return x.contiguous(memory_format=torch.channels_last)
        return x

    def autocast_ctx(self, device: torch.device):
        if self.autocast == "none":
            return contextlib.nullcontext()
        dt = torch.bfloat16 if self.autocast == "bf16" else torch.float16
        return torch.autocast(device_type=device.type, dtype=dt)


PLAIN = FastPath()


class Prefetcher:
    """Runs ``fn(arg)`` on one background thread, one job at a time: ``submit`` starts the next job, ``take``
    waits for it. Exceptions are re-raised by ``take``. The caller must not use what the job touches (the batcher)
    between ``submit`` and ``take``."""

    def __init__(self, fn: Callable):
        self.fn = fn
        self._thread: Optional[threading.Thread] = None
        self._result = None
        self._error: Optional[BaseException] = None
        self.pending_arg = None

    def submit(self, arg):
        if self._thread is not None:
            raise RuntimeError("Prefetcher: a job is already running")
        self.pending_arg = arg

        def run():
            try:
                self._result = self.fn(arg)
            except BaseException as e:       # re-raised in the caller's thread by take()
                self._error = e

        self._thread = threading.Thread(target=run, name="b2dr-prefetch", daemon=True)
        self._thread.start()

    @property
    def busy(self) -> bool:
        return self._thread is not None

    def take(self):
        if self._thread is None:
            raise RuntimeError("Prefetcher: nothing submitted")
        self._thread.join()
        self._thread = None
        err, res = self._error, self._result
        self._error = self._result = None
        if err is not None:
            raise err
        return res
