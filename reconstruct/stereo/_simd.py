"""16-lane vectors for numba kernels (private).

``U16x16``, ``U32x16``, ``F32x16`` (and 8-lane float) values in SIMD registers, so a
step over 16 disparity levels is a few vector instructions (LLVM's vectoriser would
leave short searches scalar: docs/matching.md). Integers wrap like numpy's, min/max
compare unsigned, floats are plain IEEE (bit-identical to the scalar loop). Loads
and stores take a C-contiguous 1-D array and an element index, unaligned and
unchecked (callers keep ``i + 16 <= len``). After editing this module update
_SIMD_SHA256 in _match_kernels.py (a test demands it) so numba recompiles the kernels.
"""

from __future__ import annotations

from llvmlite import ir
from numba.core import cgutils, types
from numba.extending import intrinsic, models, register_model

__all__ = [
    "F32x8",
    "F32x16",
    "U16x16",
    "U32x16",
    "U64x16",
    "v8f_acc64",
    "v8f_broadcast",
    "v8f_fma",
    "v8f_load",
    "v8f_zero",
    "v16_add",
    "v16_broadcast",
    "v16_fill_bits",
    "v16_fill_range",
    "v16_keys",
    "v16_lane",
    "v16_load",
    "v16_load_num",
    "v16_load_u8",
    "v16_lt",
    "v16_max",
    "v16_min",
    "v16_mul",
    "v16_narrow",
    "v16_popcount",
    "v16_reduce_min",
    "v16_reverse",
    "v16_slide",
    "v16_store",
    "v16_store_u8",
    "v16_sub",
    "v16_to_f32",
    "v16_to_u16",
    "v16_xor",
    "v16_zero",
]

_LANES = 16
_I32 = ir.IntType(32)


class _VecType(types.Type):
    """A vector of ``lanes`` (16 unless said) ``kind`` ("u" unsigned integer or "f"
    float) ``bits``-bit elements."""

    def __init__(self, kind: str, bits: int, lanes: int = _LANES) -> None:
        self.kind = kind
        self.bits = bits
        self.lanes = lanes
        super().__init__(name=f"{kind}{bits}x{lanes}")

    @property
    def scalar(self) -> types.Type:
        return types.float32 if self.kind == "f" else getattr(types, f"uint{self.bits}")


U16x16 = _VecType("u", 16)
U32x16 = _VecType("u", 32)
U64x16 = _VecType("u", 64)
F32x16 = _VecType("f", 32)
F32x8 = _VecType("f", 32, 8)  # the 8-lane float ops at the end of the module


def _lane_type(vt: _VecType) -> ir.Type:
    return ir.FloatType() if vt.kind == "f" else ir.IntType(vt.bits)


def _llvm(vt: _VecType) -> ir.VectorType:
    return ir.VectorType(_lane_type(vt), vt.lanes)


@register_model(_VecType)
class _VecModel(models.PrimitiveModel):
    def __init__(self, dmm, fe_type):
        super().__init__(dmm, fe_type, _llvm(fe_type))


def _vec(x: types.Type) -> _VecType | None:
    return x if isinstance(x, _VecType) else None


def _array_vec(arr: types.Type) -> _VecType | None:
    """The vector type matching a C-contiguous 1-D uint16/32/64 or float32 array."""
    if not (isinstance(arr, types.Array) and arr.ndim == 1 and arr.layout in "CF"):
        return None
    return {types.uint16: U16x16, types.uint32: U32x16, types.uint64: U64x16,
            types.float32: F32x16}.get(arr.dtype)


def _is_u8_array(arr: types.Type) -> bool:
    return (isinstance(arr, types.Array) and arr.ndim == 1 and arr.layout in "CF"
            and arr.dtype == types.uint8)


def _elem_ptr(context, builder, arrty, arr, idxty, idx):
    ary = context.make_array(arrty)(context, builder, arr)
    return builder.gep(ary.data, [context.cast(builder, idx, idxty, types.intp)])


def _splat(builder, value, vt: _VecType):
    """A vector of ``vt`` with every lane the (already lane-typed) ``value``."""
    undef = ir.Constant(_llvm(vt), ir.Undefined)
    vec = builder.insert_element(undef, value, ir.Constant(_I32, 0))
    return builder.shuffle_vector(vec, undef, ir.Constant(ir.VectorType(_I32, vt.lanes),
                                                          [0] * vt.lanes))


def _call(builder, name: str, ret: ir.Type, args: list) -> ir.Value:
    fnty = ir.FunctionType(ret, [a.type for a in args])
    fn = cgutils.get_or_insert_function(builder.module, fnty, name)
    return builder.call(fn, args)


def _load(context, builder, sig, args, ty: ir.VectorType):
    """Unaligned load of an LLVM vector ``ty`` from ``arr[idx]`` (the first two args)."""
    ptr = _elem_ptr(context, builder, sig.args[0], args[0], sig.args[1], args[1])
    return builder.load(builder.bitcast(ptr, ty.as_pointer()), align=1)


def _loader(name: str, vec_of, doc: str):
    """A load intrinsic ``name(arr, idx)``: the vector ``vec_of(arr)`` (None: not for
    this array) at ``arr[idx]``; from a uint8 array, zero-extended lanes."""

    def typer(typingctx, arr, idx):  # pragma: no cover - compiled by numba
        vt = vec_of(arr)
        if vt is None or not isinstance(idx, types.Integer):
            return None
        u8 = _is_u8_array(arr)

        def codegen(context, builder, sig, args):
            if u8:
                v8 = _load(context, builder, sig, args, ir.VectorType(ir.IntType(8), vt.lanes))
                return builder.zext(v8, _llvm(vt))
            return _load(context, builder, sig, args, _llvm(vt))

        return vt(arr, idx), codegen

    typer.__name__ = name
    typer.__doc__ = doc
    return intrinsic(typer)


v16_load = _loader("v16_load", _array_vec,
                   "``arr[idx:idx + 16]`` (uint16/32/64 or float32 array) as a vector.")
v16_load_u8 = _loader("v16_load_u8", lambda arr: U16x16 if _is_u8_array(arr) else None,
                      "``arr[idx:idx + 16]`` of a uint8 array, zero-extended to a ``U16x16``.")
v16_load_num = _loader(
    "v16_load_num", lambda arr: U16x16 if _is_u8_array(arr) else _array_vec(arr),
    "``arr[idx:idx + 16]`` of a uint8 (zero-extended to ``U16x16``), uint16/32/64 or "
    "float32 array: pixel values of either image type.")


@intrinsic
def v16_store(typingctx, arr, idx, v):  # pragma: no cover - compiled by numba
    """``arr[idx:idx + 16] = v`` (the array's dtype must be ``v``'s lane type)."""
    vt = _vec(v)
    if vt is None or _array_vec(arr) is not vt or not isinstance(idx, types.Integer):
        return None

    def codegen(context, builder, sig, args):
        ptr = _elem_ptr(context, builder, sig.args[0], args[0], sig.args[1], args[1])
        builder.store(args[2], builder.bitcast(ptr, _llvm(vt).as_pointer()), align=1)
        return context.get_dummy_value()

    return types.none(arr, idx, v), codegen


@intrinsic
def v16_store_u8(typingctx, arr, idx, v):  # pragma: no cover - compiled by numba
    """``arr[idx:idx + 16] = v`` for a ``U16x16`` into a uint8 array (truncating)."""
    if _vec(v) is not U16x16 or not _is_u8_array(arr) or not isinstance(idx, types.Integer):
        return None

    def codegen(context, builder, sig, args):
        ptr = _elem_ptr(context, builder, sig.args[0], args[0], sig.args[1], args[1])
        v8ty = ir.VectorType(ir.IntType(8), _LANES)
        builder.store(builder.trunc(args[2], v8ty), builder.bitcast(ptr, v8ty.as_pointer()),
                      align=1)
        return context.get_dummy_value()

    return types.none(arr, idx, v), codegen


@intrinsic
def v16_broadcast(typingctx, like, x):  # pragma: no cover - compiled by numba
    """A vector of ``like``'s type with every lane ``x`` (cast like numpy's
    ``astype``: integers truncate)."""
    vt = _vec(like)
    if vt is None or not isinstance(x, (types.Integer, types.Float)):
        return None

    def codegen(context, builder, sig, args):
        return _splat(builder, context.cast(builder, args[1], sig.args[1], vt.scalar), vt)

    return vt(like, x), codegen


_INT_OPS = {"add": "add", "sub": "sub", "mul": "mul", "xor": "xor", "min": "umin",
            "max": "umax"}
_FLOAT_OPS = {"add": "fadd", "sub": "fsub", "mul": "fmul", "min": "minnum",
              "max": "maxnum"}


def _binary(op: str):
    """A lane-wise binary intrinsic on two vectors of one type."""

    def typer(typingctx, a, b):  # pragma: no cover - compiled by numba
        vt = _vec(a)
        if vt is None or _vec(b) is not vt or (vt.kind == "f" and op not in _FLOAT_OPS):
            return None

        def codegen(context, builder, sig, args):
            x, y = args
            if vt.kind == "f":
                if op in ("min", "max"):
                    return _call(builder, f"llvm.{_FLOAT_OPS[op]}.v{_LANES}f32", x.type, [x, y])
                return getattr(builder, _FLOAT_OPS[op])(x, y)
            if op in ("min", "max"):
                return _call(builder, f"llvm.{_INT_OPS[op]}.v{_LANES}i{vt.bits}", x.type, [x, y])
            return getattr(builder, _INT_OPS[op])(x, y)

        return vt(a, b), codegen

    typer.__name__ = f"v16_{op}"
    return intrinsic(typer)


v16_add = _binary("add")
v16_sub = _binary("sub")
v16_mul = _binary("mul")
v16_xor = _binary("xor")
v16_min = _binary("min")
v16_max = _binary("max")


def _unary(name: str, accepts, result, emit, doc: str):
    """A one-vector intrinsic: vectors ``vt`` for which ``accepts(vt)`` holds give the
    type ``result(vt)``, built by ``emit(builder, x, vt)``."""

    def typer(typingctx, v):  # pragma: no cover - compiled by numba
        vt = _vec(v)
        if vt is None or not accepts(vt):
            return None

        def codegen(context, builder, sig, args):
            return emit(builder, args[0], vt)

        return result(vt)(v), codegen

    typer.__name__ = name
    typer.__doc__ = doc
    return intrinsic(typer)


def _unsigned(vt: _VecType) -> bool:
    return vt.kind == "u"


v16_popcount = _unary(
    "v16_popcount", _unsigned, lambda vt: vt,
    lambda builder, x, vt: _call(builder, f"llvm.ctpop.v{_LANES}i{vt.bits}", _llvm(vt), [x]),
    "Set bits of every lane of an unsigned vector.")


def _conversion(name: str, accepts, result: _VecType, op: str, doc: str):
    """A lane-wise conversion intrinsic: vectors for which ``accepts(vt)`` holds become
    ``result`` by the LLVM cast ``op`` (``trunc``, ``uitofp``, ``fptoui``)."""
    return _unary(name, accepts, lambda vt: result,
                  lambda builder, x, vt: getattr(builder, op)(x, _llvm(result)), doc)


v16_narrow = _conversion(
    "v16_narrow", lambda vt: vt in (U32x16, U64x16), U16x16, "trunc",
    "``U32x16`` / ``U64x16`` -> ``U16x16``, keeping the low 16 bits of every lane.")
v16_to_f32 = _conversion(
    "v16_to_f32", lambda vt: vt.kind == "u", F32x16, "uitofp",
    "Unsigned integer vector -> ``F32x16`` (exact below 2**24).")
v16_to_u16 = _conversion(
    "v16_to_u16", lambda vt: vt is F32x16, U16x16, "fptoui",
    "``F32x16`` -> ``U16x16``, truncating toward zero like ``np.uint16(x)`` (lanes must "
    "lie in [0, 65536)).")


v16_reduce_min = _unary(
    "v16_reduce_min", _unsigned, lambda vt: vt.scalar,
    lambda builder, x, vt: _call(builder, f"llvm.vector.reduce.umin.v{_LANES}i{vt.bits}",
                                 _lane_type(vt), [x]),
    "The smallest lane of an unsigned vector, as its scalar type.")


@intrinsic
def v16_fill_range(typingctx, v, lo, hi, x):  # pragma: no cover - compiled by numba
    """``v`` with the lanes ``lo <= i <= hi`` (lane indices 0..15; the bounds may lie
    outside that range) replaced by ``x``."""
    vt = _vec(v)
    if vt is None or not all(isinstance(t, types.Integer) for t in (lo, hi)) or not (
            isinstance(x, (types.Integer, types.Float))):
        return None

    def codegen(context, builder, sig, args):
        i64 = ir.IntType(64)
        vi32 = _llvm(_VecType("u", 32))

        def clamped(k):  # bound k as a splat of int32 in [-1, 16]
            b = context.cast(builder, args[k], sig.args[k], types.int64)
            b = builder.select(builder.icmp_signed("<", b, ir.Constant(i64, -1)),
                               ir.Constant(i64, -1), b)
            b = builder.select(builder.icmp_signed(">", b, ir.Constant(i64, _LANES)),
                               ir.Constant(i64, _LANES), b)
            return _splat(builder, builder.trunc(b, _I32), _VecType("u", 32))

        iota = ir.Constant(vi32, list(range(_LANES)))
        inside = builder.and_(builder.icmp_signed(">=", iota, clamped(1)),
                              builder.icmp_signed("<=", iota, clamped(2)))
        fill = _splat(builder, context.cast(builder, args[3], sig.args[3], vt.scalar), vt)
        return builder.select(inside, fill, args[0])

    return vt(v, lo, hi, x), codegen


@intrinsic
def v16_keys(typingctx, v, base):  # pragma: no cover - compiled by numba
    """``U32x16`` sort keys ``(v[i] << 16) | (base + i)`` of a ``U16x16``: the
    unsigned minimum of keys is the smallest value and, among equals, its first lane
    (``base + i`` must fit 16 bits)."""
    if _vec(v) is not U16x16 or not isinstance(base, types.Integer):
        return None

    def codegen(context, builder, sig, args):
        wide = builder.shl(builder.zext(args[0], _llvm(U32x16)),
                           ir.Constant(_llvm(U32x16), [16] * _LANES))
        b = builder.trunc(context.cast(builder, args[1], sig.args[1], types.int64), _I32)
        lanes = builder.add(_splat(builder, b, U32x16),
                            ir.Constant(_llvm(U32x16), list(range(_LANES))))
        return builder.or_(wide, lanes)

    return U32x16(v, base), codegen


@intrinsic
def v16_zero(typingctx, arr):  # pragma: no cover - compiled by numba
    """A zero vector of the element type of ``arr`` (a uint16/32/64 or float32 array)."""
    vt = _array_vec(arr)
    if vt is None:
        return None

    def codegen(context, builder, sig, args):
        return ir.Constant(_llvm(vt), None)

    return vt(arr), codegen


@intrinsic
def v16_lt(typingctx, a, b, like):  # pragma: no cover - compiled by numba
    """1 in the lanes where ``a < b`` (unsigned or ordered float compare), else 0, as a
    vector of ``like``'s (unsigned) type."""
    vt = _vec(a)
    lt = _vec(like)
    if vt is None or _vec(b) is not vt or lt is None or lt.kind != "u":
        return None

    def codegen(context, builder, sig, args):
        if vt.kind == "f":
            m = builder.fcmp_ordered("<", args[0], args[1])
        else:
            m = builder.icmp_unsigned("<", args[0], args[1])
        return builder.zext(m, _llvm(lt))

    return lt(a, b, like), codegen


def _reversed(builder, x, vt: _VecType):
    mask = ir.Constant(ir.VectorType(_I32, _LANES), list(range(_LANES - 1, -1, -1)))
    return builder.shuffle_vector(x, ir.Constant(_llvm(vt), ir.Undefined), mask)


v16_reverse = _unary("v16_reverse", lambda vt: True, lambda vt: vt, _reversed,
                     "The lanes of ``v`` in reverse order.")


# ------------------------------------------------------------- 8-lane float32 ops
# For small fixed-size sums (the six Lucas-Kanade window products of one pixel).


def _is_f32_array(arr: types.Type) -> bool:
    return (isinstance(arr, types.Array) and arr.ndim == 1 and arr.layout in "CF"
            and arr.dtype == types.float32)


v8f_load = _loader("v8f_load", lambda arr: F32x8 if _is_f32_array(arr) else None,
                   "``arr[idx:idx + 8]`` of a float32 array as an ``F32x8``.")


@intrinsic
def v8f_zero(typingctx):  # pragma: no cover - compiled by numba
    """An ``F32x8`` of zeros."""

    def codegen(context, builder, sig, args):
        return ir.Constant(_llvm(F32x8), None)

    return F32x8(), codegen


@intrinsic
def v8f_broadcast(typingctx, x):  # pragma: no cover - compiled by numba
    """An ``F32x8`` with every lane ``x`` (cast to float32)."""
    if not isinstance(x, (types.Integer, types.Float)):
        return None

    def codegen(context, builder, sig, args):
        return _splat(builder, context.cast(builder, args[0], sig.args[0], types.float32),
                      F32x8)

    return F32x8(x), codegen


@intrinsic
def v8f_fma(typingctx, a, b, c):  # pragma: no cover - compiled by numba
    """``a * b + c`` lane-wise: fused (one rounding) where the CPU has FMA, else a
    multiply and an add -- what a scalar loop compiled with fast-math "contract"
    does (LLVM ``fmuladd``)."""
    if not (_vec(a) is F32x8 and _vec(b) is F32x8 and _vec(c) is F32x8):
        return None

    def codegen(context, builder, sig, args):
        return _call(builder, "llvm.fmuladd.v8f32", _llvm(F32x8), list(args))

    return F32x8(a, b, c), codegen


@intrinsic
def v8f_acc64(typingctx, arr, idx, v, sign):  # pragma: no cover - compiled by numba
    """``arr[idx:idx + 8] += sign * float64(v)`` for a float64 array (the products are
    rounded to float64 lane by lane, then added, as the scalar loop does)."""
    if not (isinstance(arr, types.Array) and arr.ndim == 1 and arr.layout in "CF"
            and arr.dtype == types.float64 and isinstance(idx, types.Integer)
            and _vec(v) is F32x8 and isinstance(sign, (types.Float, types.Integer))):
        return None

    def codegen(context, builder, sig, args):
        f64x8 = ir.VectorType(ir.DoubleType(), 8)
        ptr = _elem_ptr(context, builder, sig.args[0], args[0], sig.args[1], args[1])
        vptr = builder.bitcast(ptr, f64x8.as_pointer())
        s = context.cast(builder, args[3], sig.args[3], types.float64)
        undef = ir.Constant(f64x8, ir.Undefined)
        sv = builder.shuffle_vector(builder.insert_element(undef, s, ir.Constant(_I32, 0)),
                                    undef, ir.Constant(ir.VectorType(_I32, 8), [0] * 8))
        prod = builder.fmul(sv, builder.fpext(args[2], f64x8))
        builder.store(builder.fadd(builder.load(vptr, align=1), prod), vptr, align=1)
        return context.get_dummy_value()

    return types.none(arr, idx, v, sign), codegen


@intrinsic
def v16_slide(typingctx, v, prev):  # pragma: no cover - compiled by numba
    """``[prev[15], v[0], ..., v[14]]``: the lanes of ``v`` moved up by one, the top
    lane of ``prev`` coming in at the bottom (a sliding window over several vectors)."""
    vt = _vec(v)
    if vt is None or _vec(prev) is not vt:
        return None

    def codegen(context, builder, sig, args):
        mask = ir.Constant(ir.VectorType(_I32, _LANES), [_LANES - 1 + i for i in range(_LANES)])
        return builder.shuffle_vector(args[1], args[0], mask)

    return vt(v, prev), codegen


@intrinsic
def v16_lane(typingctx, v, i):  # pragma: no cover - compiled by numba
    """Lane ``i`` (0..15, unchecked) of ``v`` as its scalar type."""
    vt = _vec(v)
    if vt is None or not isinstance(i, types.Integer):
        return None

    def codegen(context, builder, sig, args):
        idx = builder.trunc(context.cast(builder, args[1], sig.args[1], types.int64), _I32)
        return builder.extract_element(args[0], idx)

    return vt.scalar(v, i), codegen


@intrinsic
def v16_fill_bits(typingctx, v, bits, x):  # pragma: no cover - compiled by numba
    """``v`` with the lanes ``i`` whose bit ``i`` of ``bits`` is set replaced by ``x``
    (a blend under a mask register on AVX-512)."""
    vt = _vec(v)
    if vt is None or not isinstance(bits, types.Integer) or not isinstance(
            x, (types.Integer, types.Float)):
        return None

    def codegen(context, builder, sig, args):
        b16 = builder.trunc(context.cast(builder, args[1], sig.args[1], types.int64),
                            ir.IntType(_LANES))
        mask = builder.bitcast(b16, ir.VectorType(ir.IntType(1), _LANES))
        fill = _splat(builder, context.cast(builder, args[2], sig.args[2], vt.scalar), vt)
        return builder.select(mask, fill, args[0])

    return vt(v, bits, x), codegen
