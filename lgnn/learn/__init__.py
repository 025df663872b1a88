"""Learned models: graph features (`graphs`), the models (`models`), training data
(`data`) and training with checkpoints (`train`)."""
