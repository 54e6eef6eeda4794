"""Segmenter failures as on the real scenes, measured there and replayed on synthetic scenes.

``measure_rates`` classifies every annotated (view, object) of ``../shared/real/lmo_dev`` whose
ground-truth visible mask is trusted (the scene's ``quality.json``): the SAM mask is ``good``
(IoU >= 0.8 with the truth), ``wrong object`` (IoU < 0.1), ``parts missed`` (IoU < 0.8, 85% of
it inside the truth), ``leak`` (IoU < 0.8, 85% of the truth inside it), otherwise ``shifted``;
``empty`` (no mask at all) is counted over every annotated view. ``corrupt_like_sam`` applies
those failures to synthetic visible masks at those rates; the study refines every instance of
synthetic five-object scenes with such masks, from a coarse start and with no seed, and checks
that each instance is within 2 mm / 2 deg or flagged. Results: ``experiments/results/sam_failures.md``.

``python -m autoalign.experiments.studies.sam_failures [--scenes 10] [--seeds init,none]``
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from collections import Counter
from dataclasses import dataclass, replace
from pathlib import Path

import cv2
import numpy as np
from numpy.typing import NDArray

from autoalign.engine.refine import RefineOptions
from autoalign.experiments import RESULTS
from autoalign.experiments.result_files import write_results
from autoalign.experiments.scenes.procedural_models import (
    procedural_models,
    write_models,
)
from autoalign.experiments.scenes.synthetic import (
    default_K,
    perturb_pose,
    random_rotation,
    raycast_visible_masks,
    ring_cameras,
    translate_mask,
    write_multi_scene,
)
from autoalign.experiments.studies.metrics import Symmetries, pose_errors
from autoalign.experiments.studies.shared_data import REAL_SCENES
from autoalign.geometry.se3 import make_pose
from autoalign.io.atomic_files import write_json_atomic
from autoalign.io.bop import scene_gt_of
from autoalign.io.instances import read_init_poses, read_instance_scenes, read_instances
from autoalign.io.models import ModelSet
from autoalign.scene.refine import refine_scene

DEFAULT_DATA = REAL_SCENES
FAILURES = ("empty", "wrong object", "parts missed", "leak", "shifted")
MEASURED_RATES = {"empty": 0.059, "wrong object": 0.145, "parts missed": 0.172, "leak": 0.053, "shifted": 0.056}
"""``measure_rates`` on the two lmo_dev scenes (338 trusted views, 506 annotated): 42% of masks fail."""


def measure_rates(data: Path = DEFAULT_DATA) -> tuple[dict[str, float], int]:
    """Failure rates of the SAM masks of every scene under ``data`` (see the module doc)."""
    counts: Counter[str] = Counter()
    trusted = annotated = 0
    for q_path in sorted(data.glob("*/quality.json")):
        for objs in json.loads(q_path.read_text())["per_view"].values():
            for e in objs.values():
                if not e.get("annotated"):
                    continue
                annotated += 1
                if not e["sam_mask"]:
                    counts["empty"] += 1
                    continue
                if not e.get("gt_mask_trusted"):
                    continue
                trusted += 1
                if e["iou"] >= 0.8:
                    continue
                kind = ("wrong object" if e["iou"] < 0.1 else "parts missed" if e["mask_in_gt"] >= 0.85
                        else "leak" if e["gt_in_mask"] >= 0.85 else "shifted")
                counts[kind] += 1
    rates = {k: counts[k] / max(trusted, 1) for k in FAILURES if k != "empty"}
    rates["empty"] = counts["empty"] / max(annotated, 1)
    return {k: round(rates[k], 3) for k in FAILURES}, trusted


def _half_plane(mask: NDArray[np.bool_], rng: np.random.Generator, keep: tuple[float, float]) -> NDArray[np.bool_]:
    """The part of ``mask`` on one side of a random line through it, keeping a fraction in ``keep``."""
    ys, xs = np.nonzero(mask)
    a = rng.uniform(0, 2 * np.pi)
    proj = (xs - xs.mean()) * np.cos(a) + (ys - ys.mean()) * np.sin(a)
    cut = np.quantile(proj, 1.0 - rng.uniform(*keep))
    out = np.zeros_like(mask)
    out[ys[proj >= cut], xs[proj >= cut]] = True
    return out


def corrupt_like_sam(masks: list[list[NDArray[np.bool_]]], rng: np.random.Generator,
                     rates: dict[str, float] = MEASURED_RATES) -> tuple[list[list[NDArray[np.bool_]]], Counter]:
    """Visible masks ``[view][instance]`` with failures drawn at ``rates``: empty, another
    instance's mask (a wrong object), a part missed (40-80% kept on one side of a line), a leak
    (grown by 6-14 px towards one side) or shifted by 3-8 px. Returns the masks and the counts."""
    kinds = list(rates)
    p = np.array([rates[k] for k in kinds])
    out, counts = [], Counter()
    for view in masks:
        row = []
        for k, m in enumerate(view):
            u = rng.uniform()
            kind = kinds[int(np.searchsorted(np.cumsum(p), u))] if u < p.sum() else "good"
            if not m.any():
                kind = "good"
            if kind == "empty":
                m = np.zeros_like(m)
            elif kind == "wrong object":
                others = [o for j, o in enumerate(view) if j != k and o.any()]
                m = others[int(rng.integers(len(others)))].copy() if others else translate_mask(m, 60, 40)
            elif kind == "parts missed":
                m = _half_plane(m, rng, (0.4, 0.8))
            elif kind == "leak":
                r = int(rng.integers(6, 15))
                grown = cv2.dilate(m.astype(np.uint8), np.ones((2 * r + 1, 2 * r + 1), np.uint8)) > 0
                m = m | _half_plane(grown, rng, (0.3, 0.5))
            elif kind == "shifted":
                d = rng.uniform(3, 8)
                a = rng.uniform(0, 2 * np.pi)
                m = translate_mask(m, int(round(d * np.cos(a))), int(round(d * np.sin(a))))
            counts[kind] += 1
            row.append(m)
        out.append(row)
    return out, counts


def shift_outline(mask: NDArray[np.bool_], px: float) -> NDArray[np.bool_]:
    """``mask`` with its outline moved ``px`` outwards (negative: inwards), by the exact Euclidean
    distance to it."""
    if px >= 0:
        return mask | (cv2.distanceTransform((~mask).astype(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE) <= px)
    return cv2.distanceTransform(mask.astype(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE) > -px


@dataclass(frozen=True)
class SystematicErrors:
    """Errors no pixel noise explains, drawn per view: each instance's mask outline moved by up to
    ``outline_px`` in or out (uniform), and each camera's principal point off by ``camera_px`` in a
    random direction (masks cast through the moved camera, the true one written)."""

    outline_px: float = 0.0
    camera_px: float = 0.0


def make_sam_scene(root: Path, k: int, n_obj: int = 5, views: int = 40, rates: dict[str, float] = MEASURED_RATES,
                   systematic: SystematicErrors = SystematicErrors(), seed: int = 13
                   ) -> tuple[list[NDArray[np.float64]], Counter, list[str]]:
    """Synthetic scene ``k``: ``n_obj`` procedural objects close together (they hide each other),
    ``views`` views of 640x480, masks ray-cast (with ``systematic`` errors) then failed like SAM's;
    writes ``root/scene``, ``root/models`` and ``root/init_gt.json`` (10 mm / 15 deg off); returns
    the true poses, the failures drawn and the objects' names."""
    rng = np.random.default_rng([seed, k])
    pool = procedural_models()
    chosen = [pool[int(i)] for i in rng.choice(len(pool), n_obj, replace=False)]
    write_models(root / "models", chosen)
    models = ModelSet.read(root / "models")
    meshes = [models.mesh(i + 1) for i in range(n_obj)]
    truth = []
    for j, m in enumerate(meshes):
        a = 2 * np.pi * j / n_obj
        R = random_rotation(rng)
        truth.append(make_pose(R, np.array([75 * np.cos(a), 75 * np.sin(a), 40.0]) - R @ m.centre))
    cams = ring_cameras(views, rng, target=(0.0, 0.0, 40.0), K=default_K(640, 480, 600.0))
    cast_through = cams
    if systematic.camera_px > 0:
        angles = rng.uniform(0, 2 * np.pi, len(cams))
        cast_through = [replace(c, K=c.K + systematic.camera_px * np.array([[0, 0, np.cos(a)], [0, 0, np.sin(a)], [0, 0, 0]]))
                        for c, a in zip(cams, angles)]
    cast = raycast_visible_masks(meshes, truth, cast_through)
    if systematic.outline_px > 0:
        cast = [[shift_outline(m, rng.uniform(-systematic.outline_px, systematic.outline_px)) if m.any() else m
                 for m in view] for view in cast]
    masks, counts = corrupt_like_sam(cast, rng, rates)
    write_multi_scene(root / "scene", meshes, list(range(1, n_obj + 1)), truth, cams, masks)
    coarse = [perturb_pose(T, 10.0, 15.0, rng, m.centre) for T, m in zip(truth, meshes)]
    write_json_atomic(root / "init_gt.json", scene_gt_of([(j + 1, T) for j, T in enumerate(coarse)], cams[:1], [0]))
    return truth, counts, [m.name for m in chosen]


def run_scene(root: Path, k: int, n_obj: int = 5, views: int = 40, seeds: tuple[str, ...] = ("init",)
              ) -> list[dict]:
    """Make scene ``k`` under ``root`` and refine it from the coarse start (``"init"`` in
    ``seeds``) and/or with no seed (``"none"``); one row per instance and seed."""
    truth, counts, names = make_sam_scene(root, k, n_obj, views)
    found = read_instance_scenes(root / "scene", read_instances(root / "scene"))
    models = ModelSet.read(root / "models")
    rows = []
    for seed in seeds:
        starts = read_init_poses(root / "init_gt.json", found) if seed == "init" else {}
        for r in refine_scene(found, models, starts, RefineOptions()).results:
            i = r.instance.obj_id
            mesh = models.mesh(i)
            sym = Symmetries.from_info({"symmetries_discrete": models.info[i].get("symmetries_discrete", []),
                                        "symmetries_continuous": models.info[i].get("symmetries_continuous", [])})
            e = pose_errors(r.result.T_wm, truth[r.instance.index], mesh.centre, None, sym)
            rows.append({"scene": k, "seed": seed, "obj": names[r.instance.index], "err_mm": e.pos_err_mm,
                         "err_deg": e.rot_err_deg, "verdict": r.verdict.status, "reasons": r.verdict.reasons,
                         "turn_gap": r.result.turn_gap, "failures": dict(counts)})
    return rows


def within(r: dict, mm: float = 2.0, deg: float = 2.0) -> bool:
    return r["err_mm"] <= mm and r["err_deg"] <= deg


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--scenes", type=int, default=10)
    p.add_argument("--data", type=Path, default=DEFAULT_DATA)
    p.add_argument("--seeds", default="init,none", help="init (10 mm / 15 deg off), none (no seed), or both")
    p.add_argument("--out", type=Path, default=RESULTS)
    a = p.parse_args(argv)
    rates, n_trusted = measure_rates(a.data) if a.data.is_dir() else (MEASURED_RATES, 0)
    seeds = a.seeds.split(",")
    rows: list[dict] = []
    for k in range(a.scenes):
        with tempfile.TemporaryDirectory() as tmp:
            for r in run_scene(Path(tmp), k, seeds=tuple(seeds)):
                rows.append(r)
                print(json.dumps(r), flush=True)
    lines = ["# Segmenter failures like SAM's on synthetic five-object scenes", "",
             f"Rates measured on the real scenes ({n_trusted} trusted views): "
             + ", ".join(f"{k} {v:.1%}" for k, v in rates.items()) + f" (replayed: {MEASURED_RATES}).", "",
             f"`python -m autoalign.experiments.studies.sam_failures --scenes {a.scenes} --seeds {a.seeds}`: {a.scenes} "
             "scenes of five objects, 40 views of 640x480; seed `init`: starts 10 mm / 15 deg off, `none`: no "
             "seed (the search).", "",
             "| seed | instances | within 2 mm and 2 deg | outside it and not flagged (verdict ok) | "
             "verdicts ok / check / failed |", "|---|---|---|---|---|"]
    for seed in seeds:
        sub = [r for r in rows if r["seed"] == seed]
        ok = [within(r) for r in sub]
        unflagged_wrong = [r for r, good in zip(sub, ok) if not good and r["verdict"] == "ok"]
        lines.append(f"| {seed} | {len(sub)} | {np.mean(ok):.1%} ({sum(ok)}) | {len(unflagged_wrong)} | "
                     + " / ".join(str(sum(r["verdict"] == s for r in sub)) for s in ("ok", "check", "failed")) + " |")
    lines += ["", "| seed | scene | object | err mm | err deg | turn gap | verdict | reasons |",
              "|---|---|---|---|---|---|---|---|"]
    for r in rows:
        gap = "-" if r["turn_gap"] is None else f"{r['turn_gap']:.3f}"
        lines.append(f"| {r['seed']} | {r['scene']} | {r['obj']} | {r['err_mm']:.3f} | {r['err_deg']:.3f} | {gap} | "
                     f"{r['verdict']} | {'; '.join(r['reasons'])} |")
    write_results("sam_failures", {"rates": rates, "rows": rows}, lines, a.out, shown=10)
    return 0


if __name__ == "__main__":
    sys.exit(main())
