"""Judging poses and labels: IoU (``overlap``), the verdict ``ok`` / ``check`` / ``failed``
(``verdict``), the check image (``overlay``), and the ground-truth-free measures against photos:
outline-to-edge distance (``edge_distance``) and SIFT feature distance: the check of one image
(``check``) and of a scene (``scene_check``), its records (``check_report``), photos read at a scale
(``photos``), the labels' rendering (``label_rendering``), SIFT matching (``sift``), bootstrap
intervals (``stats``) and figure (``figures``); two label sets compared (``label_compare``); two
labels from halves of the views compared in units of their sigmas (``split_half``).

May import: ``geometry``, ``io``, ``runtime``, ``errors``, ``rasterizers``, ``engine.uncertainty``,
``losses.depth`` (the depth term's record, for the verdict).
"""
