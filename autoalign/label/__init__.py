"""The state behind ``autoalign label``: one labelling session (instances placed, refined,
accepted, undo, persistence in ``session.json``).

May import: every core subpackage (``engine``, ``scene``, ``quality``, ``io``, ``geometry``); not
``autoalign.cli`` (the page's server lives there).
"""
