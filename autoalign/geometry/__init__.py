"""Geometry with units and frames in every name: SE(3) poses and twists (``se3``; ``T_ab`` maps
frame b to frame a, mm), pinhole cameras (``camera``; the OpenCV / BOP pixel convention converted
on import), triangle meshes (``mesh``; mm, merged vertices, the edge-to-face table).

May import: ``autoalign.errors``, ``autoalign.runtime``.
"""
