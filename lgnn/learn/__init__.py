"""Learned models: graph features (`graphs`), the models (`models`; the strong GNS's
network in `strong_gns`, the constrained graph neural ODE in `cgnode`, the constrained
Hamiltonian graph network in `chgn`), training data (`data`), checkpoint files and inference from
them (`checkpoints`) and training (`train`)."""
