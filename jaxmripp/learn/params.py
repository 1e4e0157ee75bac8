"""Network parameter trees: what a run started from other parameters (`train.init_from`)
gains from its fresh initialisation, and where two trees of shapes differ."""

from __future__ import annotations

import jax

from jaxmripp.learn.policy import VIEW_PRIOR_PARAM


def with_prior_weight(params, fresh):
    """`params` with fresh's view-prior weight added where fresh has one and it lacks it."""
    inner, fresh_inner = params["params"], fresh["params"]
    if VIEW_PRIOR_PARAM in fresh_inner and VIEW_PRIOR_PARAM not in inner:
        return {"params": {**inner, VIEW_PRIOR_PARAM: fresh_inner[VIEW_PRIOR_PARAM]}}
    return params


def first_difference(want, got) -> str:
    """The first leaf path where two trees of shapes differ, for one error line."""
    flat_want = dict(jax.tree_util.tree_flatten_with_path(want)[0])
    flat_got = dict(jax.tree_util.tree_flatten_with_path(got)[0])
    for path in sorted(set(flat_want) | set(flat_got), key=str):
        if flat_want.get(path) != flat_got.get(path):
            return (f"{jax.tree_util.keystr(path)}: {flat_want.get(path, 'absent')} here, "
                    f"{flat_got.get(path, 'absent')} there")
    return "tree structure"
