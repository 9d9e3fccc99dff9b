"""Finetuning the reflectance model on in-the-wild images (update-by-reconstruction, DESIGN.md §7) and
single-image reconstruction with the trained encoder. See docs/finetune.md."""
