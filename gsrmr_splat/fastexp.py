"""A float32 exp(−σ) that LLVM can vectorise (numba's ``math.exp`` is a libm call per element): :func:`exp_neg`."""

from __future__ import annotations

from llvmlite import ir
import numba as nb
from numba import types
from numba.extending import intrinsic
import numpy as np

EXP_ARG_MIN = np.float32(-30.0)
_LOG2E = np.float32(1.4426950408889634)
_HALF = np.float32(0.5)
_ONE = np.float32(1.0)
_ZERO = np.float32(0.0)
# ln(2)^k / k!, k = 1..6: the Taylor series of 2^f
_C1, _C2, _C3 = np.float32(0.6931471805599453), np.float32(0.2402265069591007), np.float32(0.05550410866482158)
_C4, _C5, _C6 = np.float32(0.009618129107628477), np.float32(0.0013333558146428443), np.float32(1.5403530393381608e-4)
_BIAS = np.int32(127)
_MANTISSA_BITS = np.int32(23)


@intrinsic
def _int32_bits_as_float32(typingctx, bits):
    """Reinterpret an int32's bits as a float32 (an LLVM bitcast: no memory round trip)."""
    sig = types.float32(types.int32)

    def codegen(context, builder, signature, args):
        return builder.bitcast(args[0], ir.FloatType())

    return sig, codegen


@nb.njit(inline="always", fastmath=True, cache=True)
def exp_neg(x):
    """exp(x) for float32 x, clamped to [:data:`EXP_ARG_MIN`, 0]; relative error ≤ 4e-6 (a test checks it).

    The clamp: above 0 means σ < 0, which a positive-definite conic reaches only by rounding, so it is taken as
    σ = 0; below −30 the value (< 1e-13) is far under the 1/255 alpha cut, and clamping keeps every product normal
    (denormal float32 arithmetic is slow) and finite. Range reduction x·log2(e) = n + f with −½ ≤ f ≤ ½; 2^f by its
    degree-6 Taylor polynomial (truncation error < 2e-7); 2^n built in the exponent bits. The float32 rounding of
    x·log2(e) dominates the error. No libm call and no branch, so LLVM vectorises the loops that call it.
    """
    t = min(max(x, EXP_ARG_MIN), _ZERO) * _LOG2E
    n = np.int32(t - _HALF)  # t ≤ 0: truncation toward zero of t − ½ rounds t to the nearest integer
    f = t - np.float32(n)
    p = _ONE + f * (_C1 + f * (_C2 + f * (_C3 + f * (_C4 + f * (_C5 + f * _C6)))))
    return p * _int32_bits_as_float32((n + _BIAS) << _MANTISSA_BITS)


@nb.njit(cache=True, fastmath=True)
def exp_neg_array(x, out):
    """``out[i] = exp_neg(x[i])`` (float32 arrays; for tests and benchmarks)."""
    for i in range(x.shape[0]):
        out[i] = exp_neg(x[i])
