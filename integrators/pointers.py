"""Raw addresses as typed pointers inside numba-compiled code, and views of a buffer built on
them (for :func:`integrators.core.carve` and :mod:`hbvm_md.rebound.glue`).

numba can view memory it did not allocate (``numba.carray``) only through a typed pointer; these
intrinsics turn an integer address into one, and a ``void*`` argument (what REBOUND hands a C
callback) into its address.  They compile to one LLVM ``inttoptr`` / ``ptrtoint`` each.

:func:`view` cuts a (rows, cols) array out of a 1-d buffer.  Compiled, it is a ``carray`` at the
buffer's address plus the offset: no reference count and no call, where ``buf[o:o + r c].
reshape((r, c))`` calls numba's reshape helper (measured: carving the step's eighteen work arrays
took 0.7 microsecond that way, about 1 ns this way, on every step that a host calls one at a
time).  The view does not keep the buffer alive: the caller holds the buffer for as long as it
uses the view (the step's work buffers are its arguments).  As Python (``NUMBA_DISABLE_JIT``)
it is the slice and reshape.
"""
from __future__ import annotations

from numba import carray, types
from numba.extending import intrinsic, overload


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


def view(buf, offset, rows, cols):
    """buf[offset:offset + rows cols] as a C-contiguous (rows, cols) array (1-d buffer of float64
    or complex128; the caller checks that it is long enough)."""
    return buf[offset:offset + rows * cols].reshape((rows, cols))


def view1(buf, offset, n):
    """buf[offset:offset + n] (1-d), as :func:`view` does it."""
    return buf[offset:offset + n]


def _pointer_for(buf):
    if not isinstance(buf, types.Array) or buf.ndim != 1 or buf.layout != "C":
        return None, 0
    if buf.dtype == types.float64:
        return float64_pointer, 8
    if buf.dtype == types.complex128:
        return complex128_pointer, 16
    return None, 0


@overload(view)
def _view_compiled(buf, offset, rows, cols):
    pointer, size = _pointer_for(buf)
    if pointer is None:
        return None

    def impl(buf, offset, rows, cols):
        return carray(pointer(buf.ctypes.data + size * offset), (rows, cols))
    return impl


@overload(view1)
def _view1_compiled(buf, offset, n):
    pointer, size = _pointer_for(buf)
    if pointer is None:
        return None

    def impl(buf, offset, n):
        return carray(pointer(buf.ctypes.data + size * offset), n)
    return impl


@intrinsic
def call_int32_voidptr_double(typingctx, fn, ptr, x):
    """Call the C function at address ``fn`` (``int f(void*, double)``) with the address
    ``ptr`` and ``x``; its int32 result.  For a C library's entry point whose address is only
    known at run time (compiled code cached on disk cannot hold one)."""
    if not (isinstance(fn, types.Integer) and isinstance(ptr, types.Integer)
            and x == types.float64):
        return None

    def codegen(context, builder, signature, args):
        from llvmlite import ir
        fnty = ir.FunctionType(ir.IntType(32), [ir.IntType(8).as_pointer(), ir.DoubleType()])
        f = builder.inttoptr(args[0], fnty.as_pointer())
        p = builder.inttoptr(args[1], ir.IntType(8).as_pointer())
        return builder.call(f, [p, args[2]])
    return types.int32(fn, ptr, x), codegen
