"""Data parallelism over every device of every process: `mesh` places arrays on a
one-axis device mesh, `launch` starts a multi-process run (see docs/distributed.md),
`progress` shows process 0's progress on a terminal."""
