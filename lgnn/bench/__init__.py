"""The benchmark and the tools that measure: the grid and its stages (`benchmark`), the
report (`report`), engine crosschecks (`crosscheck`) and the hard cases (`stability`)."""
