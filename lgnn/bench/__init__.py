"""The benchmark and the tools that measure: the grid and profiles (`grid`), record
paths and reuse (`store`), the stages (`stages`: train, evaluate, speed, scaling, mass),
the whole run (`run`), the report (`report`), batched timed rollouts (`timing`), table
writers (`tables`), engine crosschecks (`crosscheck`) and the hard cases (`stability`)."""
