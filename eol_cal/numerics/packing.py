"""A pytree of arrays carried as one array per dtype: what the plant's compiled calls take and give.

A jitted call costs about 1.3 us of dispatch per array it takes or gives (its buffers checked,
an output array made for each); the plant's parameters and scan state are some 130 of them, about
0.19 ms a call, more than half a millisecond of a one-motor simulated second at 4000 ticks a call.
Packed, they are three arrays. Packing is exact: the leaves are laid side by side and cut out again
(no conversion). Under XLA's defaults a computation on them gives what it gave on the leaves, bit
for bit; the one-kernel loops of :func:`eol_cal.numerics.xla.configure_xla` may round differently
(LLVM contracts float operations across the loop's buffers, and where they lie moves with it).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from eol_cal.numerics.arrays import Array, ArrayModule


@dataclass(frozen=True)
class Packing:
    """Where each leaf of a pytree lies in its packed form (hashable: part of a compiled call's key).

    treedef : the pytree's structure (``jax.tree_util``).
    shapes : each leaf's shape without the leading axes the packed arrays share (a batch's motors).
    dtypes : the packed arrays' dtypes (numpy), one array each, in the order the leaves first use them.
    slots : each leaf's (packed array, first, end) position along the packed arrays' last axis.
    """

    treedef: Any
    shapes: tuple[tuple[int, ...], ...]
    dtypes: tuple[np.dtype, ...]
    slots: tuple[tuple[int, int, int], ...]

    @property
    def sizes(self) -> tuple[int, ...]:
        """The packed arrays' lengths (their last axis)."""
        return tuple(max((b for g2, _, b in self.slots if g2 == g), default=0) for g in range(len(self.dtypes)))


def packing_of(tree: Any, lead: int = 0) -> Packing:
    """The packing of ``tree``, whose leaves share ``lead`` leading axes (not part of the layout)."""
    import jax

    leaves, treedef = jax.tree_util.tree_flatten(tree)
    dtypes: list[np.dtype] = []
    sizes: list[int] = []
    shapes, slots = [], []
    for leaf in leaves:
        a = leaf if hasattr(leaf, "dtype") else np.asarray(leaf)  # arrays, tracers, shape structs
        dt = np.dtype(a.dtype)
        if dt not in dtypes:
            dtypes.append(dt)
            sizes.append(0)
        g = dtypes.index(dt)
        shape = tuple(a.shape[lead:])
        n = math.prod(shape)
        slots.append((g, sizes[g], sizes[g] + n))
        sizes[g] += n
        shapes.append(shape)
    return Packing(treedef, tuple(shapes), tuple(dtypes), tuple(slots))


def pack(pk: Packing, tree: Any, xp: ArrayModule = np) -> tuple[Array, ...]:
    """``tree`` as :attr:`Packing.dtypes`'s arrays: each ``(*lead, size)``, the leaves raveled side by side."""
    import jax

    leaves = jax.tree_util.tree_leaves(tree)
    parts: list[list[Array]] = [[] for _ in pk.dtypes]
    for leaf, shape, (g, _, _) in zip(leaves, pk.shapes, pk.slots, strict=True):
        a = leaf if hasattr(leaf, "reshape") else xp.asarray(leaf)
        parts[g].append(a.reshape(a.shape[:a.ndim - len(shape)] + (-1,)))
    return tuple(xp.concatenate(p, axis=-1) for p in parts)


def unpack(pk: Packing, packed: tuple[Any, ...]) -> Any:
    """The pytree :func:`pack` packed (numpy or JAX arrays; the leading axes the packed arrays share
    kept on every leaf)."""
    import jax

    lead = packed[0].shape[:-1]
    leaves = [packed[g][..., a:b].reshape(lead + shape) for shape, (g, a, b) in zip(pk.shapes, pk.slots, strict=True)]
    return jax.tree_util.tree_unflatten(pk.treedef, leaves)


def pack_stacked(pk: Packing, trees: list[Any]) -> tuple[np.ndarray, ...]:
    """Several pytrees of one packing (numpy leaves, one per motor of a batch) packed and stacked
    along a new leading axis: what :func:`pack` gives of the trees stacked leaf by leaf."""
    packed = [pack(pk, t) for t in trees]
    return tuple(np.stack(arrays) for arrays in zip(*packed, strict=True))
