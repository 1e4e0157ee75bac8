"""The radio: who can hear whom, and what knowledge flows along those links.

Knowledge is a matrix `know: (N, N) int32`, where know[i, j] is how many entries of
robot j's history (its visited poses, in order) robot i holds; know[i, i] is robot i's own
history length. Histories only grow and are shared as prefixes, so everything a radio
exchange does is a max-update of counts: robot i ends up with the longest prefix of each
history that reaches it.
"""

from __future__ import annotations

import math

import chex
import jax
import jax.numpy as jnp

from jaxmripp.sim import maps


def contacts(
    positions: jax.Array, radio_range: float | jax.Array, active: jax.Array | None = None
) -> jax.Array:
    """(N, 3) positions -> (N, N) bool, True where robots i != j are within radio range.

    The range is inclusive and may be inf (global communication) or 0 (none at all, even
    for robots at the same spot). It may be a traced scalar, so sweeps over ranges vmap.
    Inactive robots (e.g. out of the episode) neither send nor receive.
    """
    n = positions.shape[0]
    chex.assert_shape(positions, (n, 3))
    gap2 = jnp.sum(jnp.square(positions[:, None, :] - positions[None, :, :]), axis=-1)
    link = (gap2 <= jnp.square(radio_range)) & (radio_range > 0) & ~jnp.eye(n, dtype=bool)
    if active is not None:
        chex.assert_shape(active, (n,))
        link = link & active[:, None] & active[None, :]
    return link


def exchange(know: jax.Array, contact: jax.Array, relay: bool) -> jax.Array:
    """One radio round: (N, N) int32 knowledge, (N, N) bool contacts -> updated knowledge.

    Single hop (relay=False, the paper): each robot hears its neighbours' own histories.
    Relay (relay=True): everything known is forwarded through the connected component
    within the same step. Both are the same max-update; they differ in who is linked
    and which entries a linked robot shares.
    """
    n = know.shape[0]
    chex.assert_shape([know, contact], (n, n))
    if relay:
        # Repeating the single-link update N - 1 times lets i hear every robot within
        # N - 1 hops, i.e. its whole component, and max is idempotent; so one update over
        # the transitive closure gives the identical result in O(log N) matmuls.
        return _max_update(know, _reachable(contact), shared=know)
    # A neighbour shares only its own history: the diagonal of `know`.
    return _max_update(know, contact, shared=jnp.diag(jnp.diag(know)))


def _max_update(know: jax.Array, links: jax.Array, shared: jax.Array) -> jax.Array:
    """know[i, j] <- max(know[i, j], max over k with links[i, k] of shared[k, j]).

    Neighbours are heard one at a time, in O(N^2) memory: the broadcast (N, N, N) form
    materialises N^3 counts and ran about 30x slower on CPU at N = 64. Counts are
    non-negative, so 0 is neutral for robots that are not linked.
    """

    def hear(k, acc):
        return jnp.maximum(acc, jnp.where(links[:, k, None], shared[k][None, :], 0))

    return jax.lax.fori_loop(0, know.shape[0], hear, know)


def links(contact: jax.Array, relay: bool) -> jax.Array:
    """(N, N) bool contacts -> who hears whom within one round: the contacts themselves
    (single hop) or, with relay, every robot of the same connected component."""
    return _reachable(contact) if relay else contact


def _reachable(contact: jax.Array) -> jax.Array:
    """(N, N) bool links -> (N, N) bool, True where j is reachable from i (i included).

    Squaring the reflexive adjacency s times covers every path of up to 2^s links;
    ceil(log2(N - 1)) squarings cover every simple path. The 0/1 entries are exact in any
    matmul precision and positive terms cannot cancel, so `> 0` is exact.
    """
    n = contact.shape[0]
    reach = (contact | jnp.eye(n, dtype=bool)).astype(jnp.float32)
    for _ in range(math.ceil(math.log2(max(n - 1, 1)))):
        reach = (reach @ reach > 0).astype(jnp.float32)
    return reach > 0


def share_maps(team_map: jax.Array, tops: jax.Array, contact: jax.Array,
               relay: bool) -> tuple[jax.Array, jax.Array]:
    """The map merge of `jaxmripp.spec.sharing`: a team map (`jaxmripp.sim.maps`), (N, G, G)
    int8 building tops, (N, N) bool contacts -> merged team map and tops.

    Every robot learns what the robots it hears knew before this merge (single hop), or
    its whole component (relay); known codes agree with the truth, so what a robot learns
    does not depend on the order it hears its peers in."""
    n = tops.shape[0]
    chex.assert_shape(contact, (n, n))
    linked = links(contact, relay)

    def hear(k, merged_tops):
        return jnp.where(linked[:, k, None, None], jnp.maximum(merged_tops, tops[k][None]),
                         merged_tops)

    return maps.merge(team_map, linked), jax.lax.fori_loop(0, n, hear, tops)
