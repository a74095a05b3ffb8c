"""Compiled kernels for a residual MLP: the values of one configuration or a small batch (one matrix product a
layer), and one configuration's value with the Jacobian.

At batch size 1 numpy spends most of a net's time dispatching a dozen small operations, and TorchScript
more; these numba kernels do the features, the layers and the output scaling in one call (most of what is
left is the two 256x256 products of a 256x3 net, which BLAS does). The Jacobian's backward pass takes the
three outputs' gradients through each layer as three matrix-vector products, several times faster than
numba's float32 ``(3, 256) @ (256, 256)ᵀ``. The maths is the net's own (``calibration/nets.py``): features
``[(q − centre) / half span, sin q, cos q]`` for the joints, float32 layers, then ``y · scale + mean`` in
float64. The joint-1 turn stays with the caller.

A net is packed once (:func:`pack`) into one float32 array holding each layer's weight matrix ``(in, out)``
and bias, every ensemble member's layers one after another, and a table of where each lies: numba unboxes
typed lists of arrays at every call, a large share of a small net's time. Activation codes: see
``ACTIVATIONS``.
Compiled on first use and cached on disk next to this file (or in numba's user cache where that is not
writable): a fresh checkout compiles in a few seconds, once.
"""

from __future__ import annotations

import math

import numba
import numpy as np
from numba.typed import List  # inside the kernels only

ACTIVATIONS = {"linear": 0, "SiLU": 1, "Tanh": 2, "ReLU": 3}
# Float reassociation lets the reductions vectorise; no "ninf"/"nnan": SiLU's exp overflows to inf on purpose.
_FLAGS = {"reassoc", "contract", "nsz", "arcp"}


@numba.njit(cache=True, nogil=True, fastmath=_FLAGS)
def _act(v: np.float32, code: int) -> tuple[np.float32, np.float32]:
    """An activation's value and slope at ``v``."""
    one = np.float32(1.0)
    if code == 1:
        s = one / (one + np.float32(math.exp(-v)))
        y = v * s
        return y, s + y * (one - s)
    if code == 2:
        y = np.float32(math.tanh(v))
        return y, one - y * y
    if code == 3:
        return (v, one) if v > 0 else (np.float32(0.0), np.float32(0.0))
    return v, one


@numba.njit(cache=True, nogil=True, fastmath=_FLAGS)
def _features(q, center, half_span, n_joints, sincos):
    k = q.shape[0]
    x = np.empty(k + 2 * n_joints if sincos else k, dtype=np.float32)
    for i in range(k):
        x[i] = np.float32((q[i] - center[i]) / half_span[i])
    if sincos:
        for i in range(n_joints):
            x[k + i] = np.float32(math.sin(q[i]))
            x[k + n_joints + i] = np.float32(math.cos(q[i]))
    return x


@numba.njit(cache=True, nogil=True, fastmath=_FLAGS)
def _layer(y, w, b, code, slope):
    """``act(y @ w + b)``; its slope into ``slope`` (same length) when that is not empty."""
    out = np.dot(y, w) + b  # BLAS: faster than a loop numba would vectorise
    n_out = out.shape[0]
    if code != 0 or slope.shape[0]:
        for j in range(n_out):
            v, s = _act(out[j], code)
            out[j] = v
            if slope.shape[0]:
                slope[j] = s
    return out


@numba.njit(cache=True, nogil=True)
def _weight(flat, layout, layer):
    """Layer ``layer``'s weight matrix ``(in, out)``, a view into ``flat``."""
    at, rows, cols = layout[layer, 0], layout[layer, 1], layout[layer, 2]
    return flat[at : at + rows * cols].reshape((rows, cols))


@numba.njit(cache=True, nogil=True)
def _bias(flat, layout, layer):
    at = layout[layer, 3]
    return flat[at : at + layout[layer, 2]]


@numba.njit(cache=True, nogil=True, fastmath=_FLAGS)
def mlp_values(q, center, half_span, n_joints, sincos, flat, layout, codes, members, scale, mean):
    """The residuals ``(B, 3)`` float64 at inputs ``q (B, k)`` (joints, then condition columns): the mean of
    ``members`` MLPs whose layers lie one member after another in ``flat``/``layout``/``codes`` (:func:`pack`).
    One row through matrix-vector products; several through one matrix product a layer (BLAS's sgemm, faster
    than row by row), whose sums may differ from a row's in the last float32 bit."""
    per = layout.shape[0] // members
    none = np.empty(0, dtype=np.float32)
    rows = q.shape[0]
    out = np.empty((rows, 3))
    if rows == 1:
        x = _features(q[0], center, half_span, n_joints, sincos)
        total = np.zeros(3)
        for m in range(members):
            y = x
            for layer in range(m * per, (m + 1) * per):
                y = _layer(y, _weight(flat, layout, layer), _bias(flat, layout, layer), codes[layer], none)
            for j in range(3):
                total[j] += y[j]
        for j in range(3):
            out[0, j] = total[j] / members * scale[j] + mean[j]
        return out
    x = np.empty((rows, layout[0, 1]), dtype=np.float32)
    for row in range(rows):
        x[row] = _features(q[row], center, half_span, n_joints, sincos)
    total = np.zeros((rows, 3))
    for m in range(members):
        y = x
        for layer in range(m * per, (m + 1) * per):
            y = np.dot(y, _weight(flat, layout, layer))
            b, code = _bias(flat, layout, layer), codes[layer]
            for row in range(rows):
                for j in range(y.shape[1]):
                    y[row, j] = _act(y[row, j] + b[j], code)[0]
        for row in range(rows):
            for j in range(3):
                total[row, j] += y[row, j]
    for row in range(rows):
        for j in range(3):
            out[row, j] = total[row, j] / members * scale[j] + mean[j]
    return out


@numba.njit(cache=True, nogil=True, fastmath=_FLAGS)
def mlp_value_and_jacobian(q, center, half_span, n_joints, sincos, flat, layout, codes, members, scale, mean):
    """One input's :func:`mlp_values` ``(3,)`` and its derivative ``(3, k)`` in the inputs, by reverse mode:
    the three outputs' gradients go back through each layer as three matrix-vector products (the module
    docstring says why not one ``(3, width)`` product), then through the features by the chain rule."""
    x = _features(q, center, half_span, n_joints, sincos)
    per = layout.shape[0] // members
    total = np.zeros(3)
    grad = np.zeros((3, x.shape[0]))
    for m in range(members):
        y = x
        slopes = List()
        for layer in range(m * per, (m + 1) * per):
            slope = np.empty(layout[layer, 2], dtype=np.float32)
            y = _layer(y, _weight(flat, layout, layer), _bias(flat, layout, layer), codes[layer], slope)
            slopes.append(slope)
        g = np.zeros((3, 3), dtype=np.float32)  # d(outputs)/d(this layer's outputs)
        for j in range(3):
            g[j, j] = np.float32(1.0)
            total[j] += y[j]
        for layer in range((m + 1) * per - 1, m * per - 1, -1):
            w, slope = _weight(flat, layout, layer), slopes[layer - m * per]
            back = np.empty((3, w.shape[0]), dtype=np.float32)
            for r in range(3):
                for j in range(g.shape[1]):
                    g[r, j] *= slope[j]
                back[r] = np.dot(w, g[r])  # three BLAS gemv: numba's (3, n) @ wᵀ is several times slower
            g = back
        for r in range(3):
            for i in range(x.shape[0]):
                grad[r, i] += g[r, i]
    k = q.shape[0]
    out = np.empty(3)
    jac = np.empty((3, k))
    for r in range(3):
        out[r] = total[r] / members * scale[r] + mean[r]
        for i in range(k):
            jac[r, i] = grad[r, i] / half_span[i]
        if sincos:
            for i in range(n_joints):
                jac[r, i] += grad[r, k + i] * math.cos(q[i]) - grad[r, k + n_joints + i] * math.sin(q[i])
        for i in range(k):
            jac[r, i] *= scale[r] / members
    return out, jac


def pack(stacks: list[list[tuple[str, np.ndarray, np.ndarray]]]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Each member's ``(activation, weight (in, out), bias)`` layers, an activation after each Linear (or
    ``"linear"``), as the kernels take them: one float32 array of every weight and bias, a table ``(L, 4)`` of
    each layer's weight offset, rows, columns and bias offset, and the activation codes. Every member must
    have the same number of layers."""
    parts, layout, codes, at = [], [], [], 0
    for stack in stacks:
        for act, w, b in stack:
            w = np.asarray(w, dtype=np.float32)
            layout.append((at, w.shape[0], w.shape[1], at + w.size))
            parts += [w.ravel(), np.asarray(b, dtype=np.float32).ravel()]
            at += w.size + b.size
            codes.append(ACTIVATIONS[act])
    flat = np.ascontiguousarray(np.concatenate(parts), dtype=np.float32)
    return flat, np.array(layout, dtype=np.int64), np.array(codes, dtype=np.int64)
