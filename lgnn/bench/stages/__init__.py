"""The benchmark's stages, one module each: `train`, `evaluate`, `speed`, `scaling`,
`mass`. Each makes records (`lgnn.bench.store`) keyed on the settings groups it reads
(`lgnn.bench.grid`), reuses a record whose key matches, and offers public `load_*`
functions the report reads."""
