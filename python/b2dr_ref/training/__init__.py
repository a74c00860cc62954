"""Training of the B2D-R renderer with accelerate (docs/training.md "At the paper's scale").

- ``common``: what every recipe shares: arguments, the Accelerator, checkpoint rotation and resume, trackers,
  EMA, the data set and its collate function, batched VAE encoding, validation grids, the package export;
- ``sd15``: the recipe from a diffusers Stable Diffusion 1.5 folder (``python -m b2dr_ref.training.sd15``, or
  ``accelerate launch -m b2dr_ref.training.sd15``).

The nano trainer (b2dr_ref.train) keeps its own CLI; this package reuses its data sources, PETR geometry and the
pieces of its loss (draw_noise, noised_inputs, denoise, prediction_loss), so both recipes compute the same loss.
"""
