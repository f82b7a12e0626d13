"""Fixed-width vector operations for the hot loops that LLVM will not vectorise on its own.

Numba runs LLVM's loop vectoriser but not its SLP vectoriser (off by default since numba
0.57 after miscompilations), and a loop whose trip count is a small constant is unrolled
before the loop vectoriser sees it: ``for i in range(16): row[i] -= f[i] * x`` becomes 16
scalar multiply-subtracts, and with ``f`` in another array LLVM cannot prove the two do
not overlap.  The intrinsics here emit the vector instructions directly.  They do the
same IEEE operations element by element as the scalar loop (a multiply, then a subtract:
no fused multiply-add, no reassociation), so results are identical bit for bit.
"""

from llvmlite import ir
from numba import types
from numba.extending import intrinsic


@intrinsic
def lanes_sub_scaled(typingctx, row, coefs, x):
    """``row[i] -= coefs[i] * x`` for i < L, where ``coefs`` is a tuple of L float64 and
    ``row`` a contiguous float64 array of at least L elements (not checked)."""
    if not (isinstance(coefs, types.UniTuple) and coefs.dtype == types.float64 and isinstance(row, types.Array)
            and row.dtype == types.float64 and row.layout == "C" and x == types.float64):
        return None
    lanes = coefs.count
    sig = types.void(row, coefs, x)

    def codegen(context, builder, signature, args):
        row_v, coefs_v, x_v = args
        array = context.make_array(signature.args[0])(context, builder, row_v)
        vec_type = ir.VectorType(ir.DoubleType(), lanes)
        c_vec = ir.Constant(vec_type, ir.Undefined)
        x_vec = ir.Constant(vec_type, ir.Undefined)
        for i in range(lanes):
            index = ir.Constant(ir.IntType(32), i)
            c_vec = builder.insert_element(c_vec, builder.extract_value(coefs_v, i), index)
            x_vec = builder.insert_element(x_vec, x_v, index)
        pointer = builder.bitcast(array.data, vec_type.as_pointer())
        current = builder.load(pointer, align=8)
        builder.store(builder.fsub(current, builder.fmul(c_vec, x_vec)), pointer, align=8)
        return context.get_dummy_value()

    return sig, codegen
