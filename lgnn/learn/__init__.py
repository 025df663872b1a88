"""Learned models: graph features (`graphs`), the models (`models`), training data
(`data`), checkpoint files and inference from them (`checkpoints`) and training
(`train`)."""
