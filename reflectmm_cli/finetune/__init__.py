"""Finetuning on in-the-wild images (DESIGN.md §7): alignment (:mod:`.align`) and the shard dataset (:mod:`.data`)."""
