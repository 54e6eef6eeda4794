"""Judging poses and labels: IoU (``overlap``), the verdict ``ok`` / ``check`` / ``failed``
(``verdict``), the check image (``overlay``), and the ground-truth-free measures against photos:
outline-to-edge distance (``edge_distance``), SIFT feature distance (``feature_distance``), two
label sets compared (``label_compare``).

May import: ``geometry``, ``io``, ``runtime``, ``errors``, ``rasterizers``, ``engine.uncertainty``.
"""
