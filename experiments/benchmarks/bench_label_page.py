"""Benchmark of ``autoalign label``: time from a click on an object to its first outlines on screen
in every view (the orientation search's pose, dashed) and to the refined pose's, measured in the
page itself (``performance.now()`` at the click to the second animation frame after the outlines
were drawn), in a real headless Chromium.

A synthetic scene of ``--objects`` procedural objects that hide each other, 40 views of 640x480
(masks ray-cast by open3d, as ``bench_scene``); each object is clicked once, in the first view
where its mask is largest. With the 3D view closed (the page's default) and then open: without
a GPU, Chromium draws viser's WebGL in software on the same cores as the refinement. The server
and the browser share the machine's cores. With ``--before DIR`` (a checkout of earlier code, e.g.
``git worktree add DIR REV``) each session is run with that code's server and page too, the two
alternating, so that both see the same machine. Results: ``experiments/results/bench_label_page.md``.

``python -m autoalign.experiments.benchmarks.bench_label_page [--objects 5] [--views 40] [--before DIR]``
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import tempfile
import time
from pathlib import Path

import numpy as np

from autoalign.experiments.benchmarks.bench_scene import make_bench_scene, symmetries
from autoalign.experiments.pages.label_page_driver import (
    LabelServerProcess,
    launch_browser,
    open_page,
    place_in_largest_view,
)
from autoalign.experiments.result_files import write_results
from autoalign.experiments.studies.metrics import pose_errors
from autoalign.io.models import ModelSet


def measure(root: Path, n_obj: int, n_views: int, open_3d: bool, truth: list[np.ndarray], code: str,
            checkout: Path | None) -> list[dict]:
    """Click every object once with the server (and page) of ``checkout`` (``None``: this code); one row per click."""
    from playwright.sync_api import sync_playwright

    models = ModelSet.read(root / "models")
    out = root / f"session_{code}_{'3d' if open_3d else 'plain'}"
    rows = []
    with LabelServerProcess(root / "scene", root / "models", out, cwd=checkout) as server, sync_playwright() as pw:
        browser = launch_browser(pw)
        page = open_page(browser, server.url, n_views)
        if open_3d:
            page.click("#viewer-box summary")
            page.frame_locator("#viewer").locator("canvas").first.wait_for(timeout=60_000)
        for k in range(n_obj):
            placed = place_in_largest_view(page, root / "scene", k, k + 1)
            im, state, inst = placed.image_id, placed.state, placed.instance(k)
            err = pose_errors(np.array(inst["T_wm"]), truth[k], models.mesh(k + 1).centre, None,
                              symmetries(models, k + 1))
            first, refined = placed.click_to_first_outlines_s, placed.click_to_refined_pose_s
            rows.append({"code": code, "object": k + 1, "view": im, "click_to_outlines_s": placed.click_to_outlines_s,
                         "click_to_first_outlines_s": placed.click_to_outlines_s if first is None else first,
                         "click_to_refined_pose_s": placed.click_to_outlines_s if refined is None else refined,
                         "server_job_s": state["job"]["seconds"], "verdict": inst["verdict"],
                         "reasons": inst["reasons"],
                         "error_mm": err.pos_err_mm, "error_deg": err.rot_err_deg,
                         "outlined_views": page.evaluate(
                             f"new Set([...document.querySelectorAll('polyline[data-instance=\"{k}\"]')]"
                             ".map(p => p.closest('.view').dataset.imageId)).size")})
            print(f"{code}, {'3D open' if open_3d else '3D closed'}: object {k + 1}: first outlines "
                  f"{rows[-1]['click_to_first_outlines_s']:.2f} s, refined pose "
                  f"{rows[-1]['click_to_refined_pose_s']:.2f} s, judged {rows[-1]['click_to_outlines_s']:.2f} s "
                  f"(server {rows[-1]['server_job_s']:.2f} s), {rows[-1]['error_mm']:.2f} mm / "
                  f"{rows[-1]['error_deg']:.2f} deg", flush=True)
        browser.close()
    return rows


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--objects", type=int, default=5)
    ap.add_argument("--views", type=int, default=40)
    ap.add_argument("--before", type=Path, help="a checkout of the code to compare with, run alternating")
    args = ap.parse_args(argv)
    codes = ([("before", args.before.resolve())] if args.before else []) + [("after", None)]
    results: dict[str, list[dict]] = {}
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        truth = make_bench_scene(root, args.objects, views=args.views)
        (root / "scene" / "scene_gt.json").unlink()
        for view in ("closed", "open"):
            for code, checkout in codes:
                results[f"{view}, {code}"] = measure(root, args.objects, args.views, view == "open", truth, code,
                                                    checkout)
    summary = {name: {"first_median_s": statistics.median(r["click_to_first_outlines_s"] for r in rows),
                      "refined_pose_median_s": statistics.median(r["click_to_refined_pose_s"] for r in rows),
                      "median_s": statistics.median(r["click_to_outlines_s"] for r in rows),
                      "max_s": max(r["click_to_outlines_s"] for r in rows),
                      "server_median_s": statistics.median(r["server_job_s"] for r in rows)}
               for name, rows in results.items()}
    meta = {"objects": args.objects, "views": args.views, "image": "640x480", "cpus": os.cpu_count(),
            "machine": platform.machine(), "python": platform.python_version(),
            "before": str(args.before) if args.before else None, "date": time.strftime("%Y-%m-%d %H:%M")}
    before = " --before DIR" if args.before else ""
    lines = ["# autoalign label: click to outlines on screen", "",
             f"`python -m autoalign.experiments.benchmarks.bench_label_page --objects {args.objects} --views "
             f"{args.views}{before}`; {args.objects} objects that hide each other, {args.views} views of 640x480, "
             f"headless Chromium (software WebGL) and the server on the same {os.cpu_count()} cores, {meta['date']}."
             + (" `before`: the code of the checkout given, its sessions alternating with this code's." if before
                else ""), "",
             "Time from the click (in the page) to the outlines drawn in every view (the second animation frame "
             "after): first those of the orientation search's first pose (dashed), then those of the refined pose "
             "before its uncertainty and verdict, then those of the judged pose; and the server's part (place: seed "
             "from the click, orientation search, refinement, uncertainty, verdict, outlines). Code that draws no "
             "outline before the judged pose has its first and refined outlines there.", "",
             "Errors against the truth, modulo each model's symmetries (models_info.json).", "",
             "| 3D view, code | object | view clicked | click to first outlines (s) | click to refined pose (s) | "
             "click to judged pose (s) | server (s) | error (mm / deg) | verdict | views outlined |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for name, rows in results.items():
        for r in rows:
            lines.append(f"| {name} | {r['object']} | {r['view']} | {r['click_to_first_outlines_s']:.2f} | "
                         f"{r['click_to_refined_pose_s']:.2f} | {r['click_to_outlines_s']:.2f} | "
                         f"{r['server_job_s']:.2f} | {r['error_mm']:.2f} / {r['error_deg']:.2f} | {r['verdict']} | "
                         f"{r['outlined_views']} |")
    reasons = {(r["object"], "; ".join(r["reasons"])) for rows in results.values() for r in rows if r["reasons"]}
    lines += ["", "Reasons given with the verdicts:", ""] + [f"* object {o}: {why}" for o, why in sorted(reasons)]
    lines += ["", "| 3D view, code | first outlines, median (s) | refined pose, median (s) | judged, median (s) | "
              "judged, max (s) | server median (s) |", "|---|---|---|---|---|---|"]
    lines += [f"| {name} | {s['first_median_s']:.2f} | {s['refined_pose_median_s']:.2f} | {s['median_s']:.2f} | "
              f"{s['max_s']:.2f} | "
              f"{s['server_median_s']:.2f} |"
              for name, s in summary.items()]
    write_results("bench_label_page", {"meta": meta, "summary": summary, "rows": results}, lines, shown=0)
    print(json.dumps(summary, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
