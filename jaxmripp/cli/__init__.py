"""The command line: `jaxmripp COMMAND ...` (`main`), with one module per command the
package does not already hold (`train`, `evaluate`, `bench`); export, ship, demo and fly
are `jaxmripp.export`, `jaxmripp.ship`, `jaxmripp.demo` and `jaxmripp.flight`. train.py and
eval.py at the repository root call the same code."""
