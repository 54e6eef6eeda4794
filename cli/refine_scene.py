"""``autoalign refine SCENE --models DIR``: what every instance's refinement found, printed.

The work (instances read, refined, judged, the outputs written) is
:func:`autoalign.jobs.refine_scene_folder.refine_scene_folder`, called by ``autoalign refine``
(:mod:`autoalign.cli.main`); a ``check`` or ``failed`` verdict is warned and exits 3, so that no
script takes a doubtful label for a good one.
"""

from __future__ import annotations

import json
from pathlib import Path

from autoalign.cli.common import WARNINGS
from autoalign.jobs.job import FolderOutcome


def print_scene_outcome(outcome: FolderOutcome, out: Path, elapsed: float, as_json: bool, quiet: bool) -> None:
    """Print every instance's verdict and fit: one JSON object (``--json``) or a line each."""
    from autoalign.jobs.report import SceneReport

    report = outcome.report
    assert isinstance(report, SceneReport)
    if as_json:
        print(json.dumps(report.summary(elapsed, out, WARNINGS), allow_nan=False), flush=True)
        return
    if quiet:
        return
    records = report.to_json()["instances"]
    rows = [f"  obj {rec['obj_id']:>3} (instance {rec['instance']}): {rec['verdict']:<6} median IoU "
            f"{rec['median_iou_after']:.3f} over {len(rec['image_ids'])} views"
            # a sigma is the precision of a pose only where the pose is trusted (as for one object)
            + (f", sigma up to {max(rec['uncertainty']['sigma_mm']):.2g} mm / "
               f"{max(rec['uncertainty']['sigma_deg']):.2g} deg" if rec["verdict"] == "ok" else "")
            + (f"; {'; '.join(rec['reasons'])}" if rec["reasons"] else "") for rec in records]
    print(f"{len(records)} instance(s) in {len(report.image_ids)} images, {elapsed:.1f} s:\n" + "\n".join(rows)
          + f"\nwrote {', '.join(outcome.paths)} to {out}", flush=True)
