"""From a capture to a BOP scene folder (``autoalign recon``): frames from a folder or a video
(``capture``), camera poses by structure from motion with pycolmap (``sfm``), the metric scale from
depth (``scale``), the table plane by RANSAC (``plane``), TSDF fusion with open3d (``fusion``),
object proposals from the fused surface (``proposals``), and the stages chained (``pipeline``).

May import: ``autoalign.geometry``, ``autoalign.io``, ``autoalign.runtime``, ``autoalign.errors``,
``autoalign.rasterizers``.
"""
