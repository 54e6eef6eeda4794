"""The state behind ``autoalign label``: one labelling session (instances placed, refined,
accepted, undo, persistence in ``session.json``).

Modules: ``session`` (:class:`~autoalign.label.session.LabelSession`, what the page and the 3D
view call), ``scene`` (the scene's views and masks, read once), ``records`` (an instance's
record, a verdict, the job's state), ``state`` (the instances and revision under one lock),
``session_file`` (``session.json``), ``undo``, ``page_geometry`` (silhouettes, outlines, IoU,
nudges) and ``jobs`` (the slow job's thread).

May import: every core subpackage (``engine``, ``scene``, ``quality``, ``io``, ``geometry``); not
``autoalign.cli`` (the page's server lives there).
"""
