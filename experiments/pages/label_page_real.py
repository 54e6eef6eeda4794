"""``autoalign label`` on the real LM-O scenes (``../shared/real/lmo_dev``): real photos, real SAM
masks, cameras from the dataset's labels. Every object of the rigid group is clicked once in the
page (headless Chromium), with the object the scene's ``scene_gt.json`` names, in the view where its
mask is largest; the pose it is given is compared with ``gt_world.json`` (modulo symmetries), with
the time from the click to the outlines, the verdict and its reasons. A screenshot of each scene's
page is kept. Results: ``experiments/results/label_page_real.md`` and ``label_page/real-*.png``.

``python -m autoalign.experiments.pages.label_page_real [--data ../shared/real/lmo_dev]``
"""

from __future__ import annotations

import argparse
import json
import tempfile
from pathlib import Path

import numpy as np

from autoalign.experiments import RESULTS
from autoalign.experiments.benchmarks.bench_scene import symmetries
from autoalign.experiments.pages.label_page_driver import (
    LabelServerProcess,
    launch_browser,
    open_page,
    place_in_largest_view,
)
from autoalign.experiments.result_files import write_results
from autoalign.experiments.studies.metrics import pose_errors
from autoalign.experiments.studies.shared_data import REAL_SCENES
from autoalign.io.bop import read_cameras
from autoalign.io.models import ModelSet


def label_scene(scene: Path, out: Path, shot: Path) -> list[dict]:
    """Click every object of the scene's rigid group once; one row per object."""
    from playwright.sync_api import sync_playwright

    group = json.loads((scene / "gt_world.json").read_text())["T_world_from_model_mm"]
    models = ModelSet.read(scene / "models")
    rows = []
    with LabelServerProcess(scene, scene / "models", out, ("--no-3d",)) as server, sync_playwright() as pw:
        browser = launch_browser(pw)
        page = open_page(browser, server.url, len(read_cameras(scene)))
        state = page.evaluate("fetch('/api/state').then(r => r.json())")
        for inst in state["instances"]:
            obj = inst["suggested_obj_id"]
            if str(obj) not in group:
                continue
            placed = place_in_largest_view(page, scene, inst["index"], obj)
            after = placed.instance(inst["index"])
            err = pose_errors(np.array(after["T_wm"]), np.array(group[str(obj)]), models.mesh(obj).centre, None,
                              symmetries(models, obj))
            rows.append({"scene": scene.name, "obj_id": obj, "view": placed.image_id, "views": len(inst["views"]),
                         "click_to_outlines_s": placed.click_to_outlines_s,
                         "click_to_first_outlines_s": placed.click_to_first_outlines_s,
                         "click_to_refined_pose_s": placed.click_to_refined_pose_s,
                         "error_mm": err.pos_err_mm, "error_deg": err.rot_err_deg,
                         "verdict": after["verdict"], "median_iou": after["median_iou"], "reasons": after["reasons"]})
            print(json.dumps(rows[-1]), flush=True)
        page.evaluate("window.scrollTo(0, 0)")
        page.screenshot(path=str(shot))
        browser.close()
    return rows


def _s(seconds: float | None) -> str:
    return "-" if seconds is None else f"{seconds:.2f}"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", type=Path, default=REAL_SCENES)
    args = ap.parse_args(argv)
    rows = []
    (RESULTS / "label_page").mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory() as tmp:
        for scene in sorted(d for d in args.data.iterdir() if (d / "gt_world.json").is_file()):
            rows += label_scene(scene, Path(tmp) / scene.name, RESULTS / "label_page" / f"real-{scene.name}.png")
    lines = ["# autoalign label on the real LM-O scenes", "",
             "`python -m autoalign.experiments.pages.label_page_real`: each object of the rigid group clicked once in the "
             "page (headless Chromium, 2 cores), the scene's object chosen, in the view where its SAM mask is "
             "largest; error against `gt_world.json` modulo symmetries (the dataset's labels are a few px off).", "",
             "Times from the click: to the first outlines (the orientation search's pose), to the first refined "
             "pose (the masks', before the photos refine it and before its uncertainty and verdict) and to the "
             "judged pose.", "",
             "| scene | obj | views | click to first outlines (s) | to refined pose (s) | to judged pose (s) | "
             "error mm / deg | median IoU | verdict | reasons |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['scene']} | {r['obj_id']} | {r['views']} | {_s(r['click_to_first_outlines_s'])} | "
                     f"{_s(r['click_to_refined_pose_s'])} | {r['click_to_outlines_s']:.2f} | "
                     f"{r['error_mm']:.1f} / {r['error_deg']:.1f} | {r['median_iou']:.2f} | {r['verdict']} | "
                     f"{'; '.join(r['reasons'])[:160]} |")
    write_results("label_page_real", rows, lines)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
