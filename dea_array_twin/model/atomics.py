"""Atomic operations on integer array elements inside compiled (numba) code.

numba has no atomics of its own; these intrinsics emit LLVM's (sequentially consistent), so two
threads running compiled code with the GIL released can hand work to each other through a shared
``int64`` array (:mod:`.point_team`): a compare-and-swap claims an entry, an atomic load reads one
that another thread writes, an atomic store publishes one after the data it announces.
"""

from __future__ import annotations

from numba import types
from numba.core import cgutils
from numba.extending import intrinsic


def _element(context, builder, array_type, array, index):
    """Pointer to ``array[index]``."""
    view = context.make_array(array_type)(context, builder, array)
    return cgutils.get_item_pointer(context, builder, array_type, view, [index])


@intrinsic
def compare_and_swap(typingctx, array, index, expected, new):
    """``old = array[index]; if old == expected: array[index] = new``, atomically; returns ``old``."""
    signature = array.dtype(array, index, array.dtype, array.dtype)

    def codegen(context, builder, sig, args):
        pointer = _element(context, builder, sig.args[0], args[0], args[1])
        pair = builder.cmpxchg(pointer, args[2], args[3], "seq_cst", "seq_cst")
        return builder.extract_value(pair, 0)

    return signature, codegen


@intrinsic
def fetch_add(typingctx, array, index, value):
    """``array[index] += value`` atomically; returns the value before."""
    signature = array.dtype(array, index, array.dtype)

    def codegen(context, builder, sig, args):
        pointer = _element(context, builder, sig.args[0], args[0], args[1])
        return builder.atomic_rmw("add", pointer, args[2], "seq_cst")

    return signature, codegen


@intrinsic
def atomic_load(typingctx, array, index):
    """``array[index]``, read atomically (never cached in a register: a loop sees other threads' stores)."""
    signature = array.dtype(array, index)

    def codegen(context, builder, sig, args):
        pointer = _element(context, builder, sig.args[0], args[0], args[1])
        return builder.load_atomic(pointer, "seq_cst", sig.args[0].dtype.bitwidth // 8)

    return signature, codegen


@intrinsic
def atomic_store(typingctx, array, index, value):
    """``array[index] = value`` atomically, after every store before it (sequentially consistent)."""
    signature = types.void(array, index, array.dtype)

    def codegen(context, builder, sig, args):
        pointer = _element(context, builder, sig.args[0], args[0], args[1])
        builder.store_atomic(args[2], pointer, "seq_cst", sig.args[0].dtype.bitwidth // 8)
        return context.get_dummy_value()

    return signature, codegen
