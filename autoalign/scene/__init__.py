"""Several objects in one scene: each instance refined alone, then all jointly and
occlusion-aware (``refine``, ``joint``, ``occlusion``), per-view camera corrections (``cameras``),
and the scene's scale from the objects' known size (``scale``).

May import: ``engine``, ``quality``, ``geometry``, ``io``, ``runtime``, ``errors``, ``losses``,
``rasterizers``.
"""
