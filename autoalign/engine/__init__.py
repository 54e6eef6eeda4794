"""Refining one object's pose against its masks: the multi-view objective and its levels
(``objective``), the least-squares solver (``solver``: Levenberg-Marquardt, Gauss-Newton, Adam),
seeds from a click or the visual hull (``seeding``), orientation hypotheses (``hypotheses``), the
pose's uncertainty (``uncertainty``) and ``refine()`` itself (``refine``: seed -> search -> polish
-> disambiguate).

May import: ``geometry``, ``io``, ``runtime``, ``errors``, ``autoalign.losses`` (the mask term, IoU),
``autoalign.rasterizers`` (the soft silhouettes).
"""
