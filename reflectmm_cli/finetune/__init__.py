"""Finetuning the reflectance model on in-the-wild images (update-by-reconstruction, docs/design.md §7) and
single-image reconstruction with the trained encoder: alignment (:mod:`.align`), the shard dataset
(:mod:`.data`), encoder, losses, G-buffer shading and the training loop. See docs/finetune.md."""
