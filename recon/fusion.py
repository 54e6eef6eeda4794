"""TSDF fusion of registered depth frames into a coloured point cloud and mesh (open3d)."""

from __future__ import annotations

from pathlib import Path
from typing import Any, Callable

import numpy as np
from numpy.typing import NDArray

VOXEL_MM = 3.0
MAX_FRAMES = 40
"""Frames integrated at most (evenly spread): the volume changes little after a few dozen views."""
DEPTH_TRUNC_MM = 3000.0
TRUNCATION_VOXELS = 4.0
"""The signed distance is truncated at this many voxels (12 mm; open3d's default is 8). At 8 the
surface grew by up to 5 px at occluding contours in the 320x240 test stream, and the instances
proposed from it (``--propose``) took pixels of the objects behind them."""
BLOCKS = 20000
"""Initial capacity of the voxel-block hash map (8^3 voxels a block, about 10 kB): its memory is
zeroed up front, and 100 000 blocks of 16^3 took 18 s of a 30-frame run."""

Progress = Callable[[str, int, int], None]


def fuse_depth(frames: dict[int, tuple[Path, Path]], T_cw: dict[int, NDArray[np.float64]], K_opencv: NDArray[np.float64],
               size: tuple[int, int], depth_scale: float, voxel_mm: float = VOXEL_MM,
               progress: Progress | None = None) -> tuple[Any, Any]:
    """A point cloud and a triangle mesh (open3d legacy geometry, mm, world frame) fused from
    ``frames`` (id -> (colour file, depth file); depth value times ``depth_scale`` is mm) seen by
    the cameras ``T_cw`` (camera from world, mm), with open3d's tensor ``VoxelBlockGrid`` (its
    legacy ``ScalableTSDFVolume`` returned no points at all in open3d 0.20 here)."""
    import open3d as o3d
    import open3d.core as o3c

    ids = [i for i in frames if i in T_cw]
    ids = [ids[int(k)] for k in np.unique(np.linspace(0, len(ids) - 1, min(MAX_FRAMES, len(ids))).round())]
    cpu = o3c.Device("CPU:0")
    grid = o3d.t.geometry.VoxelBlockGrid(attr_names=("tsdf", "weight", "color"),
                                         attr_dtypes=(o3c.float32, o3c.float32, o3c.float32),
                                         attr_channels=((1), (1), (3)), voxel_size=voxel_mm, block_resolution=8,
                                         block_count=BLOCKS, device=cpu)
    K = o3c.Tensor(np.asarray(K_opencv, dtype=np.float64), o3c.float64)
    for n, i in enumerate(ids):
        colour = o3d.t.io.read_image(str(frames[i][0]))
        depth = o3d.t.io.read_image(str(frames[i][1]))
        ext = o3c.Tensor(np.asarray(T_cw[i], dtype=np.float64), o3c.float64)
        blocks = grid.compute_unique_block_coordinates(depth, K, ext, 1.0 / depth_scale, DEPTH_TRUNC_MM)
        grid.integrate(blocks, depth, colour, K, ext, 1.0 / depth_scale, DEPTH_TRUNC_MM, TRUNCATION_VOXELS)
        if progress is not None:
            progress("fusing depth", n + 1, len(ids))
    threshold = float(min(3, len(ids)))  # seen in at least three frames (every one, with fewer)
    cloud = grid.extract_point_cloud(weight_threshold=threshold).to_legacy()
    mesh = grid.extract_triangle_mesh(weight_threshold=threshold).to_legacy()
    return cloud, mesh
