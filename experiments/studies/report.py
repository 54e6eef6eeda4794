"""Study outputs from ``trials.jsonl``: a CSV of every trial, a markdown report, PNG plots.

Every file is written to a temporary name in the same folder and moved into place with
``os.replace``, so an interrupted report never leaves a half-written file. Units: mm, degrees,
seconds. Plots use matplotlib's Agg backend.
"""

from __future__ import annotations

import csv
import io
import json
from collections import defaultdict
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import Any

import numpy as np

from autoalign.experiments.studies.metrics import CRITERIA, auc
from autoalign.experiments.studies.paper_method import DISCRETISATIONS, PaperOptions
from autoalign.experiments.studies.protocol import PAPER_ITERATIONS, PROTOCOL_CHOICES
from autoalign.io.atomic_files import write_bytes_atomic, write_text_atomic

CSV_COLUMNS = (
    "id", "condition", "part", "method", "model_id", "model_name", "symmetric", "trial", "views", "sigma_mm",
    "noise_kind", "noise_fraction", "diameter_mm", "size_frac", "radius_mm", "init_pos_err_mm", "init_rot_err_deg",
    "pos_err_mm", "rot_err_deg", "rot_err_raw_deg", "dot_cols", "dot_axis_angle", "add_mm", "adds_mm", "addx_mm",
    "success_cols", "success_axis_angle", "success_strict", "success_addx", "iou_mean", "iterations",
    "iters_to_cols", "iters_to_axis_angle", "iters_to_strict", "stopped", "renders", "view_renders", "rays",
    "wall_s", "trial_s", "seed",
)
METHOD_ORDER = ("paper", "autoalign", "adam", "autoalign-seeded", "init")
COLOURS = {"paper": "tab:red", "autoalign": "tab:blue", "adam": "tab:green", "autoalign-seeded": "tab:purple",
           "init": "tab:gray"}

METHOD_NOTES = {
    "paper": "the paper's greedy argmax-IoU procedure (experiments/studies/paper_method.py), from T_init",
    "autoalign": "autoalign.engine.refine.refine(scene, mesh, seed=None): visual-hull centre + 384 orientation "
                 "hypotheses (best {n_starts} climbed on hard IoU{n_starts_note}), LM "
                 "coarse-to-fine (the paper's T_init carries no orientation information)",
    "adam": "the same with RefineOptions(optimizer=Adam())",
    "autoalign-seeded": "refine(scene, mesh, seed=T_init): local refinement from the paper's initial pose",
    "init": "no refinement (the initial pose)",
}


# ----------------------------------------------------------------------------------------------
# Atomic writes
# ----------------------------------------------------------------------------------------------

def atomic_savefig(fig: Any, path: str | Path) -> None:
    """Save a matplotlib figure as PNG via a temporary file and ``os.replace``, then close it."""
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=110, bbox_inches="tight")
    write_bytes_atomic(path, buf.getvalue())
    _plt().close(fig)


# ----------------------------------------------------------------------------------------------
# Tables
# ----------------------------------------------------------------------------------------------

def write_csv(records: list[dict[str, Any]], path: str | Path) -> None:
    """One row per trial, scalar fields only (trajectories and poses stay in trials.jsonl)."""
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=list(CSV_COLUMNS), extrasaction="ignore")
    w.writeheader()
    for r in sorted(records, key=lambda r: (r.get("condition", ""), r.get("method", ""), r.get("model_id", 0),
                                            r.get("trial", 0))):
        w.writerow({k: ("" if r.get(k) is None else r.get(k)) for k in CSV_COLUMNS})
    write_text_atomic(path, buf.getvalue())


def _methods(records: Iterable[dict[str, Any]]) -> list[str]:
    present = {r["method"] for r in records}
    return [m for m in METHOD_ORDER if m in present] + sorted(present - set(METHOD_ORDER))


def _arr(rs: list[dict[str, Any]], key: str) -> np.ndarray:
    return np.array([np.nan if r.get(key) is None else float(r[key]) for r in rs], dtype=np.float64)


def _fmt(x: float, nd: int = 2) -> str:
    if x is None or not np.isfinite(x):
        return "-"
    return f"{x:.{nd}f}"


def _rate(rs: list[dict[str, Any]], crit: str) -> float:
    return float(np.mean([bool(r.get(f"success_{crit}")) for r in rs])) if rs else float("nan")


def method_stats(rs: list[dict[str, Any]], crit: str = "cols") -> dict[str, float]:
    """Summary numbers of one method's trials (see the report's column notes)."""
    n = len(rs)
    ok = [r for r in rs if r.get(f"success_{crit}")]
    its_ok = _arr(ok, f"iters_to_{crit}")
    wall = _arr(rs, "wall_s")
    diam = _arr(rs, "diameter_mm")
    n_ok = len(ok)
    return {
        "n": n, "success": n_ok / n if n else float("nan"),
        "success_axis_angle": _rate(rs, "axis_angle"), "success_strict": _rate(rs, "strict"),
        "success_addx": _rate(rs, "addx"),
        "iters_mean_ok": float(np.nanmean(its_ok)) if n_ok else float("nan"),
        "iters_median_ok": float(np.nanmedian(its_ok)) if n_ok else float("nan"),
        "iters_mean_all": float(np.nanmean(_arr(rs, "iterations"))) if n else float("nan"),
        "wall_mean": float(np.nanmean(wall)) if n else float("nan"),
        "wall_median": float(np.nanmedian(wall)) if n else float("nan"),
        "wall_per_success": float(np.nansum(wall) / n_ok) if n_ok else float("inf"),
        "view_renders": float(np.nanmean(_arr(rs, "view_renders"))) if n else float("nan"),
        "pos_median": float(np.nanmedian(_arr(rs, "pos_err_mm"))) if n else float("nan"),
        "rot_median": float(np.nanmedian(_arr(rs, "rot_err_deg"))) if n else float("nan"),
        "auc_adds": auc(_arr(rs, "adds_mm") / diam) if n else float("nan"),
        "auc_addx": auc(_arr(rs, "addx_mm") / diam) if n else float("nan"),
        "iou": float(np.nanmean(_arr(rs, "iou_mean"))) if n else float("nan"),
    }


def _group(records: list[dict[str, Any]], *keys: str) -> dict[tuple, list[dict[str, Any]]]:
    out: dict[tuple, list[dict[str, Any]]] = defaultdict(list)
    for r in records:
        out[tuple(r.get(k) for k in keys)].append(r)
    return out


def main_table(records: list[dict[str, Any]], condition: str = "main") -> str:
    """The paper-style table of one condition: success, iterations, times per method."""
    rs = [r for r in records if r["condition"] == condition]
    if not rs:
        return f"_no trials in condition {condition!r} yet_\n"
    by = _group(rs, "method")
    lines = ["| method | trials | success (cols) | success (axis-angle) | success (1 mm, 1 deg) | ADD(-S) < 0.1 d "
             "| iterations mean / median (successful) | iterations mean (all) | wall s / trial mean / median "
             "| wall s per converged trial | view-renders / trial | pos. err. median mm | rot. err. median deg "
             "| AUC ADD-S | AUC ADD(-S) | mask IoU |",
             "|" + "---|" * 16]
    stats = {}
    for m in _methods(rs):
        s = stats[m] = method_stats(by[(m,)])
        lines.append(f"| {m} | {s['n']} | {100 * s['success']:.1f} % | {100 * s['success_axis_angle']:.1f} % | "
                     f"{100 * s['success_strict']:.1f} % | {100 * s['success_addx']:.1f} % | "
                     f"{_fmt(s['iters_mean_ok'])} / {_fmt(s['iters_median_ok'], 1)} | {_fmt(s['iters_mean_all'])} | "
                     f"{_fmt(s['wall_mean'], 1)} / {_fmt(s['wall_median'], 1)} | {_fmt(s['wall_per_success'], 1)} | "
                     f"{_fmt(s['view_renders'], 0)} | {_fmt(s['pos_median'], 3)} | {_fmt(s['rot_median'], 3)} | "
                     f"{_fmt(s['auc_adds'], 3)} | {_fmt(s['auc_addx'], 3)} | {_fmt(s['iou'], 4)} |")
    lines.append(f"| paper (reported) | 44 models | - | - | - | - | {PAPER_ITERATIONS} / - | - | - | - | - | - | - | - | - | - |")
    out = "\n".join(lines) + "\n"
    if "paper" in stats:
        for m in ("autoalign", "adam", "autoalign-seeded"):
            if m in stats and np.isfinite(stats[m]["wall_per_success"]) and np.isfinite(stats["paper"]["wall_per_success"]):
                ratio = stats["paper"]["wall_per_success"] / stats[m]["wall_per_success"]
                out += (f"\nSpeed ratio {m}:paper in wall time per converged trial: 1 : {ratio:.2f} "
                        f"({m} {'faster' if ratio > 1 else 'slower'} by x{max(ratio, 1 / ratio):.2f}).\n")
            elif m in stats:
                out += f"\nSpeed ratio {m}:paper: undefined (one of them converged in no trial).\n"
    return out


def symmetry_table(records: list[dict[str, Any]], condition: str = "main") -> str:
    rs = [r for r in records if r["condition"] == condition]
    if not rs:
        return ""
    lines = ["| method | asymmetric: trials | success (cols) | rot. err. median deg | symmetric: trials | "
             "success (cols) | rot. err. median deg (mod symmetry) |", "|" + "---|" * 7]
    for m in _methods(rs):
        a = [r for r in rs if r["method"] == m and not r["symmetric"]]
        s = [r for r in rs if r["method"] == m and r["symmetric"]]
        lines.append(f"| {m} | {len(a)} | {_fmt(100 * _rate(a, 'cols'), 1)} % | "
                     f"{_fmt(float(np.nanmedian(_arr(a, 'rot_err_deg'))) if a else np.nan, 3)} | {len(s)} | "
                     f"{_fmt(100 * _rate(s, 'cols'), 1)} % | "
                     f"{_fmt(float(np.nanmedian(_arr(s, 'rot_err_deg'))) if s else np.nan, 3)} |")
    return "\n".join(lines) + "\n"


def condition_table(records: list[dict[str, Any]], part: str, include_main: bool = True) -> str:
    """Success and iterations per (condition, method) of one study part."""
    rs = [r for r in records if r["part"] == part or (include_main and r["condition"] == "main")]
    rs_part = [r for r in rs if r["part"] == part]
    if not rs_part:
        return f"_no trials of part {part!r} yet_\n"
    trials = {(r["model_id"], r["trial"]) for r in rs_part}
    lines = ["| condition | method | trials | success (cols) | success (axis-angle) | success (1 mm, 1 deg) "
             "| iterations mean / median (successful) | wall s / trial | pos. err. median mm | rot. err. median deg |",
             "|" + "---|" * 10]
    for (cond, m), g in sorted(_group(rs, "condition", "method").items(),
                               key=lambda kv: (kv[0][0] != "main", kv[0][0], METHOD_ORDER.index(kv[0][1])
                                               if kv[0][1] in METHOD_ORDER else 99)):
        if cond == "main":  # the main condition restricted to the trials the part used (paired)
            g = [r for r in g if (r["model_id"], r["trial"]) in trials]
            if not any(r["method"] == m for r in rs_part):
                continue
        if not g:
            continue
        s = method_stats(g)
        lines.append(f"| {cond} | {m} | {s['n']} | {100 * s['success']:.1f} % | {100 * s['success_axis_angle']:.1f} % | "
                     f"{100 * s['success_strict']:.1f} % | {_fmt(s['iters_mean_ok'])} / {_fmt(s['iters_median_ok'], 1)} | "
                     f"{_fmt(s['wall_mean'], 1)} | {_fmt(s['pos_median'], 3)} | {_fmt(s['rot_median'], 3)} |")
    return "\n".join(lines) + "\n"


def _paper_failures(failed: list[dict[str, Any]]) -> tuple[int, int]:
    """``(flip, stuck)`` counts among failed paper trials (see :func:`paper_gap_table`); the rest are slow."""
    flip = sum(r["iou_mean"] >= 0.85 and r["rot_err_deg"] >= 150 for r in failed)
    stuck = sum(r["iou_mean"] < 0.85 for r in failed)
    return flip, stuck


def paper_gap_table(records: list[dict[str, Any]], condition: str = "main") -> str:
    """Where the paper's procedure succeeds and how it fails, from its own trials (measured).

    Rows bin the trials by initial rotation error (modulo symmetry); failures are split into
    'flip' (the silhouettes fit, IoU >= 0.85, but the rotation is >= 150 degrees off: a half
    turn that looks alike from every single view), 'stuck' (IoU < 0.85: a local optimum of the
    one-view argmax) and 'slow' (within 150 degrees and fitting, but not within 1 mm / 0.99).
    """
    rs = [r for r in records if r["condition"] == condition and r["method"] == "paper"]
    if not rs:
        return "_no paper trials_\n"
    lines = ["| initial rotation error | trials | success (cols) | iterations mean / median (successful) "
             "| failed: flip | failed: stuck | failed: slow |", "|---|---|---|---|---|---|---|"]
    for lo, hi in ((0, 60), (60, 120), (120, 180.01), (0, 180.01)):
        g = [r for r in rs if lo <= r["init_rot_err_deg"] < hi]
        if not g:
            continue
        ok = [r for r in g if r["success_cols"]]
        its = [r["iters_to_cols"] for r in ok if r["iters_to_cols"] is not None]
        bad = [r for r in g if not r["success_cols"]]
        flip, stuck = _paper_failures(bad)
        name = "all" if (lo, hi) == (0, 180.01) else f"{lo}-{min(hi, 180):.0f} deg"
        lines.append(f"| {name} | {len(g)} | {_fmt(100 * len(ok) / len(g), 1)} % | "
                     f"{_fmt(np.mean(its)) if its else '-'} / {_fmt(np.median(its), 1) if its else '-'} | "
                     f"{flip} | {stuck} | {len(bad) - flip - stuck} |")
    return "\n".join(lines) + "\n"


def paper_gap_text(records: list[dict[str, Any]], condition: str = "main") -> str:
    """The written explanation of the gap to the reported 10.36 iterations, with this run's counts."""
    rs = [r for r in records if r["condition"] == condition and r["method"] == "paper"]
    if not rs:
        return ""
    bad = [r for r in rs if not r["success_cols"]]
    flip, stuck = _paper_failures(bad)
    med_init = float(np.median(_arr(rs, "init_rot_err_deg")))
    return (
        f"Why `paper` needs more iterations, and converges less often, than the reported "
        f"{PAPER_ITERATIONS} (measured above; `plots/success_vs_initial_error.png`). Each iteration moves "
        "the pose by the argmax of ONE view's silhouette IoU, over rotations about one axis (parallel to "
        "that camera's x axis) and shifts in its image plane. From a uniformly random orientation (the "
        f"text's 'random 3D orientation'; median initial error here {med_init:.0f} degrees) most of the "
        "error is a large rotation about axes the current view does not offer, and what one view's IoU "
        "rewards need not bring the pose closer in 3-D. Of the "
        f"{len(bad)} failed trials, {stuck} are 'stuck' (mean IoU below 0.85: no discrete move improves "
        f"the view's IoU, yet the silhouettes do not fit) and {flip} are 'flips' (silhouettes fit, but the "
        "rotation is 150-180 degrees off: a half turn that looks alike from every single view). Success and "
        "speed fall with the initial rotation error (rows above); symmetric models, whose half turns are "
        "symmetries, converge far more often. The paper reports no success rate and does not say whether "
        "its mean counts only converged runs; we count iterations over converged trials only, and the "
        "sensitivity rows below show how the other readings of the protocol change this. `autoalign` meets "
        "the same starts by searching orientations in all views before refining.\n")


def _paper_choices(opts: dict[str, Any] | None) -> str:
    o = PaperOptions(**opts) if opts else PaperOptions()
    d = DISCRETISATIONS[o.discretisation]
    return (f"- Rotation axis: through the object centre, parallel to the camera's **{o.rot_axis}** axis "
            "(the paper's figure; its text says 'rotated about z-axis': run as `sens-axis-z`).\n"
            f"- Move set `{o.discretisation}`: rotation angles 0 and +-{', '.join(f'{a:g}' for a in d.angles_deg)} deg; "
            f"translations 0 and {', '.join(f'{a:g}' for a in d.steps_mm)} mm along {d.n_directions} directions "
            f"in the image-parallel plane; every combination ({d.n_candidates} moves per iteration), composed "
            "literally as exp(xi1 theta1) exp(xi2 theta2) T. Alternative `geo4` (x4 ladders to 64): `sens-disc-geo4`.\n"
            f"- Camera per iteration: **{o.camera_order}** (cycle = view k mod n; the views are randomly placed, so "
            "this is a random order without repeats). Alternative `random` (i.i.d.): `sens-order-random`.\n"
            "- IoU: hard masks of that one view (the equation's I^{i}), the SAME mitsuba ray caster autoalign "
            "uses, against the same open3d target masks. The argmax is exact for small moves and over the "
            f"top {o.top_k} of each pre-screened group of larger moves (tests check it against brute force).\n"
            "- Stop: oracle, as the paper counts iterations until convergence: the run ends when both readings "
            "of the success test hold; otherwise on a stall (a full cycle of views without a move, or with the "
            f"pose staying within {o.stall_mm:g} mm / {o.stall_deg:g} deg) or after {o.max_iters} iterations.\n"
            "- Iterations are argmax moves (one view each, idle ones included); autoalign's (and adam's) are "
            "optimiser iterations over all views along the winning hypothesis' whole path, from its start "
            "(one of the scored orientations at the visual-hull centre, polished by two rounds of hard-IoU "
            "pattern search over turns of 10 and 5 degrees) through the search level (1/8 resolution) and 1/4 "
            "to full resolution, an iteration being a step tried (rendered), accepted or not (a half-turn flip "
            "of the search's best continues that one's path); the other hypotheses count in renders and time, "
            "the scoring and polishing of the orientations (batched hard-mask ray casting at 1/16-1/8 "
            "resolution) in time only, none in iterations. Their error curves start "
            "at that start, the paper's at T_init.\n")


def _n_starts(records: list[dict[str, Any]], method: str) -> dict[str, str]:
    """The fields of :data:`METHOD_NOTES`: ``n_starts``, how many scored orientations started the
    engine's search in ``method``'s trials (``RefineOptions.search.n_starts``, recorded per trial as
    ``n_coarse``, its former name; 8 before the search kept 16), and ``n_starts_note``, which says so
    when that is not today's."""
    from autoalign.engine.refine import RefineOptions

    values = {r.get("n_coarse") for r in records if r.get("method") == method}
    text = " / ".join(str(v) for v in sorted(int(v) for v in values if v is not None))
    if None in values:
        text += " (some trials: not recorded)" if text else "? (not recorded)"
    now = RefineOptions().search.n_starts
    note = f"; RefineOptions.search.n_starts was {text} in these trials and is {now} now" if values - {now} else ""
    return {"n_starts": text, "n_starts_note": note}


def _views_of(records: list[dict[str, Any]], condition: str, last_run: dict[str, Any]) -> str:
    """How many views the trials of ``condition`` had (``8 views``; several numbers when the folder
    mixes them; the last run's when there are no trials yet)."""
    views = sorted({int(r["views"]) for r in records if r.get("condition") == condition and r.get("views") is not None})
    if not views and last_run.get("views") is not None:
        views = [int(last_run["views"])]
    if not views:
        return "views not recorded"
    return f"{' / '.join(map(str, views))} view{'s' if views != [1] else ''}"


def _this_study(records: list[dict[str, Any]], config: dict[str, Any]) -> str:
    """A line saying that the choices below are the paper's protocol and what this study's main
    trials had instead where they differ (``--views``, the image settings)."""
    setup = (config.get("fingerprint") or {}).get("setup") or {}
    image = (f", images of {setup['width']}x{setup['height']} px with f = {setup['focal']:g} px"
             if {"width", "height", "focal"} <= setup.keys() else "")
    return (f"The paper's protocol as read here; this study's main trials had "
            f"{_views_of(records, 'main', config.get('last_run') or {})}{image}.\n\n")


def markdown(records: list[dict[str, Any]], config: dict[str, Any] | None = None) -> str:
    """The full results report."""
    cfg = (config or {}).get("last_run", {})
    methods = _methods(records)
    parts = ["# Simulated convergence study (ProgressLabeller protocol)\n",
             f"{len(records)} trials; methods: {', '.join(methods)}. Per-trial data: `trials.csv` "
             "(and `trials.jsonl` with trajectories and poses). Plots in `plots/`.\n",
             f"## Main result ({_views_of(records, 'main', cfg)}, paper's initial-pose distribution)\n",
             main_table(records),
             "\nColumns: success = fraction of trials whose final pose passes the test; iterations are those "
             "to the first pose passing the headline test, over successful trials; wall time is the method's "
             "own (scene synthesis and metrics excluded); 'wall s per converged trial' = total wall time / "
             "successful trials; view-renders = single-view silhouettes rendered (paper: candidate "
             "silhouettes incl. low-resolution pre-screens; autoalign: multi-view renders x views); AUC "
             "over thresholds 0-0.1 diameter.\n",
             "\n## Symmetric vs asymmetric models (rotation judged modulo symmetry)\n", symmetry_table(records),
             "\n## The paper's procedure: where it converges and how it fails\n", paper_gap_table(records),
             "\n", paper_gap_text(records), "\n",
             "\n## Number of views\n", condition_table(records, "views"),
             "\n## Mask noise\n", condition_table(records, "noise"),
             "\n## Sensitivity to the ambiguous protocol choices\n", condition_table(records, "sensitivity"),
             "\n## Protocol choices\n", _this_study(records, config or {})]
    for k, v in PROTOCOL_CHOICES.items():
        parts.append(f"- **{k}**: {v}\n")
    parts.append("\n### The paper method\n")
    parts.append(_paper_choices(cfg.get("paper")))
    parts.append("\n### Success tests and errors\n")
    for k, v in CRITERIA.items():
        parts.append(f"- `{k}`: {v}\n")
    parts.append("- Rotation errors, axis dots and positions are taken against the ground truth's symmetric "
                 "equivalent closest to the estimate (models_info symmetries_discrete / symmetries_continuous, "
                 "BOP composition S_cont(phi) S_disc, phi optimised in closed form); `rot_err_raw_deg` ignores "
                 "symmetry. ADD-S uses the closest point (scipy cKDTree) on 1000 surface samples; ADD(-S) is "
                 "ADD for asymmetric and ADD-S for symmetric models.\n")
    parts.append("\n### Methods\n")
    for m in methods:
        parts.append(f"- `{m}`: {METHOD_NOTES.get(m, '').format(**_n_starts(records, m))}\n")
    if cfg:
        parts.append(f"\nLast run settings: `{json.dumps(cfg)}`\n")
    return "".join(parts)


# ----------------------------------------------------------------------------------------------
# Plots
# ----------------------------------------------------------------------------------------------

def _plt() -> Any:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _curves(rs: list[dict[str, Any]], col: int, max_len: int) -> np.ndarray:
    """Trajectories padded with their last value (the pose stays once a method stops)."""
    out = np.full((len(rs), max_len), np.nan)
    for i, r in enumerate(rs):
        t = np.array([p[col] for p in r.get("traj", [])], dtype=np.float64)
        if t.size == 0:
            continue
        n = min(len(t), max_len)
        out[i, :n] = t[:n]
        out[i, n:] = t[n - 1]
    return out


def plot_error_vs_iteration(records: list[dict[str, Any]], path: Path) -> None:
    plt = _plt()
    rs = [r for r in records if r["condition"] == "main"]
    fig, axes = plt.subplots(1, 2, figsize=(11, 4))
    for m in _methods(rs):
        g = [r for r in rs if r["method"] == m]
        dense = [r for r in g if len(r.get("traj", [])) > 2 or r.get("iterations", 0) <= 1]
        for ax, col in zip(axes, (0, 1)):
            if len(dense) == len(g) and g:
                L = int(np.percentile([len(r["traj"]) for r in g], 95))
                C = _curves(g, col, max(L, 2))
                x = np.arange(C.shape[1])
                q1, med, q3 = np.nanpercentile(C, [25, 50, 75], axis=0)
                ax.plot(x, med, color=COLOURS.get(m), label=m)
                ax.fill_between(x, q1, q3, color=COLOURS.get(m), alpha=0.2)
            elif g:  # only start and end known: a marker at the median iteration count with quartiles
                start = _curves(g, col, 1)[:, 0]
                end = np.array([r["traj"][-1][col] for r in g])
                it = float(np.median(_arr(g, "iterations")))
                q = np.percentile(end, [25, 50, 75])
                ax.errorbar([it], [q[1]], yerr=[[q[1] - q[0]], [q[2] - q[1]]], fmt="o", color=COLOURS.get(m),
                            label=f"{m} (final only)")
                ax.plot([0], [np.median(start)], "x", color=COLOURS.get(m))
    axes[0].set_ylabel("position error (mm)")
    axes[1].set_ylabel("rotation error (deg, mod symmetry)")
    for ax in axes:
        ax.set_xlabel("iteration")
        ax.set_yscale("log")
        ax.grid(True, which="both", alpha=0.3)
    axes[0].axhline(1.0, color="k", lw=0.8, ls="--")
    _legend(axes[0])
    fig.suptitle("Error against iteration (median, quartiles shaded)")
    atomic_savefig(fig, path)


def _legend(ax: Any) -> None:
    if ax.get_legend_handles_labels()[0]:
        ax.legend(fontsize=8)
    else:
        ax.text(0.5, 0.5, "no trials of this part yet", ha="center", va="center", transform=ax.transAxes)


def _success_lines(ax: Any, series: dict[str, tuple[list[float], list[float]]], xlabel: str) -> None:
    for m, (x, y) in series.items():
        ax.plot(x, [100 * v for v in y], "o-", color=COLOURS.get(m), label=m)
    ax.set_xlabel(xlabel)
    ax.set_ylabel("success (cols) %")
    ax.set_ylim(-3, 103)
    ax.grid(True, alpha=0.3)


def _mean_success_by(rs: list[dict[str, Any]], x_of: Callable[[dict[str, Any]], float]
                     ) -> tuple[list[float], list[float]]:
    """The distinct ``x_of`` values of ``rs``, sorted, and the share of successes (cols) at each."""
    pts = defaultdict(list)
    for r in rs:
        pts[x_of(r)].append(bool(r["success_cols"]))
    xs = sorted(pts)
    return xs, [float(np.mean(pts[x])) for x in xs]


def plot_success_vs_views(records: list[dict[str, Any]], path: Path) -> None:
    plt = _plt()
    rs = [r for r in records if r["part"] in ("views", "main")]
    trials = {(r["model_id"], r["trial"]) for r in rs if r["part"] == "views"} or None
    series = {m: _mean_success_by([r for r in rs if r["method"] == m
                                   and (trials is None or (r["model_id"], r["trial"]) in trials)],
                                  lambda r: int(r["views"]))
              for m in _methods(rs)}
    fig, ax = plt.subplots(figsize=(6, 4))
    _success_lines(ax, series, "number of views")
    ax.set_xscale("log", base=2)
    ax.set_xticks([5, 10, 20, 40], labels=["5", "10", "20", "40"])
    _legend(ax)
    ax.set_title("Success against number of views")
    atomic_savefig(fig, path)


def plot_success_vs_initial_error(records: list[dict[str, Any]], path: Path) -> None:
    plt = _plt()
    rs = [r for r in records if r["condition"] == "main"]
    fig, axes = plt.subplots(1, 2, figsize=(11, 4))
    for ax, key, edges, label in ((axes[0], "init_pos_err_mm", [0, 50, 100, 150, 200, 300, np.inf], "initial position error (mm)"),
                                  (axes[1], "init_rot_err_deg", [0, 30, 60, 90, 120, 150, 180.01], "initial rotation error (deg, mod symmetry)")):
        series = {}
        for m in _methods(rs):
            g = [r for r in rs if r["method"] == m]
            v = _arr(g, key)
            s = np.array([bool(r["success_cols"]) for r in g])
            xs, ys = [], []
            for lo, hi in zip(edges[:-1], edges[1:]):
                sel = (v >= lo) & (v < hi)
                if sel.any():
                    xs.append(float(np.median(v[sel])))
                    ys.append(float(s[sel].mean()))
            series[m] = (xs, ys)
        _success_lines(ax, series, label)
    _legend(axes[0])
    fig.suptitle("Success against initial error (main condition, binned)")
    atomic_savefig(fig, path)


def plot_success_vs_noise(records: list[dict[str, Any]], path: Path) -> None:
    plt = _plt()
    noisy = [r for r in records if r["part"] == "noise"]
    trials = {(r["model_id"], r["trial"]) for r in noisy}
    clean = [r for r in records if r["condition"] == "main" and (r["model_id"], r["trial"]) in trials]
    kinds = sorted({r["noise_kind"] for r in noisy}) or ["erode", "dilate", "shift"]
    fig, axes = plt.subplots(1, len(kinds), figsize=(4.5 * len(kinds), 4), squeeze=False)
    for ax, kind in zip(axes[0], kinds):
        kind_rs = clean + [r for r in noisy if r["noise_kind"] == kind]
        series = {m: _mean_success_by([r for r in kind_rs if r["method"] == m],
                                      lambda r: float(r.get("noise_fraction", 0.0)))
                  for m in _methods(noisy or clean)}
        _success_lines(ax, series, f"fraction of views with {kind} masks")
        ax.set_title(kind)
    _legend(axes[0][0])
    fig.suptitle("Success against mask noise")
    atomic_savefig(fig, path)


PLOTS: dict[str, Callable[[list[dict[str, Any]], Path], None]] = {
    "error_vs_iteration.png": plot_error_vs_iteration,
    "success_vs_views.png": plot_success_vs_views,
    "success_vs_initial_error.png": plot_success_vs_initial_error,
    "success_vs_mask_noise.png": plot_success_vs_noise,
}


def write_reports(out_dir: str | Path) -> dict[str, Path]:
    """Write ``trials.csv``, ``results.md`` and ``plots/*.png`` from ``OUT/trials.jsonl``."""
    from autoalign.batch import read_records

    out = Path(out_dir)
    records = read_records(out / "trials.jsonl")
    cfg_path = out / "config.json"
    config = json.loads(cfg_path.read_text()) if cfg_path.is_file() else None
    paths = {"csv": out / "trials.csv", "markdown": out / "results.md"}
    write_csv(records, paths["csv"])
    write_text_atomic(paths["markdown"], markdown(records, config))
    (out / "plots").mkdir(exist_ok=True)
    if records:
        for name, fn in PLOTS.items():
            p = out / "plots" / name
            fn(records, p)
            paths[name] = p
    return paths
