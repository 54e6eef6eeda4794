"""The ``autoalign`` command: ``refine`` (``main``; ``refine_scene`` prints a scene's outcome),
``recon``, ``export``, ``check``, ``label`` (``label``, its HTTP server ``label_http``, the 3D view
``label_3d`` and the page in ``label_page/``) and ``simulate`` (the study in
``autoalign.experiments.studies``). Each parses its arguments, calls the core and prints; errors
in the user's input are one line and exit status 2.

What the subcommands share (parser, warnings, progress bar, exit statuses) is in ``common``;
``main`` imports the subcommand modules and none of them imports ``main``.

May import: anything. Nothing in ``autoalign/`` imports it (``tests/test_layers.py``).
"""
