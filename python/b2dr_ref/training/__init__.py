"""Training of the B2D-R renderer (docs/training.md; "At the paper's scale" for the accelerate recipe).

Shared by every recipe:
- ``data``: one camera sample (``Sample``), its sources (the exported set, its shard form, a synthetic one) and its
  PETR geometry;
- ``shards``: the export packed into compressed tar shards with an index (``python -m b2dr_ref.training.shards
  pack``) and ``ShardSource``, which reads them on demand and draws the references again every epoch;
  ``shard_bench``: a synthetic log of any size in that form and the DataLoader memory measurement
  (tools/bench_shards.py);
- ``loss``: the diffusion loss in pieces (draw_noise, noised_inputs, denoise, prediction_loss, loss weights);
- ``common``: the accelerate side: arguments, the Accelerator, checkpoint rotation and resume, trackers and
  log.csv, EMA, the DataLoader's data set and collate function, batched VAE encoding, validation grids, the
  package export.

Recipes (thin scripts; none imports another):
- ``sd15``: from a diffusers Stable Diffusion 1.5 folder, with accelerate (``accelerate launch -m
  b2dr_ref.training.sd15``);
- b2dr_ref.train (the nano recipe: its own single-process CLI, kept as it was) and b2dr_ref.vae_train use
  ``data`` and ``loss`` through b2dr_ref.train's names.
- ``tiny_sd15``: a tiny SD1.5-shaped folder for tests and smoke runs.
"""
