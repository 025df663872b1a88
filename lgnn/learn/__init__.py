"""Learned models: graph features (`graphs`), the models (`models`: the registry, the
shared MLP and graph-network kit, and one module per model, e.g. `models.strong_gns`,
`models.cgnode`, `models.chgn`), training data (`data`), checkpoint files and inference
from them (`checkpoints`) and training (`train`)."""
