"""A pytree packed into one array per dtype and cut out again (the plant's compiled calls take
and give their parameters and state so): exact, in numpy and inside a jitted function."""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
import pytest

from eol_cal.numerics.packing import pack, pack_stacked, packing_of, unpack

jax = pytest.importorskip("jax")


class _Leaves(NamedTuple):
    x: np.ndarray
    n: np.ndarray
    table: np.ndarray
    empty: np.ndarray
    inner: tuple


def _tree(seed: int) -> _Leaves:
    rng = np.random.default_rng(seed)
    return _Leaves(np.float32(rng.standard_normal()), np.int32(rng.integers(-2**31, 2**31 - 1)),
                   rng.standard_normal((3, 2)).astype(np.float32), np.zeros(0, np.float32),
                   (np.int32(7), rng.integers(0, 2**30, 5).astype(np.int32), None))


def _same(a: object, b: object) -> bool:
    la, lb = jax.tree_util.tree_leaves(a), jax.tree_util.tree_leaves(b)
    return (jax.tree_util.tree_structure(a) == jax.tree_util.tree_structure(b) and len(la) == len(lb)
            and all(np.asarray(u).dtype == np.asarray(v).dtype and np.asarray(u).shape == np.asarray(v).shape
                    and np.asarray(u).tobytes() == np.asarray(v).tobytes() for u, v in zip(la, lb, strict=True)))


def test_a_tree_comes_back_bit_for_bit_one_array_per_dtype():
    t = _tree(1)
    pk = packing_of(t)
    packed = pack(pk, t)
    assert [a.dtype for a in packed] == [np.float32, np.int32] and [a.shape for a in packed] == [(7,), (7,)]
    assert _same(unpack(pk, packed), t)


def test_a_batch_stacks_as_its_trees_stacked_leaf_by_leaf_and_unpacks_inside_jit():
    trees = [_tree(s) for s in range(3)]
    pk = packing_of(trees[0])
    packed = pack_stacked(pk, trees)
    stacked = jax.tree_util.tree_map(lambda *a: np.stack(a), *trees)
    assert all(np.array_equal(a, b) for a, b in zip(packed, pack(pk, stacked), strict=True))
    assert packing_of(stacked, lead=1) == pk  # the same layout, hashable: a compiled call's key
    again = jax.jit(lambda p: pack(pk, unpack(pk, p), jax.numpy))(packed)
    assert all(np.asarray(a).tobytes() == b.tobytes() for a, b in zip(again, packed, strict=True))
    assert _same(jax.tree_util.tree_map(np.asarray, unpack(pk, tuple(np.asarray(a) for a in again))), stacked)
