"""autoalign's soft-silhouette renderer as a PyTorch op (``pip install 'autoalign[torch]'``).

:func:`silhouettes` renders the soft silhouettes of posed meshes in calibrated views, like
:meth:`autoalign.rasterizers.soft_silhouette.SoftSilhouetteRasterizer.render`, as a
``torch.autograd.Function``: the forward pass is autoalign's CPU renderer (drjit/mitsuba), and the
backward pass multiplies the incoming gradient by the renderer's own derivatives of each band
pixel w.r.t. the two end points of its outline edge (drjit forward-mode AD), chained to the pose
matrix. No finite differences, and no autograd through the rasterizer.

Poses are world-from-model 4x4 matrices (mm; ``(4, 4)`` or ``(N, 4, 4)``, float32 or float64) or
kornia ``Se3`` objects (``kornia.geometry.liegroup``), whose ``matrix()`` is differentiable in its
quaternion and translation. The gradient w.r.t. a matrix is exact for any change of its top three
rows (rotation, translation, and the affine directions a rigid pose never takes), with the outline
and the hard mask held fixed, as in autoalign's own Gauss-Newton steps; the bottom row gets zero.
Each object is rendered alone: objects do not hide each other here (the occlusion-aware loss is
:mod:`autoalign.scene.occlusion`).

The loss follows kornia's style: a functional op (:func:`silhouette_loss`) and a thin
``nn.Module`` (:class:`SilhouetteLoss`). Example (a pose fitted with ``torch.optim``)::

    import torch
    from kornia.geometry.liegroup import Se3
    from autoalign.torch import SilhouetteLoss

    loss_fn = SilhouetteLoss(mesh, cameras, targets, sigma=1.0)   # targets: (V, H, W) masks
    xi = torch.zeros(6, dtype=torch.float64, requires_grad=True)  # a twist applied to T0
    opt = torch.optim.Adam([xi], lr=1e-2)
    for _ in range(200):
        opt.zero_grad()
        loss = loss_fn(Se3.exp(xi).matrix() @ T0)
        loss.backward()
        opt.step()

The photos are evidence too (:class:`RegionLoss`): colour models of the object and its surroundings
learned around its outline at the current pose give each pixel's posterior of being the object
(:mod:`autoalign.losses.region`), the target the same L2 loss compares the silhouettes with. The
targets are held fixed between :meth:`RegionLoss.learn` calls (learn again every few steps, as
autoalign's own rounds do), so the loss is a function of the pose between them.

Importing :mod:`autoalign` does not import this module (nor torch).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
import torch

from autoalign.geometry.camera import Camera
from autoalign.losses.region import RegionOptions, region_target
from autoalign.rasterizers.pose_jacobian import (
    Renderers,
    image_size,
    render_with_vertex_jacobian,
    renderers_for,
)
from autoalign.rasterizers.soft_silhouette import SoftSilhouetteRasterizer


class _SilhouettesFn(torch.autograd.Function):
    """poses (N, 4, 4) -> soft silhouettes (N, V, H, W); see :func:`silhouettes`."""

    @staticmethod
    def forward(ctx: Any, poses: torch.Tensor, rasts: list[SoftSilhouetteRasterizer], cameras: list[Camera],
                sigma: float) -> torch.Tensor:
        T = poses.detach().cpu().double().numpy()
        images, saved = [], []
        for r, T_n in zip(rasts, T):
            img, rendered = render_with_vertex_jacobian(r, T_n, cameras, sigma)
            images.append(img)
            saved.append(rendered)
        ctx.rendered = saved
        return torch.as_tensor(np.stack(images), dtype=poses.dtype, device=poses.device)

    @staticmethod
    def backward(ctx: Any, grad: torch.Tensor) -> tuple[torch.Tensor, None, None, None]:
        g = grad.detach().cpu().double().numpy().reshape(len(ctx.rendered), -1)
        out = np.stack([r.matrix_gradient(g_n) for r, g_n in zip(ctx.rendered, g)])
        return torch.as_tensor(out, dtype=grad.dtype, device=grad.device), None, None, None


def as_matrices(poses: Any) -> tuple[torch.Tensor, bool]:
    """``(N, 4, 4)`` matrices from a tensor ``(4, 4)`` / ``(N, 4, 4)`` or a kornia ``Se3``, and
    whether a single pose was given."""
    if not isinstance(poses, torch.Tensor) and hasattr(poses, "matrix"):  # kornia.geometry.liegroup.Se3
        poses = poses.matrix()
    if not isinstance(poses, torch.Tensor) or poses.shape[-2:] != (4, 4) or poses.dim() not in (2, 3):
        raise ValueError(f"poses must be (4, 4) or (N, 4, 4) tensors or a kornia Se3, not {type(poses).__name__} "
                         f"{tuple(getattr(poses, 'shape', ()))}")
    if not poses.dtype.is_floating_point:
        raise ValueError(f"poses must be float32 or float64, not {poses.dtype}")
    return (poses[None], True) if poses.dim() == 2 else (poses, False)


def silhouettes(meshes: Renderers, poses: Any, cameras: Sequence[Camera], sigma: float = 1.0) -> torch.Tensor:
    """Soft silhouettes of posed meshes, differentiable w.r.t. the poses.

    Args:
        meshes: one :class:`~autoalign.geometry.mesh.Mesh` (or its renderer) for all poses, or one per pose
            (build renderers once and pass them again: they cache the mesh's ray-casting scene).
        poses: world-from-model (mm): ``(4, 4)``, ``(N, 4, 4)`` or a kornia ``Se3``.
        cameras: the views (one image size), world frame, mm.
        sigma: edge softness in pixels; the edge profile spans ``+-2 sigma``.

    Returns:
        ``(V, H, W)`` for one pose, ``(N, V, H, W)`` for ``N``: values in [0, 1], the poses' dtype.
    """
    T, single = as_matrices(poses)
    if not cameras:
        raise ValueError("no cameras given")
    image_size(cameras)
    out = _SilhouettesFn.apply(T, renderers_for(meshes, len(T)), list(cameras), float(sigma))
    return out[0] if single else out


def silhouette_loss(rendered: torch.Tensor, targets: torch.Tensor, weights: torch.Tensor | None = None) -> torch.Tensor:
    """The multi-view L2 silhouette loss: ``0.5 * sum_v w_v * mean_pixels (rendered - target)^2``
    summed over objects (``rendered``: (..., V, H, W); ``targets`` broadcastable to it, in [0, 1];
    ``weights`` (V,), default 1), as autoalign's own ``l2`` loss per view."""
    if rendered.shape[-3:] != targets.shape[-3:]:
        raise ValueError(f"targets {tuple(targets.shape)} do not match the silhouettes {tuple(rendered.shape)}")
    per_view = 0.5 * ((rendered - targets.to(rendered.dtype)) ** 2).mean(dim=(-2, -1))
    if weights is not None:
        per_view = per_view * weights.to(rendered.dtype)
    return per_view.sum()


class SilhouetteLoss(torch.nn.Module):
    """:func:`silhouette_loss` of :func:`silhouettes` for fixed meshes, cameras and target masks:
    ``module(poses)`` is the loss of the poses (one pose, ``N``, or a kornia ``Se3``)."""

    def __init__(self, meshes: Renderers, cameras: Sequence[Camera], targets: Any, sigma: float = 1.0,
                 weights: Any = None) -> None:
        super().__init__()
        self.cameras, self.sigma = list(cameras), float(sigma)
        H, W = image_size(self.cameras)
        t = torch.as_tensor(np.asarray(targets, dtype=np.float64))
        if t.shape[-3:] != (len(self.cameras), H, W):
            raise ValueError(f"targets {tuple(t.shape)}: expected (V, H, W) = ({len(self.cameras)}, {H}, {W})")
        self.register_buffer("targets", t)
        self.register_buffer("weights", None if weights is None else torch.as_tensor(np.asarray(weights, np.float64)))
        many = isinstance(meshes, Sequence)
        self.meshes = renderers_for(meshes, len(meshes)) if many else renderers_for(meshes, 1)[0]

    def forward(self, poses: Any) -> torch.Tensor:
        return silhouette_loss(silhouettes(self.meshes, poses, self.cameras, self.sigma), self.targets, self.weights)


def region_targets(mesh: Any, pose: Any, cameras: Sequence[Camera], photos: Sequence[np.ndarray],
                   masks: Sequence[np.ndarray] | None = None, options: RegionOptions = RegionOptions()) -> torch.Tensor:
    """``(V, H, W)`` region targets of one object at ``pose`` (world from model, mm; a tensor or a
    kornia ``Se3``; not differentiated): per view the posterior of its colour models learned around
    the hard silhouette there, fused with its mask if given (:func:`~autoalign.losses.region.region_target`).
    ``photos``: ``(H, W, 3)`` uint8 BGR per view, at the cameras' size."""
    T, single = as_matrices(pose)
    if not single:
        raise ValueError("region targets are learned for one pose (4, 4) at a time")
    image_size(cameras)
    if len(photos) != len(cameras) or (masks is not None and len(masks) != len(cameras)):
        raise ValueError(f"{len(cameras)} cameras need as many photos (and masks), not {len(photos)}")
    rast = renderers_for(mesh, 1)[0]
    sils = rast.hard_masks(T[0].detach().cpu().double().numpy(), list(cameras))
    out = [region_target(np.asarray(ph, dtype=np.uint8), s, None if masks is None else np.asarray(masks[k], np.float32),
                         None, options).target for k, (ph, s) in enumerate(zip(photos, sils))]
    return torch.as_tensor(np.stack(out), dtype=T.dtype)


class RegionLoss(torch.nn.Module):
    """:func:`silhouette_loss` of one object's :func:`silhouettes` against its region targets
    (:func:`region_targets`): the photos as evidence, with or without masks. The targets are
    learned at the first pose seen and again at each :meth:`learn`."""

    def __init__(self, mesh: Any, cameras: Sequence[Camera], photos: Sequence[np.ndarray],
                 masks: Sequence[np.ndarray] | None = None, sigma: float = 1.0,
                 options: RegionOptions = RegionOptions()) -> None:
        super().__init__()
        self.cameras, self.sigma, self.options = list(cameras), float(sigma), options
        self.photos = [np.asarray(p, dtype=np.uint8) for p in photos]
        self.masks = None if masks is None else [np.asarray(m, dtype=np.float32) for m in masks]
        self.mesh = renderers_for(mesh, 1)[0]
        self.register_buffer("targets", None)

    def learn(self, pose: Any) -> None:
        """Learn the colour models and targets again at ``pose``."""
        self.targets = region_targets(self.mesh, pose, self.cameras, self.photos, self.masks, self.options)

    def forward(self, pose: Any) -> torch.Tensor:
        if self.targets is None:
            self.learn(pose)
        return silhouette_loss(silhouettes(self.mesh, pose, self.cameras, self.sigma), self.targets)
