"""The soft edge: a band pixel's value from its signed distance to the nearest outline edge,
and its derivatives w.r.t. the pose twist, or w.r.t. the edge's two end points (drjit
forward-mode AD). The end points' derivatives are the general ones: any parametrisation of the
vertices (a twist, a 4x4 matrix, a deformation) follows from them by the chain rule
(:mod:`autoalign.torch`, :mod:`autoalign.jax`).

Twist convention: ``xi = (v [mm], w [rad])`` moves every world point ``X`` of the object to
``X + v + w x (X - c)`` to first order, ``c`` being the object centre in the world frame: the
paper's left-multiplied exponential ``exp(hat(xi')) T`` with ``xi' = (v - w x c, w)``
(:func:`autoalign.geometry.se3.apply_twist`).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from autoalign.rasterizers.camera_batch import CameraBatch
from autoalign.runtime.backend import drjit, jit_array, mitsuba


def soft_edge_values(cams: CameraBatch, view: NDArray[np.int64], px: NDArray[np.float64], py: NDArray[np.float64],
                     sign: NDArray[np.float64], A_w: NDArray[np.float64], B_w: NDArray[np.float64],
                     t0: NDArray[np.float64], t1: NDArray[np.float64], centre_w: NDArray[np.float64], half: float,
                     with_jacobian: bool, wrt_endpoints: bool = False) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Soft values of band pixels and their twist derivatives (or, with ``wrt_endpoints``, their
    derivatives w.r.t. ``A_w`` and ``B_w``).

    Args:
        cams: the views; ``view`` (B,) is each pixel's.
        px, py: (B,) pixel centres (internal convention).
        sign: (B,) +1 inside the hard mask, -1 outside.
        A_w, B_w: (B, 3) world end points of each pixel's nearest outline edge, ``t0``/``t1`` (B,)
            its visible interval (:class:`~autoalign.rasterizers.outline.Outline`).
        centre_w: the object centre the twist turns about (world, mm).
        half: the profile's half width ``2 sigma`` (pixels).

    Returns:
        the edge profile ``smoothstep(sign * dist / half)`` (B,; 0 at or below -1, 1 at or above 1,
        ``u^2 (3 - 2u)`` with ``u = (z + 1) / 2`` between) and its derivatives (B, 6) (zeros without
        ``with_jacobian``): w.r.t. the twist ``(v, w)``, or with ``wrt_endpoints`` w.r.t.
        ``(A_w, B_w)`` (mm), from one fused kernel. The visible interval ``t0, t1`` is held fixed.
    """
    dr, mi = drjit(), mitsuba()
    Float, UInt = mi.Float64, mi.UInt32
    N = len(cams.K)
    P = np.concatenate([cams.R_w2c.reshape(N, 9), cams.t_w2c, cams.K[:, :2].reshape(N, 6)], 1)  # (N, 18)
    vid = jit_array(UInt, view, np.uint32)
    cam = [dr.gather(Float, jit_array(Float, P[:, j], np.float64), vid) for j in range(18)]
    xi = [Float(0.0) for _ in range(6)]
    if with_jacobian:
        for x in xi:
            dr.enable_grad(x)
    c = [dr.opaque(Float, float(x)) for x in centre_w]  # opaque: one compiled kernel for all poses

    def moved(X: NDArray[np.float64], end: int) -> list:
        x = [jit_array(Float, X[:, j], np.float64) for j in range(3)]
        if wrt_endpoints:  # end point ``end`` moved by xi[3 end : 3 end + 3]
            return [x[j] + xi[3 * end + j] for j in range(3)]
        # X + v + w x (X - c), to first order in the twist (exact derivative at xi = 0)
        r = [x[0] - c[0], x[1] - c[1], x[2] - c[2]]
        wx = [xi[4] * r[2] - xi[5] * r[1], xi[5] * r[0] - xi[3] * r[2], xi[3] * r[1] - xi[4] * r[0]]
        return [x[j] + xi[j] + wx[j] for j in range(3)]

    def project(X: list) -> tuple:
        R, t = cam[:9], cam[9:12]
        xc = [R[3 * r + 0] * X[0] + R[3 * r + 1] * X[1] + R[3 * r + 2] * X[2] + t[r] for r in range(3)]
        k = cam[12:18]  # fx, s, cx, 0, fy, cy
        u = (k[0] * xc[0] + k[1] * xc[1]) / xc[2] + k[2]
        v = (k[3] * xc[0] + k[4] * xc[1]) / xc[2] + k[5]
        return u, v

    eu, ev = project(moved(A_w, 0))
    fu, fv = project(moved(B_w, 1))
    s0, s1 = jit_array(Float, t0, np.float64), jit_array(Float, t1, np.float64)
    au, av = eu + s0 * (fu - eu), ev + s0 * (fv - ev)  # the sub-segment [t0, t1] of the edge
    bu, bv = eu + s1 * (fu - eu), ev + s1 * (fv - ev)
    qx, qy = jit_array(Float, px, np.float64), jit_array(Float, py, np.float64)
    dx, dy = bu - au, bv - av
    t = ((qx - au) * dx + (qy - av) * dy) / dr.maximum(dx * dx + dy * dy, 1e-18)
    t = dr.clip(t, 0.0, 1.0)
    ex, ey = au + t * dx - qx, av + t * dy - qy
    dist = dr.sqrt(dr.maximum(ex * ex + ey * ey, 1e-18))
    z = jit_array(Float, sign, np.float64) * dist / dr.opaque(Float, half)
    u = dr.clip((z + 1.0) * 0.5, 0.0, 1.0)
    s = u * u * (3.0 - 2.0 * u)
    outputs = [dr.detach(s)]
    if with_jacobian:
        for k in range(6):  # one forward pass per twist coordinate; kept lazy, evaluated together
            dr.set_grad(s, 0.0)
            dr.forward_from(xi[k], flags=dr.ADFlag.ClearInterior)
            outputs.append(dr.grad(s))
        for x in xi:
            dr.disable_grad(x)
    dr.eval(*outputs)  # a single fused kernel for the values and all six derivative columns
    value = np.array(outputs[0], dtype=np.float64)
    jac = np.stack([np.array(o, dtype=np.float64) for o in outputs[1:]], 1) if with_jacobian \
        else np.zeros((len(px), 6))
    return value, jac
