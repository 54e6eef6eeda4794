"""The names ``autoalign check`` (cli/check.py) imports from here, until it imports them from their
modules: :mod:`autoalign.quality.scene_check` and :mod:`autoalign.quality.figures`. The check itself
is described in :mod:`autoalign.quality.check`."""

from autoalign.quality.figures import match_figure
from autoalign.quality.scene_check import check_prepared, prepare_check

__all__ = ["check_prepared", "match_figure", "prepare_check"]
