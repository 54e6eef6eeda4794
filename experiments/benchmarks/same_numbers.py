"""Same numbers before and after a change: a fixed set of ``autoalign refine`` commands run by two
checkouts of the code, case by case in turn, and their poses, sigmas, verdicts, reasons and wall
times compared.

The cases: the bundled example seeded (one object; ``--models``; masks only with a seed radius the
result leaves, so the seed's hold runs) and unseeded; ``bench_scene``'s scenes of 1, 4 and 8 objects
x 40 views from 10 mm / 15 deg off; and the YCB-Video RGB-D frames with masks eroded by 4 px
(every instance 20 mm along its ray and a few degrees off; ``--models`` with and without photos;
one object with depth; with depth, masks only and a seed radius it leaves). Each command runs in a
child process whose working folder is the checkout, so it imports that checkout's code; the
checkouts alternate case by case, so that a busy machine slows both alike.

``python -m autoalign.experiments.benchmarks.same_numbers --before /tmp/before_repo [--after .]``
(``--before``: a copy of the older code, e.g. ``git archive REV | tar -x -C /tmp/before_repo``).
Results: ``experiments/results/same_numbers.md``.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from autoalign.experiments import RESULTS
from autoalign.experiments.benchmarks.bench_scene import make_bench_scene
from autoalign.experiments.result_files import write_results
from autoalign.experiments.studies.rgbd_depth import eroded_folder, starts_along_rays
from autoalign.experiments.studies.shared_data import YCBV_RGBD
from autoalign.io.models import ModelSet

EXAMPLE = Path(__file__).resolve().parents[2] / "autoalign" / "data" / "example"


def cases(work: Path) -> dict[str, list[str]]:
    """Each case's ``refine`` arguments (without ``--out``); the YCB-Video ones only where its frames are."""
    ex = EXAMPLE
    out = {"example seeded": [str(ex / "scene"), "--model", str(ex / "model.ply"), "--init", str(ex / "init_gt.json")],
           "example --models": [str(ex / "scene"), "--models", str(ex / "models"), "--init", str(ex / "init_gt.json")],
           "example held, photos off": [str(ex / "scene"), "--model", str(ex / "model.ply"), "--init",
                                        str(ex / "init_gt.json"), "--photos", "off", "--seed-radius", "0.02,0.02"],
           "example unseeded": [str(ex / "scene"), "--model", str(ex / "model.ply")]}
    for n in (1, 4, 8):
        root = work / f"bench_{n}"
        make_bench_scene(root, n)
        out[f"bench_scene {n} object(s)"] = [str(root / "scene"), "--models", str(root / "models"), "--init",
                                             str(root / "init_gt.json")]
    if not YCBV_RGBD.is_dir():
        return out
    scene = eroded_folder(YCBV_RGBD, work / "ycb_scene", ("scene_camera.json", "scene_gt.json", "rgb", "depth"))
    _, coarse = starts_along_rays(YCBV_RGBD, ModelSet.read(YCBV_RGBD / "models"), 20.0, np.radians([3.0, -2.0, 2.0]))
    (work / "init.json").write_text(json.dumps({"1": coarse}))
    (work / "init8.json").write_text(json.dumps({"1": [coarse[0]]}))
    models, mesh8 = YCBV_RGBD / "models", YCBV_RGBD / "models" / "obj_000008.ply"
    out["ycb --models"] = [str(scene), "--models", str(models), "--init", str(work / "init.json")]
    out["ycb --models, photos off"] = out["ycb --models"] + ["--photos", "off"]
    out["ycb one object, depth"] = [str(scene), "--model", str(mesh8), "--obj-id", "8", "--init", str(work / "init8.json")]
    out["ycb one object held, photos off"] = out["ycb one object, depth"] + ["--photos", "off", "--seed-radius", "3,1"]
    return out


def run_case(checkout: Path, args: list[str], out: Path) -> tuple[float, list[dict[str, Any]]]:
    """The wall time (s) of ``autoalign refine ARGS --out OUT`` run by ``checkout``'s code, and per
    instance its pose, sigmas, verdict and reasons from ``refine.json``."""
    t0 = time.perf_counter()
    p = subprocess.run([sys.executable, "-m", "autoalign.cli.main", "refine", *args, "--out", str(out), "--quiet"],
                       cwd=checkout, capture_output=True, text=True)
    wall = time.perf_counter() - t0
    if p.returncode not in (0, 3):
        raise RuntimeError(f"{checkout}: refine {' '.join(args)} failed ({p.returncode}): {p.stderr[-1000:]}")
    report = json.loads((out / "refine.json").read_text())
    rows = []
    for rec in report.get("instances", [report]):
        unc = rec.get("uncertainty") or {}
        rows.append({"T_wm": rec["pose"]["T_wm"], "sigma_mm": unc.get("sigma_mm"), "sigma_deg": unc.get("sigma_deg"),
                     "verdict": rec["verdict"], "reasons": rec["reasons"]})
    return wall, rows


def largest_difference(a: Any, b: Any) -> float:
    """The largest absolute difference between two nested lists of numbers (0 when both are None)."""
    if a is None and b is None:
        return 0.0
    return float(np.max(np.abs(np.asarray(a, dtype=np.float64) - np.asarray(b, dtype=np.float64))))


def compare(before: Path, after: Path, work: Path) -> list[dict[str, Any]]:
    """Every case run by both checkouts in turn; per case the largest differences and the wall times."""
    rows = []
    for name, args in cases(work).items():
        (wall_b, got_b), (wall_a, got_a) = (run_case(c, args, work / f"{tag} {name}")
                                           for tag, c in (("before", before), ("after", after)))
        rows.append({"case": name, "instances": len(got_a),
                     "pose": max(largest_difference(x["T_wm"], y["T_wm"]) for x, y in zip(got_b, got_a)),
                     "sigma_mm": max(largest_difference(x["sigma_mm"], y["sigma_mm"]) for x, y in zip(got_b, got_a)),
                     "sigma_deg": max(largest_difference(x["sigma_deg"], y["sigma_deg"]) for x, y in zip(got_b, got_a)),
                     "verdicts_same": all(x["verdict"] == y["verdict"] for x, y in zip(got_b, got_a)),
                     "reasons_same": all(x["reasons"] == y["reasons"] for x, y in zip(got_b, got_a)),
                     "wall_before_s": wall_b, "wall_after_s": wall_a})
        print(f"{name}: pose {rows[-1]['pose']:.3g}, verdicts same {rows[-1]['verdicts_same']}, "
              f"{wall_b:.1f} s -> {wall_a:.1f} s", flush=True)
    return rows


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--before", type=Path, required=True, help="a checkout of the older code")
    ap.add_argument("--after", type=Path, default=Path(__file__).resolve().parents[2], help="default: this checkout")
    ap.add_argument("--out", type=Path, default=RESULTS)
    args = ap.parse_args(argv)
    with tempfile.TemporaryDirectory() as tmp:
        rows = compare(args.before.resolve(), args.after.resolve(), Path(tmp))
    table = ["# Same numbers before and after", "",
             f"`{args.before}` against `{args.after}`: the largest difference of any pose entry (4x4, mm and "
             "rotation entries) and of any sigma; verdicts and reasons compared as text; wall time of the "
             "whole command (the checkouts alternate case by case).", "",
             "| case | instances | max d pose | max d sigma mm | max d sigma deg | verdicts | reasons | wall before s | "
             "wall after s | ratio |", "|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        table.append(f"| {r['case']} | {r['instances']} | {r['pose']:.2g} | {r['sigma_mm']:.2g} | {r['sigma_deg']:.2g} | "
                     f"{'same' if r['verdicts_same'] else 'DIFFER'} | {'same' if r['reasons_same'] else 'DIFFER'} | "
                     f"{r['wall_before_s']:.1f} | {r['wall_after_s']:.1f} | {r['wall_after_s'] / r['wall_before_s']:.2f} |")
    write_results("same_numbers", {"before": str(args.before), "after": str(args.after), "rows": rows}, table, args.out)


if __name__ == "__main__":
    main()
