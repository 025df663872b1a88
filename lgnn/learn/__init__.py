"""Learned models: graph features (`graphs`), the models (`models`; the strong GNS's
network in `strong_gns`), training data (`data`), checkpoint files and inference from
them (`checkpoints`) and training (`train`)."""
