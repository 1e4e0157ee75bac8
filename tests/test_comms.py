"""The radio: contact graph and knowledge exchange (single hop and relay)."""

from __future__ import annotations

import math

import chex
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxmripp.sim import comms, maps

exchange = jax.jit(comms.exchange, static_argnames="relay")
contacts = jax.jit(comms.contacts)

# Three robots on a line: 0-1 and 1-2 are 0.25 apart, 0-2 are 0.5 apart.
CHAIN = jnp.asarray([[0.0, 0.0, 0.0], [0.25, 0.0, 0.0], [0.5, 0.0, 0.0]], jnp.float32)


def own_histories(lengths):
    """Start of an episode's step: every robot knows only its own history."""
    return jnp.diag(jnp.asarray(lengths, jnp.int32))


def reference_exchange(know, contact, relay):
    """The specification, literally: one max-update (relay: repeated N - 1 times)."""
    know, contact = np.array(know), np.array(contact)
    n = len(know)
    for _ in range(n - 1 if relay else 1):
        shared = know if relay else np.diag(np.diag(know))
        new = know.copy()
        for i in range(n):
            for k in range(n):
                if contact[i, k]:
                    new[i] = np.maximum(new[i], shared[k])
        know = new
    return know


def random_case(seed, n, p_link):
    rng = np.random.default_rng(seed)
    link = np.triu(rng.random((n, n)) < p_link, 1)
    contact = link | link.T
    own = rng.integers(0, 20, n)
    # Partial knowledge of others never exceeds their own history length.
    know = np.minimum(rng.integers(0, 20, (n, n)), own[None, :])
    np.fill_diagonal(know, own)
    return jnp.asarray(know, jnp.int32), jnp.asarray(contact)


def test_contacts_range_is_inclusive_and_excludes_self():
    c = np.asarray(contacts(CHAIN, 0.25))
    np.testing.assert_array_equal(c, [[0, 1, 0], [1, 0, 1], [0, 1, 0]])
    np.testing.assert_array_equal(c, c.T)
    np.testing.assert_array_equal(np.asarray(contacts(CHAIN, 0.2499)), np.zeros((3, 3)))


def test_contacts_infinite_and_zero_range():
    co_located = jnp.zeros((4, 3), jnp.float32)
    np.testing.assert_array_equal(contacts(co_located, math.inf), ~np.eye(4, dtype=bool))
    np.testing.assert_array_equal(contacts(CHAIN, math.inf), ~np.eye(3, dtype=bool))
    # Range 0 means no radio at all, even for robots at the same spot.
    np.testing.assert_array_equal(contacts(co_located, 0.0), np.zeros((4, 4), bool))


def test_inactive_robots_neither_send_nor_receive():
    c = np.asarray(contacts(CHAIN, math.inf, jnp.asarray([True, False, True])))
    np.testing.assert_array_equal(c, [[0, 0, 1], [0, 0, 0], [1, 0, 0]])


def test_contacts_vmap_over_radio_ranges():
    sweep = jax.jit(jax.vmap(comms.contacts, in_axes=(None, 0)))
    out = np.asarray(sweep(CHAIN, jnp.asarray([0.0, 0.3, math.inf])))
    np.testing.assert_array_equal(out[0], np.zeros((3, 3)))
    np.testing.assert_array_equal(out[1], contacts(CHAIN, 0.3))
    np.testing.assert_array_equal(out[2], ~np.eye(3, dtype=bool))


@pytest.mark.parametrize("relay", [False, True])
def test_global_radio_shares_every_history_in_one_exchange(relay):
    lengths = [3, 5, 0, 7]
    positions = jax.random.uniform(jax.random.key(0), (4, 3))
    know = exchange(own_histories(lengths), contacts(positions, math.inf), relay=relay)
    np.testing.assert_array_equal(know, np.tile(lengths, (4, 1)))


@pytest.mark.parametrize("relay", [False, True])
def test_no_radio_learns_nothing(relay):
    know, _ = random_case(0, 5, 0.0)
    positions = jnp.zeros((5, 3), jnp.float32)
    np.testing.assert_array_equal(exchange(know, contacts(positions, 0.0), relay=relay), know)


def test_chain_relay_reaches_the_far_end_single_hop_does_not():
    contact = contacts(CHAIN, 0.3)
    know = own_histories([1, 2, 3])
    hop = np.asarray(exchange(know, contact, relay=False))
    np.testing.assert_array_equal(hop, [[1, 2, 0], [1, 2, 3], [0, 2, 3]])
    relayed = np.asarray(exchange(know, contact, relay=True))
    np.testing.assert_array_equal(relayed, np.tile([1, 2, 3], (3, 1)))
    # Single hop never forwards second-hand knowledge, however many steps it repeats.
    np.testing.assert_array_equal(exchange(jnp.asarray(hop), contact, relay=False), hop)


def test_hand_worked_example():
    # Robot 0 has flown 4 poses, robot 1 has 2, robot 2 has 5, robot 3 has 1. Earlier
    # contacts left 0 knowing 1 pose of robot 2's history and 3 knowing 3 of robot 0's.
    know = jnp.asarray([[4, 0, 1, 0],
                        [0, 2, 0, 0],
                        [0, 0, 5, 0],
                        [3, 0, 0, 1]], jnp.int32)
    # Links now: 0-1 and 1-3; robot 2 is out of range.
    contact = jnp.asarray([[0, 1, 0, 0],
                           [1, 0, 0, 1],
                           [0, 0, 0, 0],
                           [0, 1, 0, 0]], bool)
    # Single hop: each robot hears its neighbours' own histories only. Robot 1 hears 0's
    # 4 poses and 3's 1; it does not hear what 0 knows of robot 2.
    np.testing.assert_array_equal(exchange(know, contact, relay=False),
                                  [[4, 2, 1, 0],
                                   [4, 2, 0, 1],
                                   [0, 0, 5, 0],
                                   [3, 2, 0, 1]])
    # Relay: 0, 1 and 3 form one component and pool everything they know, including 0's
    # partial copy of robot 2's history; robot 3's stale copy of 0 (3 poses) is updated.
    np.testing.assert_array_equal(exchange(know, contact, relay=True),
                                  [[4, 2, 1, 1],
                                   [4, 2, 1, 1],
                                   [0, 0, 5, 0],
                                   [4, 2, 1, 1]])


@pytest.mark.parametrize("relay", [False, True])
@pytest.mark.parametrize("seed", range(4))
def test_matches_the_literal_specification_and_is_monotone(relay, seed):
    n = 7 + seed  # N - 1 = 6..9 crosses a power of two: 3 and 4 squarings
    know, contact = random_case(seed, n, p_link=0.25)
    new = np.asarray(exchange(know, contact, relay=relay))
    np.testing.assert_array_equal(new, reference_exchange(know, contact, relay))
    assert np.all(new >= np.asarray(know))  # nothing is ever forgotten
    assert np.all(new <= np.diag(np.asarray(know))[None, :])  # nothing is invented
    # A second exchange with the same links changes nothing under relay.
    if relay:
        np.testing.assert_array_equal(exchange(jnp.asarray(new), contact, relay=True), new)


@pytest.mark.parametrize("n", [1, 2])
def test_tiny_teams(n):
    know = own_histories(range(1, n + 1))
    contact = contacts(jnp.zeros((n, 3)), math.inf)
    for relay in (False, True):
        np.testing.assert_array_equal(exchange(know, contact, relay=relay),
                                      np.tile(np.arange(1, n + 1), (n, 1)))


def test_vmaps_over_envs_and_is_traced_once():
    @jax.jit
    @chex.assert_max_traces(n=1)
    def batched(positions, know):
        def one_env(positions, know):
            return comms.exchange(know, comms.contacts(positions, 0.3), relay=True)

        return jax.vmap(one_env)(positions, know)

    for seed in range(2):
        positions = jax.random.uniform(jax.random.key(seed), (5, 4, 3))
        know = jnp.broadcast_to(own_histories([1, 2, 3, 4]), (5, 4, 4))
        out = batched(positions, know)
        chex.assert_shape(out, (5, 4, 4))
        for e in range(5):
            np.testing.assert_array_equal(
                out[e], reference_exchange(know[e], contacts(positions[e], 0.3), relay=True))


# ---------------------------------------------------------------------------------------
# Shared maps (jaxmripp.spec.sharing)

share_maps = jax.jit(comms.share_maps, static_argnames="relay")


def consistent_maps(rng, n, size):
    """n maps that each know a random part of one random truth (FREE / OCCUPIED), as int8
    maps and as the team map that holds them (`jaxmripp.sim.maps`)."""
    truth = rng.choice([0, 2], size=(size, size, size)).astype(np.int8)
    known = rng.random((n, size, size, size)) < 0.3
    robot_maps = np.where(known, truth[None], 1).astype(np.int8)
    column_top = lambda m: np.max(np.where(m == 2, np.arange(size) + 1, 0), axis=-1)
    tops = np.stack([column_top(m) for m in robot_maps]).astype(np.int8)
    return truth, robot_maps, team_map_of(truth, known), tops, column_top


def team_map_of(truth, known):
    """The team map of a truth (G, G, G) codes and known (N, G, G, G) bool, bit by bit
    (bit 0 building, bit 1 + i robot i, eight bits per byte)."""
    n = known.shape[0]
    bits = np.zeros(((n + 8) // 8 * 8, *truth.shape), bool)
    bits[0], bits[1:n + 1] = truth == 2, known
    weights = (1 << np.arange(8)).reshape(1, 8, 1, 1, 1)
    return (bits.reshape(-1, 8, *truth.shape) * weights).sum(axis=1).astype(np.uint8)


@pytest.mark.parametrize("relay", [False, True])
def test_shared_maps_are_the_union_of_what_each_robot_hears(relay):
    rng = np.random.default_rng(0)
    truth, robot_maps, team, tops, column_top = consistent_maps(rng, 3, 6)
    contact = np.asarray(contacts(CHAIN, 0.3))  # 0-1 and 1-2 linked, 0-2 not
    team, merged_tops = share_maps(team, tops, contact, relay=relay)
    merged, merged_tops = np.asarray(maps.robot_maps(team, 3)), np.asarray(merged_tops)
    for i in range(3):
        sources = [i] + [k for k in range(3) if contact[i, k] or (relay and k != i)]
        known = np.any(robot_maps[sources] != 1, axis=0)
        np.testing.assert_array_equal(merged[i], np.where(known, truth, 1))
        np.testing.assert_array_equal(merged_tops[i], column_top(merged[i]))
    # The chain's ends hear each other's maps only through the middle robot (relay).
    assert relay == bool(np.any((robot_maps[2] != 1) & (robot_maps[0] == 1) & (merged[0] != 1)
                                & (robot_maps[1] == 1)))


@pytest.mark.parametrize("relay", [False, True])
def test_shared_maps_of_a_large_team_match_the_union(relay):
    """Nine robots: their bits span two bytes per voxel, merged receiver by receiver."""
    rng = np.random.default_rng(2)
    n = 9
    truth, robot_maps, team, tops, _ = consistent_maps(rng, n, 4)
    contact = rng.random((n, n)) < 0.3
    contact = (contact | contact.T) & ~np.eye(n, dtype=bool)
    merged = np.asarray(maps.robot_maps(share_maps(team, tops, contact, relay=relay)[0], n))
    hears = np.asarray(comms.links(jnp.asarray(contact), relay)) | np.eye(n, dtype=bool)
    for i in range(n):
        known = np.any(robot_maps[hears[i]] != 1, axis=0)
        np.testing.assert_array_equal(merged[i], np.where(known, truth, 1))


@pytest.mark.parametrize("map_by_map", [False, True])
def test_a_batch_of_large_team_maps_merges_each_map_by_its_own_links(map_by_map, monkeypatch):
    """Seventeen robots (three bytes per voxel), four environments vmapped: all linked, two
    components, nobody linked, random single-hop contacts; merged receiver by receiver
    (small maps) or map by map, where robots that hear the same set take one pass whose
    bits span every byte."""
    monkeypatch.setattr(maps, "_MAP_BY_MAP_VOXELS", 0 if map_by_map else 10**9)
    rng = np.random.default_rng(5)
    n, envs = 17, 4
    eye = np.eye(n, dtype=bool)
    halves = np.arange(n)[:, None] < 9
    random = rng.random((n, n)) < 0.15
    linked = np.stack([~eye, (halves == halves.T) & ~eye, np.zeros((n, n), bool),
                       (random | random.T) & ~eye])
    worlds = [consistent_maps(rng, n, 4) for _ in range(envs)]
    teams = jnp.asarray(np.stack([w[2] for w in worlds]))
    merged = jax.jit(jax.vmap(maps.merge))(teams, jnp.asarray(linked))
    for e, (truth, robot_maps, team, _, _) in enumerate(worlds):
        np.testing.assert_array_equal(merged[e], maps.merge(jnp.asarray(team), linked[e]))
        decoded = np.asarray(maps.robot_maps(merged[e], n))
        for i in range(n):
            known = np.any(robot_maps[linked[e, i] | eye[i]] != 1, axis=0)
            np.testing.assert_array_equal(decoded[i], np.where(known, truth, 1))


def test_shared_maps_without_contact_change_nothing():
    rng = np.random.default_rng(1)
    _, _, team, tops, _ = consistent_maps(rng, 3, 5)
    merged, merged_tops = share_maps(team, tops, np.zeros((3, 3), bool), relay=False)
    np.testing.assert_array_equal(np.asarray(merged), team)
    np.testing.assert_array_equal(np.asarray(merged_tops), tops)
