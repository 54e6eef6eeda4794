"""One scene folder refined into an output folder, as ``autoalign refine`` does it, without the
command line: the job's typed options and hand-offs (``job``: ``FolderJob``, ``RunLog``,
``FolderOutcome``, exit statuses), one object (``refine_folder``), several (``refine_scene_folder``),
and the typed reports written as ``refine.json`` (``report``); ``autoalign.check`` (``check``: the
photo check, or the split-half check, which refines each half of the views as ``refine`` does). The
CLI, ``autoalign.batch`` and Python users call it.

May import: every core subpackage (``engine``, ``scene``, ``quality``, ``io``, ``geometry``,
``runtime``); not ``autoalign.cli`` or ``autoalign.experiments``.
"""
