"""Raw addresses as typed pointers inside numba-compiled code (for :mod:`hbvm_md.rebound_step`).

numba can view memory it did not allocate (``numba.carray``) only through a typed pointer; these
intrinsics turn an integer address into one, and a ``void*`` argument (what REBOUND hands a C
callback) into its address.  They compile to one LLVM ``inttoptr`` / ``ptrtoint`` each.
"""
from __future__ import annotations

from numba import types
from numba.extending import intrinsic


@intrinsic
def address_of(typingctx, ptr):
    """The address held by a ``void*`` as an int64."""
    if ptr != types.voidptr:
        return None

    def codegen(context, builder, signature, args):
        return builder.ptrtoint(args[0], context.get_value_type(types.int64))
    return types.int64(ptr), codegen


def _pointer_intrinsic(dtype):
    ptr_type = types.CPointer(dtype)

    def impl(typingctx, addr):
        if not isinstance(addr, types.Integer):
            return None

        def codegen(context, builder, signature, args):
            return builder.inttoptr(args[0], context.get_value_type(ptr_type))
        return ptr_type(addr), codegen
    impl.__name__ = f"{dtype}_pointer"
    return intrinsic(impl)


float64_pointer = _pointer_intrinsic(types.float64)
int64_pointer = _pointer_intrinsic(types.int64)
int32_pointer = _pointer_intrinsic(types.int32)
complex128_pointer = _pointer_intrinsic(types.complex128)
