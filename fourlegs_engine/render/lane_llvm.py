"""The LLVM vector code numba compiles for the lane functions of :mod:`.lane_kernels` (``overload``).

Each ``@intrinsic`` here emits one chunk row's work on ``<LANES x double>`` values with llvmlite's IR
builder — loads and stores of whole rows of the tile planes, masks instead of branches, ``llvm.ctpop``
for the stop counts, ``llvm.masked.compressstore`` for fragments, a polynomial exp — in the order of the
plain-Python reference, operation for operation, so that both give the same bits. LLVM lowers the
vectors to the machine's widest registers (two AVX-512 registers per vector here, four AVX2 ones, …).
Imported by :mod:`.blend_kernels` (numba installed) before any kernel compiles.
"""
from __future__ import annotations

import numpy as np
from llvmlite import ir
from numba import types
from numba.core import cgutils
from numba.extending import intrinsic, overload

from .lane_kernels import (EXP_LIMIT, GEOMETRY_SUMS, LANES, _EXP_TAYLOR, _LN2_HIGH, _LN2_LOW, _LOG2_E, blend_lanes,
                           fragment_lanes, gradient_lanes, prefetch, prefetch_for_write, start_lanes)

#: bytes the CPU loads at a time (a prefetch touches one address per line)
CACHE_LINE = 64


def _vector_helpers(builder):
    """Constructors for <LANES x double> / <LANES x i64> values in ``builder``."""
    f64, i64, i32 = ir.DoubleType(), ir.IntType(64), ir.IntType(32)
    vec, ivec = ir.VectorType(f64, LANES), ir.VectorType(i64, LANES)
    zeros = ir.Constant(ir.VectorType(i32, LANES), [0] * LANES)

    def splat(value, vector_type):
        one = builder.insert_element(ir.Constant(vector_type, ir.Undefined), value, ir.Constant(i32, 0))
        return builder.shuffle_vector(one, ir.Constant(vector_type, ir.Undefined), zeros)

    return vec, ivec, splat


def _vector_pointer(context, builder, array_type, array, offset, element_type):
    data = context.make_array(array_type)(context, builder, array).data
    return builder.bitcast(builder.gep(data, [offset]), ir.VectorType(element_type, LANES).as_pointer())


def _lane_rule_ir(builder, gauss, t_before, n_lanes, alpha_floor, alpha_max, transmittance_min):
    """The vector form of :func:`_lane_rule`: (T to store, w, stop mask, blend mask, α after the clamp)."""
    vec, ivec, splat = _vector_helpers(builder)
    amax = splat(alpha_max, vec)
    alpha = builder.select(builder.fcmp_ordered("<", gauss, amax), gauss, amax)
    zero = ir.Constant(vec, [0.0] * LANES)
    in_chunk = builder.icmp_signed("<", ir.Constant(ivec, list(range(LANES))), splat(n_lanes, ivec))
    ok = builder.and_(builder.and_(in_chunk, builder.fcmp_ordered(">", t_before, zero)),
                      builder.fcmp_ordered(">", alpha, splat(alpha_floor, vec)))
    after = builder.fmul(t_before, builder.fsub(ir.Constant(vec, [1.0] * LANES), alpha))
    low = builder.fcmp_ordered("<", after, splat(transmittance_min, vec))
    stop = builder.and_(ok, low)
    blend = builder.and_(ok, builder.not_(low))
    t_new = builder.select(stop, builder.fneg(t_before), builder.select(blend, after, t_before))
    weight = builder.select(blend, builder.fmul(alpha, t_before), zero)
    return t_new, weight, stop, blend, alpha


def _advance_ir(context, builder, lanes_type, lanes, step):
    """α ← α·ratio, ratio ← ratio·step in ``lanes``; returns the α vector before the update."""
    vec, _, splat = _vector_helpers(builder)
    f64, i64 = ir.DoubleType(), ir.IntType(64)
    gauss_ptr = _vector_pointer(context, builder, lanes_type, lanes, ir.Constant(i64, 0), f64)
    ratio_ptr = _vector_pointer(context, builder, lanes_type, lanes, ir.Constant(i64, LANES), f64)
    gauss = builder.load(gauss_ptr, align=8)
    ratio = builder.load(ratio_ptr, align=8)
    builder.store(builder.fmul(gauss, ratio), gauss_ptr, align=8)
    builder.store(builder.fmul(ratio, splat(step, vec)), ratio_ptr, align=8)
    return gauss


def _row_ir(context, builder, sig, trans_index, lanes_index, trans, lanes, base, step, n_lanes, alpha_floor,
            alpha_max, transmittance_min):
    """The part every lane function shares: advance the α recurrence in ``lanes``, apply the lane rule to
    the T row at ``base`` and store its new T. Returns (w, stop mask, blend mask, α after the clamp)."""
    gauss = _advance_ir(context, builder, sig.args[lanes_index], lanes, step)
    t_ptr = _vector_pointer(context, builder, sig.args[trans_index], trans, base, ir.DoubleType())
    t_new, weight, stop, blend, alpha = _lane_rule_ir(builder, gauss, builder.load(t_ptr, align=8), n_lanes,
                                                      alpha_floor, alpha_max, transmittance_min)
    builder.store(t_new, t_ptr, align=8)
    return weight, stop, blend, alpha


def _declare(builder, name, function_type):
    """The LLVM intrinsic ``name`` of the builder's module (declared on first use)."""
    function = builder.module.globals.get(name)
    return function if function is not None else ir.Function(builder.module, function_type, name=name)


def _any(builder, mask):
    """Whether any lane of the <LANES x i1> ``mask`` is set (an i1)."""
    bits = builder.bitcast(mask, ir.IntType(LANES))
    return builder.icmp_unsigned("!=", bits, ir.Constant(ir.IntType(LANES), 0))


def _popcount(builder, mask):
    count = builder.module.declare_intrinsic("llvm.ctpop", [ir.IntType(LANES)])
    return builder.zext(builder.call(count, [builder.bitcast(mask, ir.IntType(LANES))]), ir.IntType(64))


def _compress_store(builder, values, pointer, mask):
    """llvm.masked.compressstore: the masked lanes of ``values`` stored one after another at ``pointer``."""
    element = values.type.element
    suffix = {ir.DoubleType(): "f64", ir.FloatType(): "f32", ir.IntType(64): "i64"}[element]
    function = _declare(builder, f"llvm.masked.compressstore.v{LANES}{suffix}",
                        ir.FunctionType(ir.VoidType(), [values.type, element.as_pointer(), mask.type]))
    builder.call(function, [values, builder.bitcast(pointer, element.as_pointer()), mask])


def _channel_pointer(context, builder, planes_type, planes, channel, base):
    """<LANES x double>* at planes[channel, base] of a C-contiguous (C, P) float64 array."""
    view = context.make_array(planes_type)(context, builder, planes)
    plane_size = builder.extract_value(view.shape, 1)
    offset = builder.add(builder.mul(channel, plane_size), base)
    return builder.bitcast(builder.gep(view.data, [offset]), ir.VectorType(ir.DoubleType(), LANES).as_pointer())


def _value(context, builder, vals_type, vals, channel):
    """vals[channel] as a double (vals a 1-D float array, any stride)."""
    view = context.make_array(vals_type)(context, builder, vals)
    stride = builder.extract_value(view.strides, 0)
    address = builder.add(builder.ptrtoint(view.data, ir.IntType(64)), builder.mul(channel, stride))
    element = context.get_value_type(vals_type.dtype)
    value = builder.load(builder.inttoptr(address, element.as_pointer()))
    return value if element == ir.DoubleType() else builder.fpext(value, ir.DoubleType())


def _channel_count(context, builder, planes_type, planes):
    return builder.extract_value(context.make_array(planes_type)(context, builder, planes).shape, 0)


@intrinsic
def _blend_lanes_ir(typingctx, trans, planes, lanes, base, n_lanes, step, vals, alpha_floor, alpha_max,
                    transmittance_min):
    signature = types.int64(trans, planes, lanes, base, n_lanes, step, vals, alpha_floor, alpha_max,
                            transmittance_min)

    def codegen(context, builder, sig, args):
        trans_a, planes_a, lanes_a, base_v, n_lanes_v, step_v, vals_a, floor_v, amax_v, tmin_v = args
        vec, _, splat = _vector_helpers(builder)
        weight, stop, blend, _ = _row_ir(context, builder, sig, 0, 2, trans_a, lanes_a, base_v, step_v, n_lanes_v,
                                         floor_v, amax_v, tmin_v)
        with builder.if_then(_any(builder, blend)):  # a row where nothing blends leaves the sums alone
            with cgutils.for_range(builder, _channel_count(context, builder, sig.args[1], planes_a)) as loop:
                ptr = _channel_pointer(context, builder, sig.args[1], planes_a, loop.index, base_v)
                value = _value(context, builder, sig.args[6], vals_a, loop.index)
                builder.store(builder.fadd(builder.load(ptr, align=8), builder.fmul(weight, splat(value, vec))),
                              ptr, align=8)
        return _popcount(builder, stop)

    return signature, codegen


@intrinsic
def _fragment_lanes_ir(typingctx, trans, lanes, base, n_lanes, step, pixel_base, frag_pixel, frag_weight,
                       frag_alpha, n_frag, alpha_floor, alpha_max, transmittance_min):
    result = types.UniTuple(types.int64, 2)
    signature = result(trans, lanes, base, n_lanes, step, pixel_base, frag_pixel, frag_weight, frag_alpha, n_frag,
                       alpha_floor, alpha_max, transmittance_min)

    def codegen(context, builder, sig, args):
        (trans_a, lanes_a, base_v, n_lanes_v, step_v, pixel_base_v, pixel_a, weight_a, alpha_a, n_frag_v, floor_v,
         amax_v, tmin_v) = args
        _, ivec, splat = _vector_helpers(builder)
        weight, stop, blend, alpha = _row_ir(context, builder, sig, 0, 1, trans_a, lanes_a, base_v, step_v,
                                             n_lanes_v, floor_v, amax_v, tmin_v)
        pixels = builder.add(splat(pixel_base_v, ivec), ir.Constant(ivec, list(range(LANES))))
        for array_type, array, values in ((sig.args[6], pixel_a, pixels), (sig.args[7], weight_a, weight),
                                          (sig.args[8], alpha_a, alpha)):
            if isinstance(array_type, types.NoneType):
                continue
            element = context.get_value_type(array_type.dtype)
            if values.type.element != element:
                values = builder.fptrunc(values, ir.VectorType(element, LANES))
            data = context.make_array(array_type)(context, builder, array).data
            _compress_store(builder, values, builder.gep(data, [n_frag_v]), blend)
        count = builder.add(n_frag_v, _popcount(builder, blend))
        return context.make_tuple(builder, result, [count, _popcount(builder, stop)])

    return signature, codegen


@intrinsic
def _gradient_lanes_ir(typingctx, trans, grads, total, prefix, lanes, base, n_lanes, step, vals, dx_first, dy,
                       sums, alpha_floor, alpha_max, transmittance_min):
    signature = types.int64(trans, grads, total, prefix, lanes, base, n_lanes, step, vals, dx_first, dy, sums,
                            alpha_floor, alpha_max, transmittance_min)

    def codegen(context, builder, sig, args):
        (trans_a, grads_a, total_a, prefix_a, lanes_a, base_v, n_lanes_v, step_v, vals_a, dx_first_v, dy_v,
         sums_a, floor_v, amax_v, tmin_v) = args
        vec, _, splat = _vector_helpers(builder)
        f64, i64 = ir.DoubleType(), ir.IntType(64)
        zero = ir.Constant(vec, [0.0] * LANES)

        def plane(index, array):
            return _vector_pointer(context, builder, sig.args[index], array, base_v, f64)

        sums_data = context.make_array(sig.args[11])(context, builder, sums_a).data

        def sums_row(row):
            offset = builder.mul(row, ir.Constant(i64, LANES))
            return builder.bitcast(builder.gep(sums_data, [offset]), vec.as_pointer())

        def accumulate(row, mask, term):
            ptr = sums_row(row)
            current = builder.load(ptr, align=8)
            builder.store(builder.select(mask, builder.fadd(current, term), current), ptr, align=8)

        weight, stop, blend, alpha = _row_ir(context, builder, sig, 0, 4, trans_a, lanes_a, base_v, step_v,
                                             n_lanes_v, floor_v, amax_v, tmin_v)
        dot_slot = cgutils.alloca_once_value(builder, zero)
        with builder.if_then(_any(builder, blend)):  # a row where nothing blends adds nothing
            channels = _channel_count(context, builder, sig.args[1], grads_a)
            with cgutils.for_range(builder, channels) as loop:
                grad = builder.load(_channel_pointer(context, builder, sig.args[1], grads_a, loop.index, base_v),
                                    align=8)
                value = _value(context, builder, sig.args[8], vals_a, loop.index)
                dot = builder.fadd(builder.load(dot_slot), builder.fmul(grad, splat(value, vec)))
                builder.store(dot, dot_slot)
                accumulate(builder.add(loop.index, ir.Constant(i64, GEOMETRY_SUMS)), blend,
                           builder.fmul(weight, grad))
            dot = builder.load(dot_slot)
            prefix_ptr = plane(3, prefix_a)
            prefix_old = builder.load(prefix_ptr, align=8)
            prefix_new = builder.fadd(prefix_old, builder.fmul(weight, dot))
            builder.store(builder.select(blend, prefix_new, prefix_old), prefix_ptr, align=8)
            unclamped = builder.and_(blend, builder.fcmp_ordered("<", alpha, splat(amax_v, vec)))
            one = ir.Constant(vec, [1.0] * LANES)
            d_alpha = builder.fsub(builder.fmul(builder.fdiv(weight, alpha), dot),
                                   builder.fdiv(builder.fsub(builder.load(plane(2, total_a), align=8), prefix_new),
                                                builder.fsub(one, alpha)))
            d_power = builder.fmul(d_alpha, alpha)
            dx = builder.fadd(splat(dx_first_v, vec), ir.Constant(vec, [float(lane) for lane in range(LANES)]))
            dy_vec = splat(dy_v, vec)
            terms = (d_power, builder.fmul(d_power, dx), builder.fmul(d_power, dy_vec),
                     builder.fmul(builder.fmul(d_power, dx), dx), builder.fmul(builder.fmul(d_power, dx), dy_vec),
                     builder.fmul(builder.fmul(d_power, dy_vec), dy_vec))
            for row, term in enumerate(terms):
                accumulate(ir.Constant(i64, row), unclamped, term)
        return _popcount(builder, stop)

    return signature, codegen


def _prefetch_intrinsic(write: int):
    """An intrinsic (array, row, byte offset) -> llvm.prefetch of that address, for reading (write 0)
    or writing (1), kept in every cache level."""
    @intrinsic
    def prefetch_address(typingctx, array, row, byte_offset):
        def codegen(context, builder, sig, args):
            view = context.make_array(sig.args[0])(context, builder, args[0])
            stride = builder.extract_value(view.strides, 0)
            address = builder.add(builder.ptrtoint(view.data, ir.IntType(64)),
                                  builder.add(builder.mul(args[1], stride), args[2]))
            i8_ptr = ir.IntType(8).as_pointer()
            i32 = ir.IntType(32)
            hint = _declare(builder, "llvm.prefetch.p0", ir.FunctionType(ir.VoidType(), [i8_ptr, i32, i32, i32]))
            builder.call(hint, [builder.inttoptr(address, i8_ptr), ir.Constant(i32, write), ir.Constant(i32, 3),
                                ir.Constant(i32, 1)])
            return context.get_dummy_value()

        return types.none(array, types.int64, types.int64), codegen
    return prefetch_address


_prefetch_read_ir = _prefetch_intrinsic(0)
_prefetch_write_ir = _prefetch_intrinsic(1)


@overload(prefetch, inline="always")
def _prefetch_overload(array, row):
    def implementation(array, row):
        for offset in range(0, array.strides[0], CACHE_LINE):
            _prefetch_read_ir(array, np.int64(row), np.int64(offset))
    return implementation


@overload(prefetch_for_write, inline="always")
def _prefetch_for_write_overload(array, row):
    def implementation(array, row):
        for offset in range(0, array.strides[0], CACHE_LINE):
            _prefetch_write_ir(array, np.int64(row), np.int64(offset))
    return implementation


def _exp_ir(builder, x):
    """The vector code of :func:`exp_lanes` (the same operations in the same order)."""
    vec, ivec, splat = _vector_helpers(builder)

    def constant(value):
        return ir.Constant(vec, [float(value)] * LANES)

    low, high = constant(-EXP_LIMIT), constant(EXP_LIMIT)
    x = builder.select(builder.fcmp_ordered(">", x, low), x, low)
    x = builder.select(builder.fcmp_ordered("<", x, high), x, high)
    rint = _declare(builder, f"llvm.rint.v{LANES}f64", ir.FunctionType(vec, [vec]))
    n = builder.call(rint, [builder.fmul(x, constant(_LOG2_E))])
    r = builder.fsub(builder.fsub(x, builder.fmul(n, constant(_LN2_HIGH))), builder.fmul(n, constant(_LN2_LOW)))
    poly = constant(_EXP_TAYLOR[-1])
    for coefficient in _EXP_TAYLOR[-2::-1]:
        poly = builder.fadd(builder.fmul(poly, r), constant(coefficient))
    exponent = builder.shl(builder.fptosi(n, ivec), ir.Constant(ivec, [52] * LANES))
    return builder.bitcast(builder.add(builder.bitcast(poly, ivec), exponent), vec)


@intrinsic
def _start_lanes_ir(typingctx, lanes, mx, my, a, b, c, log_o, cx, cy):
    signature = types.none(lanes, mx, my, a, b, c, log_o, cx, cy)

    def codegen(context, builder, sig, args):
        lanes_a, mx_v, my_v, a_v, b_v, c_v, log_o_v, cx_v, cy_v = args
        vec, ivec, splat = _vector_helpers(builder)
        f64, i64 = ir.DoubleType(), ir.IntType(64)
        half = ir.Constant(f64, 0.5)
        columns = builder.sitofp(builder.add(splat(cx_v, ivec), ir.Constant(ivec, list(range(LANES)))), vec)
        dx = builder.fsub(builder.fadd(columns, splat(half, vec)), splat(mx_v, vec))
        dy = builder.fsub(builder.fadd(builder.sitofp(cy_v, f64), half), my_v)
        quadratic = builder.fadd(
            builder.fadd(builder.fmul(builder.fmul(splat(a_v, vec), dx), dx),
                         builder.fmul(builder.fmul(splat(builder.fmul(ir.Constant(f64, 2.0), b_v), vec), dx),
                                      splat(dy, vec))),
            splat(builder.fmul(builder.fmul(c_v, dy), dy), vec))
        exponent = builder.fsub(splat(log_o_v, vec), builder.fmul(splat(half, vec), quadratic))
        step = builder.fsub(builder.fneg(builder.fadd(builder.fmul(splat(b_v, vec), dx),
                                                      splat(builder.fmul(c_v, dy), vec))),
                            splat(builder.fmul(half, c_v), vec))
        builder.store(_exp_ir(builder, exponent),
                      _vector_pointer(context, builder, sig.args[0], lanes_a, ir.Constant(i64, 0), f64), align=8)
        builder.store(_exp_ir(builder, step),
                      _vector_pointer(context, builder, sig.args[0], lanes_a, ir.Constant(i64, LANES), f64),
                      align=8)
        return context.get_dummy_value()

    return signature, codegen


@overload(start_lanes, inline="always")
def _start_lanes_overload(lanes, mx, my, a, b, c, log_o, cx, cy):
    def implementation(lanes, mx, my, a, b, c, log_o, cx, cy):
        _start_lanes_ir(lanes, np.float64(mx), np.float64(my), np.float64(a), np.float64(b), np.float64(c),
                        np.float64(log_o), np.int64(cx), np.int64(cy))
    return implementation


@overload(blend_lanes, inline="always")
def _blend_lanes_overload(trans, planes, lanes, base, n_lanes, step, vals, alpha_floor, alpha_max,
                          transmittance_min):
    def implementation(trans, planes, lanes, base, n_lanes, step, vals, alpha_floor, alpha_max,
                       transmittance_min):
        return _blend_lanes_ir(trans, planes, lanes, np.int64(base), np.int64(n_lanes), np.float64(step), vals,
                               np.float64(alpha_floor), np.float64(alpha_max), np.float64(transmittance_min))
    return implementation


@overload(fragment_lanes, inline="always")
def _fragment_lanes_overload(trans, lanes, base, n_lanes, step, pixel_base, frag_pixel, frag_weight, frag_alpha,
                             n_frag, alpha_floor, alpha_max, transmittance_min):
    def implementation(trans, lanes, base, n_lanes, step, pixel_base, frag_pixel, frag_weight, frag_alpha, n_frag,
                       alpha_floor, alpha_max, transmittance_min):
        return _fragment_lanes_ir(trans, lanes, np.int64(base), np.int64(n_lanes), np.float64(step),
                                  np.int64(pixel_base), frag_pixel, frag_weight, frag_alpha, np.int64(n_frag),
                                  np.float64(alpha_floor), np.float64(alpha_max), np.float64(transmittance_min))
    return implementation
@overload(gradient_lanes, inline="always")
def _gradient_lanes_overload(trans, grads, total, prefix, lanes, base, n_lanes, step, vals, dx_first, dy, sums,
                             alpha_floor, alpha_max, transmittance_min):
    def implementation(trans, grads, total, prefix, lanes, base, n_lanes, step, vals, dx_first, dy, sums,
                       alpha_floor, alpha_max, transmittance_min):
        return _gradient_lanes_ir(trans, grads, total, prefix, lanes, np.int64(base), np.int64(n_lanes),
                                  np.float64(step), vals, np.float64(dx_first), np.float64(dy), sums,
                                  np.float64(alpha_floor), np.float64(alpha_max), np.float64(transmittance_min))
    return implementation
