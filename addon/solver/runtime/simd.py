"""Vector operations for the hot loops that LLVM will not vectorise on its own.

Numba runs LLVM's loop vectoriser but not its SLP vectoriser (off by default since numba
0.57 after miscompilations), and a loop whose trip count is a small constant is unrolled
before the loop vectoriser sees it: ``for i in range(16): row[i] -= f[i] * x`` becomes 16
scalar multiply-subtracts, and with ``f`` in another array LLVM cannot prove the two do
not overlap.  Where it does vectorise (rows of a runtime length), it adds runtime overlap
checks and a scalar remainder, and a row that the next operation reads right after a
store stalls on store forwarding.  The intrinsics here emit the vector instructions
directly, as generic LLVM vector IR (any x86-64 or other target lowers it; CHUNK = 8
doubles is one AVX-512 register or two AVX ones): whole-row updates, an 8 x 8 block
transpose, a min/max reduction, the de Casteljau halves, a pivot search.

Each does the scalar loop's IEEE operations on each element (a multiply, then an add: no
fused multiply-add, no reassociation), so results are the scalar loop's bit for bit; the
exceptions are named where they occur (the order of a min/max reduction, which can only
change the sign of a zero; the de Casteljau halvings deferred, exact short of subnormals).
two_bounce's users are checked against their scalar forms on random cases.
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


def _is_matrix(t):
    return isinstance(t, types.Array) and t.dtype == types.float64 and t.layout == "C" and t.ndim == 2


def _as_i64(builder, v):
    return builder.sext(v, ir.IntType(64)) if v.type.width < 64 else v


def _vector_at(builder, array, row, col):
    """Pointer to the CHUNK elements array[row, col:col + CHUNK] of a C-contiguous matrix."""
    cols = cgutils.unpack_tuple(builder, array.shape, 2)[1]
    return builder.bitcast(builder.gep(array.data, [builder.add(builder.mul(row, cols), col)]), _VEC.as_pointer())


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
        n = _as_i64(builder, args[-1])
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


def _add_scaled(b, v, s):
    return b.fadd(v[0], b.fmul(s[0], v[1]))


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
def rows_scale_add(typingctx, dst, x, s, n):
    """dst[i] = dst[i] * s + x[i] for i < n rounded up to a multiple of CHUNK (one Horner
    step on a whole coefficient vector)."""
    return _row_signature((dst, x), (s,), n), _row_codegen(2, lambda b, v, s: b.fadd(b.fmul(v[0], s[0]), v[1]), False)


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
    if not (_is_matrix(src) and _is_matrix(dst) and isinstance(blocks, types.Integer)):
        return None
    assert CHUNK == 8
    sig = types.void(src, dst, blocks)

    def codegen(context, builder, signature, args):
        i64 = ir.IntType(64)
        src_a = context.make_array(signature.args[0])(context, builder, args[0])
        dst_a = context.make_array(signature.args[1])(context, builder, args[1])
        blocks_v = _as_i64(builder, args[2])
        with cgutils.for_range(builder, blocks_v) as bi_loop:
            with cgutils.for_range(builder, blocks_v) as bj_loop:
                r0 = builder.mul(bi_loop.index, ir.Constant(i64, 8))
                c0 = builder.mul(bj_loop.index, ir.Constant(i64, 8))
                rows = [builder.load(_vector_at(builder, src_a, builder.add(r0, ir.Constant(i64, r)), c0), align=8)
                        for r in range(8)]
                for c, column in enumerate(_transpose8(builder, rows)):
                    builder.store(column, _vector_at(builder, dst_a, builder.add(c0, ir.Constant(i64, c)), r0), align=8)
        return context.get_dummy_value()

    return sig, codegen


def _fold_lanes(builder, vec, op):
    """The lane of vec that wins ``fcmp_ordered(op, lane, best)`` from lane 0 up (op "<": the
    minimum, ">": the maximum; a NaN lane never wins, and a NaN in lane 0 is never replaced:
    the callers' lanes start at ±inf or 0 and take only ordered winners, so hold none)."""
    best = builder.extract_element(vec, ir.Constant(ir.IntType(32), 0))
    for i in range(1, CHUNK):
        x = builder.extract_element(vec, ir.Constant(ir.IntType(32), i))
        best = builder.select(builder.fcmp_ordered(op, x, best), x, best)
    return best


SMALL_BOX_DEGREE = CHUNK - 1  # the largest degree small_box_range takes (its rows fit one vector)


@intrinsic
def small_box_range(typingctx, p, d, u0, v0, w, R):
    """(min, max) of the tensor Bernstein coefficients of p (p[i, j] u^i v^j, total degree
    1 ≤ d ≤ SMALL_BOX_DEGREE) over the box [u0, u0 + w] × [v0, v0 + w], R the power ->
    Bernstein weights of degree d: two_bounce.prepass's ``tensor_bernstein_box`` then
    ``square_min_max_abs`` with every row in a register.  Each degree's steps are unrolled
    (a switch on d): the Taylor shift and scaling along u, a transpose, along v, a transpose,
    the weights along u, a transpose, along v — the row operations' arithmetic on each
    element in their order (so the same coefficients bit for bit; the min/max the loop's
    comparisons, up to the sign of a zero).  The box ranges of the pre-pass's hit and band
    tests (degrees 1 to 8, ~24 per random TT tuple) were ~0.6-0.8 µs each through memory.
    Returns (nan, nan) for a degree outside 1 .. SMALL_BOX_DEGREE."""
    if not (_is_matrix(p) and _is_matrix(R) and isinstance(d, types.Integer)
            and all(x == types.float64 for x in (u0, v0, w))):
        return None
    result = types.UniTuple(types.float64, 2)
    sig = result(p, d, u0, v0, w, R)

    def codegen(context, builder, signature, args):
        i64 = ir.IntType(64)
        dbl = ir.DoubleType()
        p_arr = context.make_array(signature.args[0])(context, builder, args[0])
        r_arr = context.make_array(signature.args[5])(context, builder, args[5])
        r_cols = cgutils.unpack_tuple(builder, r_arr.shape, 2)[1]
        d_v = _as_i64(builder, args[1])
        u0_v, v0_v, w_v = args[2], args[3], args[4]
        zero = ir.Constant(_VEC, [0.0] * CHUNK)
        nan = ir.Constant(dbl, float("nan"))
        lo_ptr = cgutils.alloca_once_value(builder, nan)
        hi_ptr = cgutils.alloca_once_value(builder, nan)
        end = builder.append_basic_block("small_box.end")
        switch = builder.switch(d_v, end)

        def shift(A, deg, s):
            # _shift_rows: Taylor shift by s, then row i scaled by w^i
            sv = _splat(builder, s)
            for k in range(deg):
                for i in range(deg - 1, k - 1, -1):
                    A[i] = _add_scaled(builder, (A[i], A[i + 1]), (sv,))
            f = ir.Constant(dbl, 1.0)
            for i in range(deg + 1):
                A[i] = builder.fmul(A[i], _splat(builder, f))
                f = builder.fmul(f, w_v)

        def weights(A, deg):
            # _bernstein_rows: B[k] = 0 + Σ_(i ≤ k) R[k, i] A[i], i ascending
            B = []
            for k in range(deg + 1):
                acc = zero
                for i in range(k + 1):
                    r = builder.load(builder.gep(r_arr.data, [builder.add(builder.mul(ir.Constant(i64, k), r_cols),
                                                                          ir.Constant(i64, i))]))
                    acc = _add_scaled(builder, (acc, A[i]), (_splat(builder, r),))
                B.append(acc)
            return B + [zero] * (CHUNK - deg - 1)

        for deg in range(1, CHUNK):
            block = builder.append_basic_block(f"small_box.d{deg}")
            switch.add_case(ir.Constant(i64, deg), block)
            builder.position_at_end(block)
            A = []
            for i in range(CHUNK):
                if i <= deg:  # the triangle: p[i, j] for j ≤ deg - i, zeros beyond
                    mask = ir.Constant(_MASK, [j <= deg - i for j in range(CHUNK)])
                    A.append(_masked_load(builder, _vector_at(builder, p_arr, ir.Constant(i64, i), ir.Constant(i64, 0)), mask))
                else:
                    A.append(zero)
            shift(A, deg, u0_v)
            A = _transpose8(builder, A)
            shift(A, deg, v0_v)
            A = _transpose8(builder, A)
            A = _transpose8(builder, weights(A, deg))
            C = weights(A, deg)
            inf = float("inf")
            lo = ir.Constant(_VEC, [inf] * CHUNK)
            hi = ir.Constant(_VEC, [-inf] * CHUNK)
            valid = ir.Constant(_MASK, [j <= deg for j in range(CHUNK)])
            for k in range(deg + 1):
                lo = builder.select(builder.and_(valid, builder.fcmp_ordered("<", C[k], lo)), C[k], lo)
                hi = builder.select(builder.and_(valid, builder.fcmp_ordered(">", C[k], hi)), C[k], hi)
            builder.store(_fold_lanes(builder, lo, "<"), lo_ptr)
            builder.store(_fold_lanes(builder, hi, ">"), hi_ptr)
            builder.branch(end)
        builder.position_at_end(end)
        return context.make_tuple(builder, result, [builder.load(lo_ptr), builder.load(hi_ptr)])

    return sig, codegen


@intrinsic
def square_min_max_abs(typingctx, c, d):
    """(min, max, max |.|) of c[i, j] for i, j ≤ d (c: C-contiguous 2-D float64, at least
    d + 1 rows and columns, not checked): each row by vectors of CHUNK elements, the tail
    masked.  The loop's comparisons (x < lo, x > hi: a NaN is skipped); the order of the
    elements differs, which changes nothing but the sign of a zero result."""
    if not (_is_matrix(c) and isinstance(d, types.Integer)):
        return None
    result = types.UniTuple(types.float64, 3)
    sig = result(c, d)

    def codegen(context, builder, signature, args):
        i64 = ir.IntType(64)
        array = context.make_array(signature.args[0])(context, builder, args[0])
        n = builder.add(_as_i64(builder, args[1]), ir.Constant(i64, 1))
        inf = float("inf")
        lo_ptr = cgutils.alloca_once_value(builder, ir.Constant(_VEC, [inf] * CHUNK))
        hi_ptr = cgutils.alloca_once_value(builder, ir.Constant(_VEC, [-inf] * CHUNK))
        big_ptr = cgutils.alloca_once_value(builder, ir.Constant(_VEC, [0.0] * CHUNK))
        fabs = cgutils.get_or_insert_function(builder.module, ir.FunctionType(_VEC, [_VEC]), "llvm.fabs.v8f64")
        chunks = builder.sdiv(builder.add(n, ir.Constant(i64, CHUNK - 1)), ir.Constant(i64, CHUNK))
        iota = ir.Constant(ir.VectorType(i64, CHUNK), list(range(CHUNK)))
        with cgutils.for_range(builder, n) as row_loop:
            with cgutils.for_range(builder, chunks) as chunk_loop:
                j0 = builder.mul(chunk_loop.index, ir.Constant(i64, CHUNK))
                valid = builder.icmp_signed("<", builder.add(_splat(builder, j0), iota), _splat(builder, n))
                x = _masked_load(builder, _vector_at(builder, array, row_loop.index, j0), valid)
                lo, hi, big = builder.load(lo_ptr), builder.load(hi_ptr), builder.load(big_ptr)
                take_lo = builder.and_(valid, builder.fcmp_ordered("<", x, lo))
                take_hi = builder.and_(valid, builder.fcmp_ordered(">", x, hi))
                ax = builder.call(fabs, [x])
                take_big = builder.and_(valid, builder.fcmp_ordered(">", ax, big))
                builder.store(builder.select(take_lo, x, lo), lo_ptr)
                builder.store(builder.select(take_hi, x, hi), hi_ptr)
                builder.store(builder.select(take_big, ax, big), big_ptr)
        lo, hi, big = builder.load(lo_ptr), builder.load(hi_ptr), builder.load(big_ptr)
        lo_s, hi_s, big_s = _fold_lanes(builder, lo, "<"), _fold_lanes(builder, hi, ">"), _fold_lanes(builder, big, ">")
        return context.make_tuple(builder, result, [lo_s, hi_s, big_s])

    return sig, codegen


@intrinsic
def casteljau_halves(typingctx, src, d, left, right):
    """The de Casteljau halves at the midpoint along the rows of src (rows 0 .. d, columns
    0 .. d rounded up to whole CHUNKs: all three arrays C-contiguous 2-D float64 with at
    least that many rows and columns, distinct, not checked): left[k] = Σ_i C(k, i) src[i] / 2^k
    over i ≤ k, right[d - r] likewise from the other end.

    The level-r rows 0.5 (x[k - 1] + x[k]) are kept unscaled, S_r[k] = S_(r-1)[k - 1] +
    S_(r-1)[k], and each output row is multiplied by 2^-r once at the end: a power of two
    commutes with rounding, so this is the halving loop's result bit for bit (short of
    subnormal values), with one addition per element and level instead of an addition and
    a multiplication.  Column chunks one at a time, two levels per sweep with the rows in
    flight carried in registers (one load and one store per step of two levels).  d = 42:
    ~1.5x faster than the halving loop on whole rows."""
    if not (_is_matrix(src) and _is_matrix(left) and _is_matrix(right) and isinstance(d, types.Integer)):
        return None
    sig = types.void(src, d, left, right)

    def codegen(context, builder, signature, args):
        i64 = ir.IntType(64)
        src_a = context.make_array(signature.args[0])(context, builder, args[0])
        left_a = context.make_array(signature.args[2])(context, builder, args[2])
        right_a = context.make_array(signature.args[3])(context, builder, args[3])
        d_v = _as_i64(builder, args[1])
        one = ir.Constant(i64, 1)

        def at(array, row, col):
            return _vector_at(builder, array, row, col)

        chunks = builder.sdiv(builder.add(d_v, ir.Constant(i64, CHUNK)), ir.Constant(i64, CHUNK))
        carry_ptr = cgutils.alloca_once(builder, _VEC)
        with cgutils.for_range(builder, chunks) as chunk_loop:
            col = builder.mul(chunk_loop.index, ir.Constant(i64, CHUNK))
            with cgutils.for_range(builder, builder.add(d_v, one)) as copy_loop:
                builder.store(builder.load(at(src_a, copy_loop.index, col), align=8), at(left_a, copy_loop.index, col), align=8)
            builder.store(builder.load(at(left_a, d_v, col), align=8), at(right_a, d_v, col), align=8)
            # levels two at a time (r, r + 1): a step loads one row, adds twice and stores
            # the level-(r + 1) row; S_r[k] and the row below are carried in registers
            prev_ptr = cgutils.alloca_once(builder, _VEC)
            with cgutils.for_range(builder, builder.sdiv(d_v, ir.Constant(i64, 2))) as pair_loop:
                r = builder.add(builder.mul(pair_loop.index, ir.Constant(i64, 2)), one)
                top = builder.load(at(left_a, d_v, col), align=8)
                below = builder.load(at(left_a, builder.sub(d_v, one), col), align=8)
                s_top = builder.fadd(below, top)  # S_r[d]
                builder.store(s_top, at(right_a, builder.sub(d_v, r), col), align=8)
                builder.store(s_top, prev_ptr)
                builder.store(below, carry_ptr)
                with cgutils.for_range(builder, builder.sub(d_v, r)) as row_loop:
                    k = builder.sub(builder.sub(d_v, one), row_loop.index)  # d - 1 .. r
                    below = builder.load(at(left_a, builder.sub(k, one), col), align=8)
                    s_k = builder.fadd(below, builder.load(carry_ptr))  # S_r[k]
                    s_up = builder.fadd(s_k, builder.load(prev_ptr))  # S_(r+1)[k + 1]
                    builder.store(s_up, at(left_a, builder.add(k, one), col), align=8)
                    with builder.if_then(builder.icmp_signed("==", row_loop.index, ir.Constant(i64, 0))):
                        builder.store(s_up, at(right_a, builder.sub(builder.sub(d_v, r), one), col), align=8)
                    builder.store(s_k, prev_ptr)
                    builder.store(below, carry_ptr)
                builder.store(builder.load(prev_ptr), at(left_a, r, col), align=8)  # S_r[r]
            # d odd: the last level (r = d) alone
            with builder.if_then(builder.icmp_signed("==", builder.srem(d_v, ir.Constant(i64, 2)), one)):
                last = builder.fadd(builder.load(at(left_a, builder.sub(d_v, one), col), align=8),
                                    builder.load(at(left_a, d_v, col), align=8))
                builder.store(last, at(left_a, d_v, col), align=8)
                builder.store(last, at(right_a, ir.Constant(i64, 0), col), align=8)
            # the halvings: left row k and right row d - k by 2^-k
            scale_ptr = cgutils.alloca_once_value(builder, ir.Constant(ir.DoubleType(), 1.0))
            with cgutils.for_range(builder, builder.add(d_v, one)) as k_loop:
                k = k_loop.index
                s = _splat(builder, builder.load(scale_ptr))
                for array, row in ((left_a, k), (right_a, builder.sub(d_v, k))):
                    pointer = at(array, row, col)
                    builder.store(builder.fmul(builder.load(pointer, align=8), s), pointer, align=8)
                builder.store(builder.fmul(builder.load(scale_ptr), ir.Constant(ir.DoubleType(), 0.5)), scale_ptr)
        return context.get_dummy_value()

    return sig, codegen


@intrinsic
def lanes_abs_argmax(typingctx, row, floor, lanes):
    """(top, p): top the largest of floor and |row[i]| (i < lanes, a compile-time constant
    given as a literal), p the first lane holding it, -1 when no |row[i]| exceeds floor —
    what ``for i: x = abs(row[i]); if x > top: top, p = x, i`` returns (NaN lanes skipped),
    without its serial chain of compares and its mispredicted branches: a tree of vector
    maxima and the first set bit of a vector compare."""
    if not (_is_row(row) and floor == types.float64 and isinstance(lanes, types.IntegerLiteral)):
        return None
    width = lanes.literal_value
    result = types.Tuple((types.float64, types.int64))
    sig = result(row, floor, lanes)

    def codegen(context, builder, signature, args):
        i64 = ir.IntType(64)
        vec_type = ir.VectorType(ir.DoubleType(), width)
        data = context.make_array(signature.args[0])(context, builder, args[0]).data
        values = builder.load(builder.bitcast(data, vec_type.as_pointer()), align=8)
        fabs = cgutils.get_or_insert_function(builder.module, ir.FunctionType(vec_type, [vec_type]), f"llvm.fabs.v{width}f64")
        magnitude = builder.call(fabs, [values])
        floor_vec = ir.Constant(vec_type, ir.Undefined)
        for i in range(width):
            floor_vec = builder.insert_element(floor_vec, args[1], ir.Constant(ir.IntType(32), i))
        # lanes not above the floor (NaN included) count as the floor
        clipped = builder.select(builder.fcmp_ordered(">", magnitude, floor_vec), magnitude, floor_vec)
        top = clipped
        size = width
        while size > 1:
            half = size // 2
            lo = builder.shuffle_vector(top, top, ir.Constant(ir.VectorType(ir.IntType(32), half), list(range(half))))
            hi = builder.shuffle_vector(top, top, ir.Constant(ir.VectorType(ir.IntType(32), half), list(range(half, size))))
            top = builder.select(builder.fcmp_ordered(">", hi, lo), hi, lo)
            size = half
        top = builder.extract_element(top, ir.Constant(ir.IntType(32), 0))
        top_vec = ir.Constant(vec_type, ir.Undefined)
        for i in range(width):
            top_vec = builder.insert_element(top_vec, top, ir.Constant(ir.IntType(32), i))
        hits = builder.bitcast(builder.fcmp_ordered("==", magnitude, top_vec), ir.IntType(width))
        cttz = cgutils.get_or_insert_function(builder.module, ir.FunctionType(ir.IntType(width), [ir.IntType(width), ir.IntType(1)]),
                                              f"llvm.cttz.i{width}")
        first = builder.zext(builder.call(cttz, [hits, ir.Constant(ir.IntType(1), 0)]), i64)
        above = builder.fcmp_ordered(">", top, args[1])
        index = builder.select(above, first, ir.Constant(i64, -1))
        return context.make_tuple(builder, result, [top, index])

    return sig, codegen
