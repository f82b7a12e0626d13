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
from numba.core import cgutils
from numba.extending import intrinsic

CHUNK = 8  # float64 lanes of one vector operation in the row operations below (one AVX-512 register)


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



_VEC = ir.VectorType(ir.DoubleType(), CHUNK)
_MASK = ir.VectorType(ir.IntType(1), CHUNK)


def _is_row(t):
    return isinstance(t, types.Array) and t.dtype == types.float64 and t.layout == "C" and t.ndim == 1


def _splat(builder, x):
    vec = ir.Constant(ir.VectorType(x.type, CHUNK), ir.Undefined)
    for i in range(CHUNK):
        vec = builder.insert_element(vec, x, ir.Constant(ir.IntType(32), i))
    return vec


def _masked_load(builder, pointer, mask):
    fnty = ir.FunctionType(_VEC, [_VEC.as_pointer(), ir.IntType(32), _MASK, _VEC])
    fn = cgutils.get_or_insert_function(builder.module, fnty, "llvm.masked.load.v8f64.p0")
    return builder.call(fn, [pointer, ir.Constant(ir.IntType(32), 8), mask, ir.Constant(_VEC, None)])


def _masked_store(builder, value, pointer, mask):
    fnty = ir.FunctionType(ir.VoidType(), [_VEC, _VEC.as_pointer(), ir.IntType(32), _MASK])
    fn = cgutils.get_or_insert_function(builder.module, fnty, "llvm.masked.store.v8f64.p0")
    builder.call(fn, [value, pointer, ir.Constant(ir.IntType(32), 8), mask])


def _row_signature(rows, scalars, n):
    if all(_is_row(r) for r in rows) and all(x == types.float64 for x in scalars) and isinstance(n, types.Integer):
        return types.void(*rows, *scalars, n)
    return None


def _row_codegen(n_rows, body, exact):
    """Codegen of ``f(row_0, ..., row_(n_rows - 1), scalars..., n)``: row_0[i] = body(row_0[i],
    ..., scalars) for i < n, CHUNK elements per vector operation (rows contiguous float64;
    their length is not checked).  ``body(builder, loaded rows, splatted scalars)``.
    exact: the last n mod CHUNK elements by a masked operation, nothing beyond element n - 1
    read or written; else n is rounded up to a multiple of CHUNK (the rows must be that
    long; the extra elements are computed on).  A masked store does not forward to a load
    that follows it, so where a row is read right after it was written the rounded form is
    the faster (bernstein rows at d = 42: 4.9 µs, exact 7.6, scalar 6.7)."""

    def codegen(context, builder, signature, args):
        i64 = ir.IntType(64)
        datas = [context.make_array(signature.args[i])(context, builder, args[i]).data for i in range(n_rows)]
        splats = [_splat(builder, x) for x in args[n_rows:-1]]
        n = args[-1]
        n = builder.sext(n, i64) if n.type.width < 64 else n
        if not exact:
            n = builder.add(n, ir.Constant(i64, CHUNK - 1))
        full = builder.sdiv(n, ir.Constant(i64, CHUNK))

        def pointers_at(offset):
            return [builder.bitcast(builder.gep(d, [offset]), _VEC.as_pointer()) for d in datas]

        with cgutils.for_range(builder, full) as loop:
            pointers = pointers_at(builder.mul(loop.index, ir.Constant(i64, CHUNK)))
            values = [builder.load(p, align=8) for p in pointers]
            builder.store(body(builder, values, splats), pointers[0], align=8)
        if exact:
            offset = builder.mul(full, ir.Constant(i64, CHUNK))
            rest = builder.trunc(builder.sub(n, offset), ir.IntType(32))
            with builder.if_then(builder.icmp_signed(">", rest, ir.Constant(ir.IntType(32), 0)), likely=True):
                lanes = ir.Constant(ir.VectorType(ir.IntType(32), CHUNK), list(range(CHUNK)))
                mask = builder.icmp_signed("<", lanes, _splat(builder, rest))
                pointers = pointers_at(offset)
                values = [_masked_load(builder, p, mask) for p in pointers]
                _masked_store(builder, body(builder, values, splats), pointers[0], mask)
        return context.get_dummy_value()

    return codegen


# The row operations of the Bernstein conversions, de Casteljau splits and polynomial
# products (two_bounce): the scalar loop's IEEE operations in the same order, element by
# element, so the results are the scalar loop's bit for bit.


_HALF = ir.Constant(ir.DoubleType(), 0.5)


def _mean(b, v, s):
    return b.fmul(_splat(b, _HALF), b.fadd(v[1], v[2]))


def _add_scaled(b, v, s):
    return b.fadd(v[0], b.fmul(s[0], v[1]))


@intrinsic
def rows_mean(typingctx, dst, x, y, n):
    """dst[i] = 0.5 * (x[i] + y[i]) for i < n rounded up to a multiple of CHUNK."""
    return _row_signature((dst, x, y), (), n), _row_codegen(3, _mean, False)


@intrinsic
def rows_add_scaled(typingctx, dst, x, s, n):
    """dst[i] += s * x[i] for i < n rounded up to a multiple of CHUNK."""
    return _row_signature((dst, x), (s,), n), _row_codegen(2, _add_scaled, False)


@intrinsic
def rows_add_scaled_exact(typingctx, dst, x, s, n):
    """dst[i] += s * x[i] for i < n."""
    return _row_signature((dst, x), (s,), n), _row_codegen(2, _add_scaled, True)


@intrinsic
def rows_scale(typingctx, dst, s, n):
    """dst[i] *= s for i < n rounded up to a multiple of CHUNK."""
    return _row_signature((dst,), (s,), n), _row_codegen(1, lambda b, v, s: b.fmul(v[0], s[0]), False)


@intrinsic
def rows_copy(typingctx, dst, x, n):
    """dst[i] = x[i] for i < n rounded up to a multiple of CHUNK."""
    return _row_signature((dst, x), (), n), _row_codegen(2, lambda b, v, s: v[1], False)


@intrinsic
def shifted_products_difference(typingctx, out, a, x, nx, b, y, ny, terms, n_out):
    """out[k] = Σ_l a[l] x[k - l] - Σ_l b[l] y[k - l] for k < n_out, l < terms, the first sum
    over 0 ≤ k - l ≤ nx and the second over 0 ≤ k - l ≤ ny: two truncated convolutions.
    Per element the scalar loops' operations in their order (0.0, then the a-terms added by
    ascending l, then the b-terms subtracted), CHUNK elements of out at a time in a
    register; x and y are read with masked loads (nothing outside x[0 .. nx], y[0 .. ny]),
    so no store lands on a row that the next operation loads (the row-by-row form, one
    vector operation per l on the output row at offset l, stalled on store forwarding)."""
    if not (_is_row(out) and _is_row(a) and _is_row(x) and _is_row(b) and _is_row(y)
            and all(isinstance(t, types.Integer) for t in (nx, ny, terms, n_out))):
        return None
    sig = types.void(out, a, x, nx, b, y, ny, terms, n_out)

    def codegen(context, builder, signature, args):
        i64 = ir.IntType(64)
        i32 = ir.IntType(32)
        data = [context.make_array(signature.args[i])(context, builder, args[i]).data for i in (0, 1, 2, 4, 5)]
        out_d, a_d, x_d, b_d, y_d = data
        nx_v, ny_v, terms_v, n_v = (builder.sext(v, i64) if v.type.width < 64 else v for v in (args[3], args[6], args[7], args[8]))
        iota = ir.Constant(ir.VectorType(i64, CHUNK), list(range(CHUNK)))
        zero_vec = ir.Constant(_VEC, [0.0] * CHUNK)
        acc_ptr = cgutils.alloca_once(builder, _VEC)
        chunks = builder.sdiv(builder.add(n_v, ir.Constant(i64, CHUNK - 1)), ir.Constant(i64, CHUNK))
        with cgutils.for_range(builder, chunks) as chunk_loop:
            k0 = builder.mul(chunk_loop.index, ir.Constant(i64, CHUNK))
            k_vec = builder.add(_splat(builder, k0), iota)
            in_out = builder.icmp_signed("<", k_vec, _splat(builder, n_v))
            builder.store(zero_vec, acc_ptr)
            for coef_d, src_d, n_src, subtract in ((a_d, x_d, nx_v, False), (b_d, y_d, ny_v, True)):
                with cgutils.for_range(builder, terms_v) as term_loop:
                    l = term_loop.index
                    offset = builder.sub(k0, l)  # x index of lane 0
                    idx = builder.add(_splat(builder, offset), iota)
                    valid = builder.and_(in_out, builder.and_(
                        builder.icmp_signed(">=", idx, ir.Constant(ir.VectorType(i64, CHUNK), [0] * CHUNK)),
                        builder.icmp_signed("<=", idx, _splat(builder, n_src))))
                    pointer = builder.bitcast(builder.gep(src_d, [offset]), _VEC.as_pointer())
                    values = _masked_load(builder, pointer, valid)
                    coef = _splat(builder, builder.load(builder.gep(coef_d, [l])))
                    acc = builder.load(acc_ptr)
                    product = builder.fmul(coef, values)
                    new = builder.fsub(acc, product) if subtract else builder.fadd(acc, product)
                    builder.store(builder.select(valid, new, acc), acc_ptr)
            out_pointer = builder.bitcast(builder.gep(out_d, [k0]), _VEC.as_pointer())
            _masked_store(builder, builder.load(acc_ptr), out_pointer, in_out)
        return context.get_dummy_value()

    return sig, codegen


def _transpose8(builder, rows):
    """The 8 x 8 transpose of eight <8 x double> rows in three rounds of shuffles (pairs of
    elements, then of pairs, then of quadruples)."""
    def shuffle(x, y, mask):
        return builder.shuffle_vector(x, y, ir.Constant(ir.VectorType(ir.IntType(32), 8), mask))

    t = []
    for i in range(0, 8, 2):
        t.append(shuffle(rows[i], rows[i + 1], [0, 8, 2, 10, 4, 12, 6, 14]))
        t.append(shuffle(rows[i], rows[i + 1], [1, 9, 3, 11, 5, 13, 7, 15]))
    s = [None] * 8
    for base in (0, 4):
        for odd in (0, 1):
            x, y = t[base + odd], t[base + 2 + odd]
            s[base + odd] = shuffle(x, y, [0, 1, 8, 9, 4, 5, 12, 13])
            s[base + 2 + odd] = shuffle(x, y, [2, 3, 10, 11, 6, 7, 14, 15])
    out = [None] * 8
    for c in range(4):
        out[c] = shuffle(s[c], s[c + 4], [0, 1, 2, 3, 8, 9, 10, 11])
        out[c + 4] = shuffle(s[c], s[c + 4], [4, 5, 6, 7, 12, 13, 14, 15])
    return out


@intrinsic
def transpose_blocks(typingctx, src, dst, blocks):
    """dst[j, i] = src[i, j] for i, j < CHUNK * blocks, by CHUNK x CHUNK blocks in
    registers (the element-wise loop is one scalar load and store per element).  src and
    dst: C-contiguous 2-D float64 arrays, distinct, at least CHUNK * blocks rows and
    columns (not checked)."""
    if not (isinstance(src, types.Array) and isinstance(dst, types.Array) and src.ndim == 2 and dst.ndim == 2
            and src.dtype == types.float64 and dst.dtype == types.float64 and src.layout == "C" and dst.layout == "C"
            and isinstance(blocks, types.Integer)):
        return None
    assert CHUNK == 8
    sig = types.void(src, dst, blocks)

    def codegen(context, builder, signature, args):
        i64 = ir.IntType(64)
        src_a = context.make_array(signature.args[0])(context, builder, args[0])
        dst_a = context.make_array(signature.args[1])(context, builder, args[1])
        src_cols = cgutils.unpack_tuple(builder, src_a.shape, 2)[1]
        dst_cols = cgutils.unpack_tuple(builder, dst_a.shape, 2)[1]
        blocks_v = builder.sext(args[2], i64) if args[2].type.width < 64 else args[2]

        def pointer(array, cols, row, col):
            return builder.bitcast(builder.gep(array.data, [builder.add(builder.mul(row, cols), col)]), _VEC.as_pointer())

        with cgutils.for_range(builder, blocks_v) as bi_loop:
            with cgutils.for_range(builder, blocks_v) as bj_loop:
                r0 = builder.mul(bi_loop.index, ir.Constant(i64, 8))
                c0 = builder.mul(bj_loop.index, ir.Constant(i64, 8))
                rows = [builder.load(pointer(src_a, src_cols, builder.add(r0, ir.Constant(i64, r)), c0), align=8)
                        for r in range(8)]
                for c, column in enumerate(_transpose8(builder, rows)):
                    builder.store(column, pointer(dst_a, dst_cols, builder.add(c0, ir.Constant(i64, c)), r0), align=8)
        return context.get_dummy_value()

    return sig, codegen
