"""Glass and metal in path-traced photos (issue 45, must-shows 1 and 3): glassware standing on a
textured table among metal and opaque objects, path-traced with mitsuba
(:mod:`~autoalign.experiments.scenes.path_traced`), with depth that sees through the glass.

Each scene: 7 procedural objects (:data:`GLASSWARE`, 5 of them standing, of clear or frosted
glass; one of polished or brushed aluminium; one textured opaque), 32 views of 640 x 480 at
450-700 mm on a ring (every other scene in front of a mirror-like backdrop, only the cameras in
front of it); sensor depth through the glass onto what lies behind it, with blobs of holes on the
glass and the metal. Masks eroded by 3 px, and in 1 view in 4 cut by a straight line to half
(:func:`~autoalign.experiments.studies.photo_evidence.cut_mask`).

Conditions, each ``autoalign refine --models`` from ``--init`` 10 mm / 15 deg off, nothing
declared in ``materials.json``: ``all`` (the degraded masks, photos and depth: the defaults),
``resting`` (as ``all``, with ``--resting``: held to the table plane fitted to the depth),
``masks`` (the degraded masks alone: ``--photos off --depth off``), ``exact-masks`` and
``exact-all`` (the same with the exact masks: does a term pull a pose away from where exact masks
put it?), ``none`` (as ``all``, without ``--init``: do the glasses come out standing the right
way up?) and ``photos`` (the photos and the depth, every mask withheld: ``--masks none``). Per instance: the error (symmetry-aware), the verdict, and whether the depth was read as
seeing through it.

``python -m autoalign.experiments.studies.glass_photos [--scenes 8] [--views 32] [--spp 32]``
(results: ``experiments/results/glass_photos.md``)
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import tempfile
from pathlib import Path

import cv2
import numpy as np
from numpy.typing import NDArray

from autoalign.experiments import RESULTS
from autoalign.experiments.commands import run_autoalign
from autoalign.experiments.result_files import write_results
from autoalign.experiments.scenes.path_traced import SEE_THROUGH, PathTracing
from autoalign.experiments.scenes.photo_scene import write_photo_scene
from autoalign.experiments.scenes.procedural_models import models_info_entry, procedural_models
from autoalign.experiments.scenes.synthetic import perturb_pose
from autoalign.experiments.studies.metrics import Symmetries, pose_errors
from autoalign.experiments.studies.photo_evidence import cut_mask
from autoalign.geometry.mesh import Mesh, mesh_from_trimesh
from autoalign.geometry.se3 import make_pose
from autoalign.io.bop import read_scene, scene_gt_of

GLASSWARE = ("mug", "can_plain", "bottle_plain", "travel_mug", "pitcher", "bowl", "oil_can")
"""Procedural models that stand on their -z side, as glassware: cups with a handle (mug, pitcher:
not symmetric), a tumbler-like can, a bottle, a bowl."""
GLASS_PER_SCENE = 5
CONDITIONS = ("all", "resting", "masks", "exact-masks", "exact-all", "none", "photos")
MASKS_ONLY = ["--photos", "off", "--depth", "off"]
NO_MASKS = ["--masks", "none"]


def degrade_masks(scene: Path, rng: np.random.Generator) -> None:
    """Erode every mask of ``scene`` by 3 px, and cut those of 1 view in 4 to half (in place)."""
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (7, 7))
    for path in sorted((scene / "mask_visib").glob("*.png")):
        m = cv2.erode(cv2.imread(str(path), cv2.IMREAD_GRAYSCALE), kernel) > 0
        if int(path.stem.split("_")[0]) % 4 == 3 and m.any():
            m = cut_mask(m, 0.5, rng)
        cv2.imwrite(str(path), m.astype(np.uint8) * 255)


def make_scene(seed: int, work: Path, views: int, spp: int) -> tuple[list[Mesh], list[str], list[Symmetries]]:
    """The scene of ``seed`` (module doc) written into ``work`` (``scene/``, ``scene_degraded/``,
    ``models/``, ``init.json``), or found there from an earlier run (``--keep``: the renders are
    the slow part); its meshes, materials and symmetries."""
    rng = np.random.default_rng([seed, 4545])
    pool = {p.name: p for p in procedural_models()}
    glass = [pool[n] for n in rng.choice(GLASSWARE, GLASS_PER_SCENE, replace=False)]
    others = [p for n, p in pool.items() if n not in GLASSWARE]
    metal, opaque = (others[int(i)] for i in rng.choice(len(others), 2, replace=False))
    chosen = [*glass, metal, opaque]
    materials = [("glass", "frosted")[j % 2] for j in range(GLASS_PER_SCENE)] + [("metal", "brushed")[seed % 2], "opaque"]
    meshes = [mesh_from_trimesh(p.mesh, p.name) for p in chosen]
    syms = [Symmetries.from_info(models_info_entry(p)) for p in chosen]
    if (work / "init.json").is_file():
        return meshes, materials, syms
    tracing = PathTracing(spp=spp, backdrop_y_mm=300.0 if seed % 2 else None, seed=seed)
    ps = write_photo_scene(work / "scene", meshes, views, seed=seed, depth=True, dist_range=(450.0, 700.0),
                           materials=materials, tracing=tracing, upright=[j < GLASS_PER_SCENE for j in range(len(chosen))])
    shutil.copytree(ps.folder, work / "scene_degraded")
    degrade_masks(work / "scene_degraded", rng)
    models = work / "models"
    models.mkdir()
    for j, p in enumerate(chosen):
        p.mesh.export(models / f"obj_{j + 1:06d}.ply")
    (models / "models_info.json").write_text(json.dumps({str(j + 1): models_info_entry(p) for j, p in enumerate(chosen)}))
    starts = [perturb_pose(T, 10.0, 15.0, rng, m.centre) for T, m in zip(ps.poses, meshes)]
    (work / "init.json").write_text(json.dumps(scene_gt_of([(j + 1, T) for j, T in enumerate(starts)],
                                                           ps.cameras[:1], [0])))
    return meshes, materials, syms


def true_poses(scene: Path) -> list[NDArray[np.float64]]:
    """The world-from-model poses (mm) of ``scene``'s instances, from its first image's labels."""
    first = read_scene(scene).cameras[0]
    entries = json.loads((scene / "scene_gt.json").read_text())["0"]
    return [np.linalg.inv(first.T_cw) @ make_pose(np.reshape(e["cam_R_m2c"], (3, 3)), np.asarray(e["cam_t_m2c"]))
            for e in entries]


def run_scene(seed: int, work: Path, views: int, spp: int, conditions: list[str], reuse: bool = False) -> list[dict]:
    """One scene (module doc), refined under each condition (``reuse``: a condition's output kept
    from an earlier run is read, not refined again); one row per instance and condition."""
    meshes, materials, syms = make_scene(seed, work, views, spp)
    poses = true_poses(work / "scene")
    rows = []
    for condition in conditions:
        out = work / f"out_{condition}"
        if not (reuse and (out / "refine.json").is_file()):
            shutil.rmtree(out, ignore_errors=True)
            scene = work / ("scene" if condition.startswith("exact") else "scene_degraded")
            extra = ((MASKS_ONLY if condition.endswith("masks") else NO_MASKS if condition == "photos" else [])
                     + ([] if condition == "none" else
                     ["--init", str(work / "init.json")]) + (["--resting"] if condition == "resting" else []))
            run_autoalign("refine", str(scene), "--models", str(work / "models"), *extra, "--out", str(out),
                          "--quiet").check()
        doc = json.loads((out / "refine.json").read_text())
        for inst, T_true, mesh, sym, material in zip(doc["instances"], poses, meshes, syms, materials):
            e = pose_errors(np.asarray(inst["pose"]["T_wm"]), T_true, mesh.centre, None, sym)
            depth = inst.get("depth") or {}
            rows.append({"seed": seed, "condition": condition, "object": mesh.name, "material": material,
                         "err_mm": e.pos_err_mm, "err_deg": e.rot_err_deg, "verdict": inst["verdict"],
                         "sees_through": bool(depth.get("sees_through", False)), "reasons": inst["reasons"],
                         "T_wm": inst["pose"]["T_wm"], "wall_s": doc["timings"]["total"]})
    moved_by_terms(rows, meshes, syms)
    return rows


def moved_by_terms(rows: list[dict], meshes: list[Mesh], syms: list[Symmetries]) -> None:
    """On each ``exact-all`` row, how far the photos and the depth moved the instance from where the
    exact masks alone put it (``exact-masks``; symmetry-aware, mm / deg), in place."""
    alone = [r for r in rows if r["condition"] == "exact-masks"]
    together = [r for r in rows if r["condition"] == "exact-all"]
    if len(alone) == len(together) == len(meshes):
        for a, b, mesh, sym in zip(alone, together, meshes, syms):
            e = pose_errors(np.asarray(b["T_wm"]), np.asarray(a["T_wm"]), mesh.centre, None, sym)
            b["moved_mm"], b["moved_deg"] = e.pos_err_mm, e.rot_err_deg


def kind_of(material: str) -> str:
    """``glass`` (clear or frosted), ``metal`` (polished or brushed) or ``opaque``."""
    return "glass" if material in SEE_THROUGH else "opaque" if material == "opaque" else "metal"


def table(rows: list[dict]) -> list[str]:
    """Per condition and kind: accuracy, verdicts, wrong poses called ``ok``, upside-down poses, and
    recognition."""
    lines = ["| condition | kind | instances | within 1 mm / 1 deg | within 2 mm / 2 deg | within 3 mm / 3 deg | "
             "median err mm / deg | ok/check/failed | outside 3 mm / 3 deg and ok | upside down | "
             "read as seeing through | largest move from the exact masks alone, mm / deg |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for condition in CONDITIONS:
        for kind in ("glass", "metal", "opaque"):
            sel = [r for r in rows if r["condition"] == condition and kind_of(r["material"]) == kind]
            if not sel:
                continue
            mm, deg = np.array([r["err_mm"] for r in sel]), np.array([r["err_deg"] for r in sel])
            verdicts = "/".join(str(sum(r["verdict"] == v for r in sel)) for v in ("ok", "check", "failed"))
            wrong_ok = sum(r["verdict"] == "ok" and (r["err_mm"] > 3 or r["err_deg"] > 3) for r in sel)
            within = [f"{np.mean((mm <= t) & (deg <= t)):.0%}" for t in (1, 2, 3)]
            lines.append(f"| {condition} | {kind} | {len(sel)} | {' | '.join(within)} | "
                         f"{np.median(mm):.2f} / {np.median(deg):.2f} | {verdicts} | {wrong_ok} | {int(np.sum(deg > 90))} | "
                         f"{sum(r['sees_through'] for r in sel)} of {len(sel)} | {_largest_move(sel)} |")
    return lines


def write(rows: list[dict], args: argparse.Namespace, scenes_done: int) -> None:
    """The results file of the ``scenes_done`` scenes refined so far."""
    conditions = args.conditions.split(",")
    cmd = (f"python -m autoalign.experiments.studies.glass_photos --scenes {args.scenes} --views {args.views} "
           f"--spp {args.spp} --conditions {args.conditions}")
    md = ["# Glass and metal in path-traced photos (synthetic)", "",
          f"`{cmd}` ({scenes_done} of {args.scenes} scenes done): scenes of 7 procedural objects on a textured table "
          f"({GLASS_PER_SCENE} standing glassware of clear or frosted glass, one aluminium, one opaque), path-traced "
          f"with mitsuba ({args.spp} samples a pixel), {args.views} views of 640x480, every other scene before a "
          "mirror; depth through the glass with holes on glass and metal; masks eroded 3 px, 1 view in 4 cut to "
          "half (`exact-`: exact masks); `refine --models` from `--init` 10 mm / 15 deg off (`none`: no seed), "
          "nothing declared; `resting`: with `--resting` (the table plane fitted to the depth); `masks`: photos and depth off; `photos`: every mask withheld (`--masks none`). Errors are symmetry-aware; upside down: more than "
          "90 deg off.", "", *table(rows), "",
          "| scene | condition | object | material | err mm | err deg | verdict | sees through |",
          "|---|---|---|---|---|---|---|---|",
          *[f"| {r['seed']} | {r['condition']} | {r['object']} | {r['material']} | {r['err_mm']:.2f} | "
            f"{r['err_deg']:.2f} | {r['verdict']} | {'yes' if r['sees_through'] else 'no'} |" for r in rows]]
    write_results("glass_photos", {"command": cmd, "scenes_done": scenes_done, "rows": rows}, md, args.out,
                  shown=4 + len(conditions) * 3)


def _largest_move(rows: list[dict]) -> str:
    """The rows' largest move from the exact masks' pose (:func:`moved_by_terms`), or ``-``."""
    moved = [(r["moved_mm"], r["moved_deg"]) for r in rows if "moved_mm" in r]
    return f"{max(m for m, _ in moved):.2f} / {max(d for _, d in moved):.2f}" if moved else "-"


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--scenes", type=int, default=8)
    p.add_argument("--views", type=int, default=32)
    p.add_argument("--spp", type=int, default=32, help="path-tracing samples per pixel")
    p.add_argument("--conditions", default=",".join(CONDITIONS), help="comma-separated, of: " + ", ".join(CONDITIONS))
    p.add_argument("--keep", type=Path, help="keep the scenes and outputs in this folder (a scene found there "
                                             "from an earlier run is refined again, not rendered again)")
    p.add_argument("--reuse", action="store_true", help="with --keep: read a condition's output kept there instead "
                                                        "of refining it again")
    p.add_argument("--picture", type=Path, help="write the README's picture here: the first two rows of scene 1's "
                                                "overlay under --resting (needs both)")
    p.add_argument("--out", type=Path, default=RESULTS)
    args = p.parse_args(argv)
    conditions = args.conditions.split(",")
    if unknown := set(conditions) - set(CONDITIONS):
        p.error(f"--conditions: unknown {', '.join(sorted(unknown))}; choose from {', '.join(CONDITIONS)}")
    rows: list[dict] = []
    with tempfile.TemporaryDirectory() as tmp:
        root = args.keep or Path(tmp)
        for seed in range(args.scenes):
            work = root / f"scene_{seed}"
            work.mkdir(parents=True, exist_ok=True)
            rows += run_scene(seed, work, args.views, args.spp, conditions, args.reuse and args.keep is not None)
            write(rows, args, seed + 1)  # after every scene: a long run's results so far
            print(f"scene {seed}: {len(rows)} rows", file=sys.stderr, flush=True)
        overlay = root / "scene_1" / "out_resting" / "overlay.png"
        if args.picture is not None and overlay.is_file():
            write_picture(cv2.imread(str(overlay)), args.picture)
    return 0


def write_picture(overlay: NDArray[np.uint8], path: Path, width: int = 800) -> None:
    """The top two of the overlay's three rows of views (under its title band), ``width`` pixels wide."""
    top = overlay[30:30 + 2 * (overlay.shape[0] - 30) // 3]
    h, w = top.shape[:2]
    cv2.imwrite(str(path), cv2.resize(top, (width, round(h * width / w)), interpolation=cv2.INTER_AREA),
                [cv2.IMWRITE_PNG_COMPRESSION, 9])


if __name__ == "__main__":
    sys.exit(main())
