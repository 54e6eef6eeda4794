"""Judging poses and labels: the verdict ``ok`` / ``check`` / ``failed`` (``verdict``), the check
image (``overlay``), and the ground-truth-free measures against photos: outline-to-edge distance
(``edge_distance``) and SIFT feature distance: the check of one image (``check``) and of a scene
(``scene_check``), its records (``check_report``), photos read at a scale (``photos``), SIFT
matching (``sift``), bootstrap intervals (``stats``) and figure (``figures``); two label sets
compared (``label_compare``); two labels from halves of the views compared in units of their
sigmas (``split_half``).

May import: ``geometry``, ``io``, ``runtime``, ``errors``, ``rasterizers``, ``losses``, ``engine``
(the pose's uncertainty and evidence records, for the verdict), ``scene``.
"""
