"""Calls, from numba-compiled code, of C functions known by their address at run time: the
host's callbacks and REBOUND's functions (``reb_simulation_update_acceleration``,
``reb_tools_megno_update``).  A module of its own, so that the numba steps that need them
(:mod:`hbvm_md.rebound.glue`, :mod:`hbvm_md.rebound.forces`) do not compile the numba dispatch
of :mod:`hbvm_md.rebound.cabi` at import."""
from numba import types
from numba.extending import intrinsic


@intrinsic
def call_status(typingctx, fn, r, p):
    """``((int (*)(void*, void*)) fn)(r, p)``: a function known by its address at run time."""
    if not (isinstance(fn, types.Integer) and r == types.voidptr and p == types.voidptr):
        return None

    def codegen(context, builder, signature, args):
        from llvmlite import ir
        i8p = ir.IntType(8).as_pointer()
        fnty = ir.FunctionType(ir.IntType(32), [i8p, i8p])
        return builder.call(builder.inttoptr(args[0], fnty.as_pointer()), [args[1], args[2]])
    return types.int32(fn, r, p), codegen


@intrinsic
def call_void(typingctx, fn, addr):
    """``((void (*)(void*)) fn)((void*) addr)``: a C function known by its address at run time
    (the C library's ``free`` here, REBOUND's ``reb_simulation_update_acceleration`` in
    :mod:`hbvm_md.rebound.forces`)."""
    if not (isinstance(fn, types.Integer) and isinstance(addr, types.Integer)):
        return None

    def codegen(context, builder, signature, args):
        from llvmlite import ir
        i8p = ir.IntType(8).as_pointer()
        fnty = ir.FunctionType(ir.VoidType(), [i8p])
        builder.call(builder.inttoptr(args[0], fnty.as_pointer()), [builder.inttoptr(args[1], i8p)])
        return context.get_dummy_value()
    return types.none(fn, addr), codegen


@intrinsic
def call_megno(typingctx, fn, r, dY, dt):
    """``((void (*)(void*, double, double)) fn)((void*) r, dY, dt)``: REBOUND's
    ``reb_tools_megno_update(r, dY, dt_done)``, its address known at run time."""
    if not all(isinstance(a, types.Integer) for a in (fn, r)) or not all(
            isinstance(a, types.Float) for a in (dY, dt)):
        return None

    def codegen(context, builder, signature, args):
        from llvmlite import ir
        i8p, f64 = ir.IntType(8).as_pointer(), ir.DoubleType()
        fnty = ir.FunctionType(ir.VoidType(), [i8p, f64, f64])
        builder.call(builder.inttoptr(args[0], fnty.as_pointer()),
                     [builder.inttoptr(args[1], i8p), args[2], args[3]])
        return context.get_dummy_value()
    return types.none(fn, r, dY, dt), codegen
