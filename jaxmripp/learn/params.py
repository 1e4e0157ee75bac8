"""Network parameter trees: where two trees of shapes differ, for the error of a run
started from other parameters (`train.init_from`)."""

from __future__ import annotations

import jax


def first_difference(want, got) -> str:
    """The first leaf path where two trees of shapes differ, for one error line."""
    flat_want = dict(jax.tree_util.tree_flatten_with_path(want)[0])
    flat_got = dict(jax.tree_util.tree_flatten_with_path(got)[0])
    for path in sorted(set(flat_want) | set(flat_got), key=str):
        if flat_want.get(path) != flat_got.get(path):
            return (f"{jax.tree_util.keystr(path)}: {flat_want.get(path, 'absent')} here, "
                    f"{flat_got.get(path, 'absent')} there")
    return "tree structure"
