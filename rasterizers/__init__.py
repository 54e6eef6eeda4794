"""Rendering on the CPU (drjit/mitsuba, LLVM backend): ray casting (``ray_casting``: hard masks,
depth and hits, pixel centres in autoalign's convention), the object's outline in each view
(``outline``), the band of pixels near it (``band``), soft edge values and their derivatives
(``soft_edge``), all chained by ``SoftSilhouetteRasterizer`` (``soft_silhouette``: soft masks of
many views at once with their Jacobians with respect to the pose twist), cameras batched for drjit
(``camera_batch``), the chain rule to a 4x4 pose for the PyTorch and JAX ops (``pose_jacobian``) and
labels rendered into photos, coloured (``label_rendering``).

May import: ``autoalign.geometry``, ``autoalign.runtime``, ``autoalign.errors``.
"""
