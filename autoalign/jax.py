"""autoalign's soft-silhouette renderer as JAX ops, and the multi-view pose solve with optimistix
(``pip install 'autoalign[jax]'``).

Two ops around one host callback (``jax.pure_callback``: autoalign's CPU renderer, drjit/mitsuba),
both usable under ``jit`` and ``vmap`` (over poses; the callback then runs pose by pose):

* :func:`silhouettes` -- soft silhouettes ``(V, H, W)`` of a pose ``(4, 4)``, a ``jax.custom_vjp``:
  reverse mode (``jax.grad`` of a loss). Its backward pass multiplies the cotangent by the
  renderer's derivatives w.r.t. the outline edges' end points, chained to the pose matrix
  (:mod:`autoalign.rasterizers.pose_jacobian`).
* :func:`pixel_silhouettes` -- the soft values at fixed pixels, a ``jax.custom_jvp``: forward mode,
  which is what a least-squares solver needs (optimistix linearises the residuals and lineax's QR
  materialises the Jacobian from one tangent per unknown; a ``custom_vjp`` op would leave it
  reverse mode only, a Jacobian built from one backward pass per residual).

:func:`refine` solves the multi-view silhouette least squares for one object with
``optimistix.LevenbergMarquardt`` over a twist about the object centre, the residuals being
rendered minus target at the pixels near the targets' contours.

Importing :mod:`autoalign` does not import this module (nor jax).
"""

from __future__ import annotations

from collections import OrderedDict
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import cv2
import jax
import jax.numpy as jnp
import numpy as np
from numpy.typing import NDArray

from autoalign.geometry.camera import Camera
from autoalign.geometry.mesh import Mesh
from autoalign.io.bop import Scene
from autoalign.rasterizers.pose_jacobian import (
    RenderedPose,
    image_size,
    render_with_vertex_jacobian,
)
from autoalign.rasterizers.soft_silhouette import SoftSilhouetteRasterizer

_CACHE: OrderedDict[tuple, tuple[NDArray[np.float64], RenderedPose]] = OrderedDict()
"""The last few renders, so that a backward or tangent pass at the pose of a forward pass reuses it."""


def _rendered(rast: SoftSilhouetteRasterizer, T: NDArray[np.float64], cameras: tuple[Camera, ...],
              sigma: float) -> tuple[NDArray[np.float64], RenderedPose]:
    T = np.ascontiguousarray(T, dtype=np.float64)
    key = (id(rast), T.tobytes(), id(cameras), sigma)
    if key not in _CACHE:
        _CACHE[key] = render_with_vertex_jacobian(rast, T, cameras, sigma)
        while len(_CACHE) > 8:
            _CACHE.popitem(last=False)
    return _CACHE[key]


@dataclass(frozen=True, eq=False)
class SilhouetteOp:
    """One mesh's renderer with fixed cameras and edge softness (hashable by identity, so that it
    can be a static argument of the ops)."""

    rast: SoftSilhouetteRasterizer
    cameras: tuple[Camera, ...]
    sigma: float = 1.0

    @staticmethod
    def of(mesh: Mesh | SoftSilhouetteRasterizer, cameras: Sequence[Camera], sigma: float = 1.0) -> "SilhouetteOp":
        image_size(cameras)
        rast = mesh if isinstance(mesh, SoftSilhouetteRasterizer) else SoftSilhouetteRasterizer(mesh)
        return SilhouetteOp(rast, tuple(cameras), float(sigma))

    @property
    def shape(self) -> tuple[int, int, int]:
        H, W = image_size(self.cameras)
        return len(self.cameras), H, W

    def images(self, T: NDArray[np.float64]) -> NDArray[np.float64]:
        return _rendered(self.rast, T, self.cameras, self.sigma)[0]

    def matrix_gradient(self, T: NDArray[np.float64], g: NDArray[np.float64]) -> NDArray[np.float64]:
        return _rendered(self.rast, T, self.cameras, self.sigma)[1].matrix_gradient(np.asarray(g, np.float64).ravel())

    def image_tangent(self, T: NDArray[np.float64], dT: NDArray[np.float64]) -> NDArray[np.float64]:
        return _rendered(self.rast, T, self.cameras, self.sigma)[1].image_tangent(dT, int(np.prod(self.shape)))


def _host(fn: Any, shape: tuple[int, ...], dtype: Any, *args: Any) -> jax.Array:
    return jax.pure_callback(lambda *a: np.asarray(fn(*a), dtype=dtype), jax.ShapeDtypeStruct(shape, dtype), *args,
                             vmap_method="sequential")


def _images_impl(op: SilhouetteOp, T: jax.Array) -> jax.Array:
    return _host(op.images, op.shape, T.dtype, T)


_images = jax.custom_vjp(_images_impl, nondiff_argnums=(0,))


def _images_fwd(op: SilhouetteOp, T: jax.Array) -> tuple[jax.Array, jax.Array]:
    return _images(op, T), T


def _images_bwd(op: SilhouetteOp, T: jax.Array, g: jax.Array) -> tuple[jax.Array]:
    return (_host(op.matrix_gradient, (4, 4), T.dtype, T, g),)


_images.defvjp(_images_fwd, _images_bwd)


def silhouettes(op: SilhouetteOp, T: jax.Array) -> jax.Array:
    """Soft silhouettes ``(V, H, W)`` of the pose ``T`` (4x4 world from model, mm) in ``op``'s
    cameras; reverse-mode differentiable (see module doc)."""
    T = jnp.asarray(T)
    if T.shape != (4, 4):
        raise ValueError(f"T must be (4, 4) (vmap for several poses), not {T.shape}")
    return _images(op, T)


def _pixels_impl(op: SilhouetteOp, pixels: "Pixels", T: jax.Array) -> jax.Array:
    return _host(lambda T: op.images(T).ravel()[pixels.array], (len(pixels.array),), T.dtype, T)


_pixels = jax.custom_jvp(_pixels_impl, nondiff_argnums=(0, 1))


@_pixels.defjvp
def _pixels_jvp(op: SilhouetteOp, pixels: "Pixels", primals: tuple, tangents: tuple) -> tuple[jax.Array, jax.Array]:
    (T,), (dT,) = primals, tangents
    tangent = _host(lambda T, dT: op.image_tangent(T, dT)[pixels.array], (len(pixels.array),), T.dtype, T, dT)
    return _pixels(op, pixels, T), tangent


@dataclass(frozen=True, eq=False)
class Pixels:
    """Flat indices into ``(V, H, W)`` images (hashable by identity: a static argument)."""

    array: NDArray[np.int64]


def pixel_silhouettes(op: SilhouetteOp, pixels: Pixels, T: jax.Array) -> jax.Array:
    """The soft values of :func:`silhouettes` at the flat ``pixels``; forward-mode differentiable."""
    return _pixels(op, pixels, jnp.asarray(T))


def twist_pose(xi: jax.Array, T0: jax.Array, centre_w: jax.Array) -> jax.Array:
    """``exp(hat(xi')) @ T0`` with the twist ``xi = (v [mm], w [rad])`` turning about the world point
    ``centre_w`` (:func:`autoalign.geometry.se3.apply_twist`, in JAX)."""
    v, w = xi[:3], xi[3:]
    Xi = jnp.zeros((4, 4), dtype=xi.dtype)
    Xi = Xi.at[0, 1].set(-w[2]).at[0, 2].set(w[1]).at[1, 0].set(w[2]).at[1, 2].set(-w[0])
    Xi = Xi.at[2, 0].set(-w[1]).at[2, 1].set(w[0]).at[:3, 3].set(v - jnp.cross(w, centre_w))
    return jax.scipy.linalg.expm(Xi) @ T0


@dataclass
class JaxRefinement:
    """What :func:`refine` found: the pose (4x4 world from model, mm), the solver's steps, whether
    it converged (``"successful"``, or it ran out of steps), and the final loss (``0.5 sum r^2``)."""

    T_wm: NDArray[np.float64]
    steps: int
    result: str
    loss: float


CONTOUR_PX = 12
"""The residuals are the pixels within this many pixels (at the working resolution) of a target's
contour: farther in or out, a pose that starts a few millimetres and degrees off changes nothing."""


def refine(scene: Scene, mesh: Mesh, T_init: NDArray[np.float64], sigma: float = 0.5, resolution: float = 1.0,
           max_steps: int = 60, tol: float = 1e-9) -> JaxRefinement:
    """The multi-view silhouette least squares of one object solved with
    ``optimistix.LevenbergMarquardt`` from ``T_init`` (world from model, mm): residuals ``soft
    silhouette - mask`` at the pixels near the masks' contours (:data:`CONTOUR_PX`), each view's
    over the square root of its mask's area (autoalign's ``l2`` loss; no robust weights: the same
    problem as ``autoalign.refine`` with ``RefineOptions(robust=False)``), at ``resolution`` times
    the cameras'. Needs double precision, switched on for
    the whole process (``jax.config.update("jax_enable_x64", True)``): the renderer's callbacks run
    on JAX's own threads, where a ``jax.enable_x64`` context does not reach."""
    import optimistix as optx

    from autoalign.engine.refine import checked_inputs, checked_pose

    checked_inputs(scene, mesh, None, None)  # a path for either: one line saying how to read it
    T_init = checked_pose(T_init, "T_init")  # a scaled or mirrored pose would be refined as one
    if not jax.config.jax_enable_x64:
        raise ValueError('autoalign.jax.refine needs double precision: call jax.config.update("jax_enable_x64", True) '
                         "first (single precision cannot hold poses to 0.01 mm)")
    cams = [c.scaled(resolution) for c in scene.cameras] if resolution != 1.0 else list(scene.cameras)
    op = SilhouetteOp.of(mesh, cams, sigma)
    V, H, W = op.shape
    targets = np.stack([cv2.resize(m.astype(np.float32), (W, H), interpolation=cv2.INTER_AREA) > 0.5
                        for m in scene.masks]).astype(np.float64)
    kernel = np.ones((2 * CONTOUR_PX + 1,) * 2, np.uint8)
    near = np.stack([cv2.dilate(t.astype(np.uint8), kernel) > cv2.erode(t.astype(np.uint8), kernel) for t in targets])
    pixels = Pixels(np.flatnonzero(near.ravel()))
    target = jnp.asarray(targets.ravel()[pixels.array])
    # each view's residuals over the square root of its mask's area, as autoalign's l2 loss
    per_view = np.repeat(1.0 / np.sqrt(np.maximum(targets.sum((1, 2)), 1.0)), H * W)[pixels.array]
    scale = jnp.asarray(per_view)
    T0 = jnp.asarray(np.asarray(T_init, dtype=np.float64))
    centre = T0[:3, :3] @ jnp.asarray(mesh.centre) + T0[:3, 3]

    def residuals(xi: jax.Array, args: Any) -> jax.Array:
        return (pixel_silhouettes(op, pixels, twist_pose(xi, T0, centre)) - target) * scale

    solver = optx.LevenbergMarquardt(rtol=tol, atol=tol)
    sol = optx.least_squares(residuals, solver, jnp.zeros(6), max_steps=max_steps, throw=False)
    T = np.asarray(twist_pose(sol.value, T0, centre))
    r = np.asarray(residuals(sol.value, None))
    result = "successful" if bool(sol.result == optx.RESULTS.successful) else "stopped before converging"
    return JaxRefinement(T, int(sol.stats["num_steps"]), result, float(0.5 * r @ r))
