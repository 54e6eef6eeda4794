"""Running the study's trials: task list, one trial, parallel execution, resume.

* :func:`build_tasks` expands a :class:`StudyConfig` into one task per (condition, model, trial,
  method); a task is a plain JSON-able dict whose ``id`` is unique and stable.
* :func:`run_task` runs one task in the current process and returns its record (errors in mm
  and degrees, iterations, renders, wall time, the error trajectory).
* :func:`run_study` runs the tasks not yet in ``OUT/trials.jsonl`` with :func:`autoalign.batch.run_tasks`
  (in-process, across processes or on a Dask cluster; resumable), the engine ``autoalign refine
  --batch`` runs on too.
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable, Iterable
from dataclasses import asdict, dataclass, field, replace
from functools import lru_cache
from pathlib import Path
from typing import Any

import numpy as np

from autoalign.batch import RunSummary, check_resume, run_tasks, settings_changes
from autoalign.errors import AutoalignError
from autoalign.experiments.studies.metrics import (
    CRITERIA,
    PoseErrors,
    Symmetries,
    pose_errors,
    success,
)
from autoalign.experiments.studies.paper_method import PaperOptions
from autoalign.experiments.studies.protocol import (
    ALT_SIGMA_MM,
    PAPER_SIGMA_MM,
    ImageSetup,
    make_trial,
    noise_rng,
)
from autoalign.io.atomic_files import write_json_atomic

METHODS = ("paper", "autoalign", "adam", "autoalign-seeded", "init")
"""``paper``: the discrete argmax-IoU baseline; ``autoalign``: ``refine(seed=None)`` (visual hull +
orientation hypotheses: the paper's initial orientation is uniformly random, so it carries no
information); ``adam``: the same with ``RefineOptions(optimizer=Adam())``; ``autoalign-seeded``:
``refine(seed=T_init)``; ``init``: no refinement (the initial pose itself)."""
ALL_METHODS = ("paper", "autoalign", "adam", "autoalign-seeded")
INIT_DEPENDENT = ("paper", "autoalign-seeded", "init")
PARTS = ("main", "views", "noise", "sensitivity")
SWEEP_VIEWS = (5, 10, 20, 40)
NOISE_KINDS = ("erode", "dilate", "shift")
NOISE_FRACTIONS = (0.25, 0.5)
HEADLINE = "cols"
TRIAL_SETTINGS = ("views", "sigma_mm", "noise", "paper", "models", "seed", "setup")
"""A task's fields that define its trial besides its id: recorded with it, and a rerun that
differs in them is refused (:func:`autoalign.batch.check_resume`) instead of skipping it as done."""
PROCEDURAL = "procedural44"
TRAJ_MAX = 400  # trajectory points kept per trial
RECORDS = "trials.jsonl"


@dataclass(frozen=True)
class StudyConfig:
    """What to run.

    Attributes:
        models: ``"procedural44"`` or a BOP models folder (``models_info.json`` + ``obj_*.ply``).
        model_ids: models to use (None: all).
        trials: trials per model of the ``main`` condition.
        views: views of the ``main`` condition (the paper: 40).
        methods: subset of :data:`METHODS`.
        seed: master seed.
        parts: subset of :data:`PARTS`: ``main``; ``views`` (5/10/20/40 views); ``noise`` (eroded,
            dilated, shifted masks on 25 % / 50 % of the views); ``sensitivity`` (the paper
            method under the alternative readings: sigma 31.6 mm, random camera order, rotation
            about the optical axis, coarser discretisation).
        sweep_trials: trials per model of every condition outside ``main`` (trials 0.. so they
            pair with the main ones).
        sigma_mm: initial position noise of the main condition (per axis).
        paper: the paper method's settings in the main condition.
        setup: image size and apparent object size.
    """

    models: str = PROCEDURAL
    model_ids: tuple[int, ...] | None = None
    trials: int = 10
    views: int = 40
    methods: tuple[str, ...] = ALL_METHODS
    seed: int = 0
    parts: tuple[str, ...] = ("main",)
    sweep_trials: int = 1
    sigma_mm: float = PAPER_SIGMA_MM
    paper: PaperOptions = field(default_factory=PaperOptions)
    setup: ImageSetup = field(default_factory=ImageSetup)

    def fingerprint(self) -> dict[str, Any]:
        """The settings two runs into one output folder must share: they define the trials (the
        main condition's views and initial noise, the paper method's settings), so a folder holds
        one study (its report one number of views). Trials, methods and parts may change."""
        return {"models": self.models, "seed": self.seed, "setup": asdict(self.setup), "views": self.views,
                "sigma_mm": self.sigma_mm, "paper": asdict(self.paper)}


# ----------------------------------------------------------------------------------------------
# Models
# ----------------------------------------------------------------------------------------------

@dataclass
class ModelEntry:
    """One object: mesh (mm), symmetries, surface points for ADD, name."""

    model_id: int
    name: str
    mesh: Any
    sym: Symmetries
    points: np.ndarray


def resolve_models(models: str) -> str:
    """``procedural44`` or the absolute path of a BOP models folder; raises AutoalignError otherwise."""
    if models == PROCEDURAL:
        return models
    p = Path(models).expanduser()
    if not p.is_dir():
        raise AutoalignError(f"--models {models}: not a folder; pass 'procedural44' or a BOP models folder "
                             "with models_info.json and obj_XXXXXX.ply files")
    if not (p / "models_info.json").is_file():
        raise AutoalignError(f"--models {models}: no models_info.json in it; pass a BOP models folder "
                             "(models_info.json + obj_XXXXXX.ply)")
    return str(p.resolve())


@lru_cache(maxsize=4)
def model_ids(models: str) -> tuple[int, ...]:
    """All model ids of a model source."""
    if models == PROCEDURAL:
        from autoalign.experiments.scenes.procedural_models import PROCEDURAL_COUNT

        return tuple(range(1, PROCEDURAL_COUNT + 1))
    from autoalign.experiments.scenes.procedural_models import load_bop_models_info

    info = load_bop_models_info(models)
    ids = tuple(sorted(i for i in info if (Path(models) / f"obj_{i:06d}.ply").is_file()))
    if not ids:
        raise AutoalignError(f"--models {models}: models_info.json lists no model with an obj_XXXXXX.ply file")
    return ids


@lru_cache(maxsize=1)
def _procedural() -> list[Any]:
    from autoalign.experiments.scenes.procedural_models import procedural_models

    return procedural_models()


@lru_cache(maxsize=8)
def get_model(models: str, model_id: int) -> ModelEntry:
    """Load one model (cached per process)."""
    from autoalign.geometry.mesh import load_mesh, mesh_from_trimesh

    if models == PROCEDURAL:
        pm = _procedural()[model_id - 1]
        mesh = mesh_from_trimesh(pm.mesh, pm.name)
        sym = Symmetries.from_info({"symmetries_discrete": pm.symmetries_discrete,
                                    "symmetries_continuous": pm.symmetries_continuous})
        name = pm.name
    else:
        from autoalign.experiments.scenes.procedural_models import load_bop_models_info

        info = load_bop_models_info(models)
        mesh = load_mesh(Path(models) / f"obj_{model_id:06d}.ply", name=f"obj_{model_id:06d}")
        sym = Symmetries.from_info(info.get(model_id))
        name = mesh.name
    return ModelEntry(model_id, name, mesh, sym, mesh.sample_points(1000, seed=0))


# ----------------------------------------------------------------------------------------------
# Tasks
# ----------------------------------------------------------------------------------------------

def _condition(name: str, part: str, views: int, sigma_mm: float, noise: dict[str, Any] | None,
               paper: PaperOptions, methods: Iterable[str]) -> dict[str, Any]:
    return {"condition": name, "part": part, "views": views, "sigma_mm": sigma_mm, "noise": noise,
            "paper": asdict(paper), "methods": list(methods)}


def conditions(cfg: StudyConfig) -> list[dict[str, Any]]:
    """The study's conditions (see :class:`StudyConfig`), each with the methods it runs."""
    out = []
    m = [x for x in cfg.methods]
    if "main" in cfg.parts:
        out.append(_condition("main", "main", cfg.views, cfg.sigma_mm, None, cfg.paper, m))
    if "views" in cfg.parts:
        for n in SWEEP_VIEWS:
            if n != cfg.views:
                out.append(_condition(f"views{n}", "views", n, cfg.sigma_mm, None, cfg.paper, m))
    if "noise" in cfg.parts:
        for kind in NOISE_KINDS:
            for frac in NOISE_FRACTIONS:
                out.append(_condition(f"noise-{kind}-{frac:g}", "noise", cfg.views, cfg.sigma_mm,
                                      {"kind": kind, "fraction": frac}, cfg.paper, m))
    if "sensitivity" in cfg.parts:
        dep = [x for x in m if x in INIT_DEPENDENT]
        paper_only = [x for x in m if x == "paper"]
        alt_sigma = ALT_SIGMA_MM if cfg.sigma_mm == PAPER_SIGMA_MM else PAPER_SIGMA_MM
        out.append(_condition(f"sens-sigma{alt_sigma:.1f}", "sensitivity", cfg.views, alt_sigma, None, cfg.paper, dep))
        for label, alt in (("order-random", replace(cfg.paper, camera_order="random")),
                           ("axis-z", replace(cfg.paper, rot_axis="z")),
                           ("disc-geo4", replace(cfg.paper, discretisation="geo4"))):
            out.append(_condition(f"sens-{label}", "sensitivity", cfg.views, cfg.sigma_mm, None, alt, paper_only))
    return [c for c in out if c["methods"]]


def build_tasks(cfg: StudyConfig, ids: Iterable[int] | None = None) -> list[dict[str, Any]]:
    """One task per (condition, model, trial, method), ordered trial-major so early results
    cover many models. ``ids`` defaults to ``cfg.model_ids`` or every model of the source."""
    ids = list(ids if ids is not None else (cfg.model_ids or model_ids(cfg.models)))
    tasks = []
    conds = conditions(cfg)
    for trial in range(max(cfg.trials, cfg.sweep_trials)):
        for c in conds:
            if trial >= (cfg.trials if c["part"] == "main" else cfg.sweep_trials):
                continue
            for mid in ids:
                for method in c["methods"]:
                    t = {k: v for k, v in c.items() if k != "methods"}
                    t.update(id=f"{c['condition']}|m{mid}|t{trial}|{method}", model_id=int(mid), trial=int(trial),
                             method=method, models=cfg.models, seed=int(cfg.seed), setup=asdict(cfg.setup))
                    t["settings"] = {k: t[k] for k in TRIAL_SETTINGS}
                    tasks.append(t)
    return tasks


# ----------------------------------------------------------------------------------------------
# One trial
# ----------------------------------------------------------------------------------------------

@lru_cache(maxsize=2)
def _scene(models: str, model_id: int, trial: int, views: int, sigma_mm: float, noise_key: str, seed: int,
           setup_key: str) -> tuple[Any, Any]:
    from autoalign.experiments.scenes.synthetic import corrupt_views, make_scene

    entry = get_model(models, model_id)
    setup = ImageSetup(**{k: tuple(v) if isinstance(v, list) else v for k, v in json.loads(setup_key).items()})
    geo = make_trial(entry.mesh.centre, entry.mesh.diameter, seed, model_id, trial, views, sigma_mm, setup)
    scene = make_scene(entry.mesh, geo.T_gt, geo.cameras)
    noise = json.loads(noise_key)
    if noise:
        masks, idx = corrupt_views(scene.masks, noise["fraction"], noise_rng(seed, model_id, trial), kinds=(noise["kind"],))
        scene.masks = masks
        scene.skipped = tuple()
    return geo, scene


def _errors(T: np.ndarray, geo: Any, entry: ModelEntry, with_add: bool = True) -> PoseErrors:
    return pose_errors(T, geo.T_gt, entry.mesh.centre, entry.points if with_add else None, entry.sym)


def _flags(e: PoseErrors, diameter: float) -> dict[str, bool]:
    return {f"success_{c}": success(e, c, diameter) for c in CRITERIA}


def _trajectory(poses: list[np.ndarray], geo: Any, entry: ModelEntry) -> list[list[float]]:
    """``[pos_err_mm, rot_err_deg, dot_cols, dot_axis_angle]`` per pose (no ADD: cheap)."""
    out = []
    for T in poses:
        e = _errors(T, geo, entry, with_add=False)
        out.append([round(e.pos_err_mm, 5), round(e.rot_err_deg, 5), round(e.dot_cols, 6), round(e.dot_axis_angle, 6)])
    return out


def _first_success(traj: list[list[float]], criterion: str) -> int | None:
    for k, (pos, rot, dc, da) in enumerate(traj):
        e = {"pos_err_mm": pos, "rot_err_deg": rot, "dot_cols": dc, "dot_axis_angle": da}
        if success(e, criterion):
            return k
    return None


def _engine_poses(result: Any) -> list[np.ndarray] | None:
    """Per-iteration poses of the winning run, if the engine reports them (``history[*]['poses']``)."""
    poses = []
    for h in getattr(result, "history", []) or []:
        p = h.get("poses") if isinstance(h, dict) else None
        if p is None:
            return None
        poses.extend(np.asarray(x, dtype=np.float64) for x in p)
    return poses


def run_task(task: dict[str, Any]) -> dict[str, Any]:
    """Run one task (see :func:`build_tasks`) and return its record (JSON-able)."""
    from autoalign.engine.refine import RefineOptions, hard_ious, refine
    from autoalign.losses.compared_views import ComparedViews
    from autoalign.engine.solver import Adam
    from autoalign.experiments.studies.paper_method import refine_paper
    from autoalign.rasterizers.soft_silhouette import SoftSilhouetteRasterizer

    t_task = time.perf_counter()
    models, mid, trial = task["models"], int(task["model_id"]), int(task["trial"])
    entry = get_model(models, mid)
    geo, scene = _scene(models, mid, trial, int(task["views"]), float(task["sigma_mm"]),
                        json.dumps(task.get("noise"), sort_keys=True), int(task["seed"]),
                        json.dumps(task["setup"], sort_keys=True))
    diameter = float(entry.mesh.diameter)
    method = task["method"]
    rec: dict[str, Any] = {k: task[k] for k in ("id", "condition", "part", "model_id", "trial", "method", "views",
                                                 "sigma_mm", "seed")}
    rec["noise_kind"] = (task.get("noise") or {}).get("kind", "")
    rec["noise_fraction"] = float((task.get("noise") or {}).get("fraction", 0.0))
    rec.update(model_name=entry.name, symmetric=entry.sym.symmetric, diameter_mm=diameter,
               size_frac=geo.size_frac, radius_mm=geo.radius_mm)
    e0 = _errors(geo.T_init, geo, entry)
    rec.update(init_pos_err_mm=e0.pos_err_mm, init_rot_err_deg=e0.rot_err_deg)
    rast = SoftSilhouetteRasterizer(entry.mesh)
    extra: dict[str, Any] = {}
    t0 = time.perf_counter()
    if method == "paper":
        opts = PaperOptions(**task["paper"])

        def stop(T: np.ndarray) -> bool:  # oracle stop: both readings of the paper's criterion met
            e = _errors(T, geo, entry, with_add=False)
            return success(e, "cols") and success(e, "axis_angle")

        rng = np.random.default_rng([int(task["seed"]), mid, trial, 7])
        res = refine_paper(rast, scene, geo.T_init, opts, rng=rng, stop=stop)
        wall = time.perf_counter() - t0
        T_final, poses = res.T_wm, [geo.T_init] + res.poses
        extra.update(iterations=res.iterations, stopped=res.stopped, view_renders=res.view_renders, rays=res.rays,
                     renders=res.view_renders, moves=int(sum(res.moved)))
    elif method == "init":
        wall = time.perf_counter() - t0
        T_final, poses = geo.T_init, [geo.T_init]
        extra.update(iterations=0, stopped="none", view_renders=0, rays=0, renders=0)
    elif method in ("autoalign", "adam", "autoalign-seeded"):
        opts = RefineOptions(optimizer=Adam()) if method == "adam" else RefineOptions()
        seed = geo.T_init if method == "autoalign-seeded" else None
        res = refine(scene, entry.mesh, seed=seed, options=opts)
        wall = time.perf_counter() - t0
        T_final = res.T_wm
        hist = _engine_poses(res)
        poses = [res.T_init] + hist if hist is not None else [res.T_init, res.T_wm]
        extra.update(iterations=int(res.iterations), stopped="ambiguous" if res.ambiguous else "done",
                     renders=int(res.renders), view_renders=int(res.renders) * len(scene), rays=None,
                     n_coarse=int(opts.search.n_starts),  # the record keeps the field's former name
                     per_iteration_poses=hist is not None, timings={k: round(v, 4) for k, v in res.timings.items()})
    else:
        raise ValueError(f"unknown method {method!r}; choose one of {METHODS}")
    e = _errors(T_final, geo, entry)
    rec.update(e.as_dict())
    rec.update(_flags(e, diameter))
    rec["iou_mean"] = float(np.mean(hard_ious(rast, ComparedViews.of(scene), T_final)))
    traj = _trajectory(poses, geo, entry)
    if len(traj) > TRAJ_MAX:  # keep the start and the end
        traj = traj[: TRAJ_MAX // 2] + traj[-TRAJ_MAX // 2:]
    rec.update(extra)
    if method == "paper":
        for c in ("cols", "axis_angle", "strict"):
            rec[f"iters_to_{c}"] = _first_success(traj, c)
    else:  # the engine has no oracle: its iteration count, when its final pose passes
        for c in ("cols", "axis_angle", "strict"):
            rec[f"iters_to_{c}"] = rec["iterations"] if rec[f"success_{c}"] else None
    rec.update(wall_s=wall, trial_s=time.perf_counter() - t_task, traj=traj,
               T_final=[float(x) for x in np.asarray(T_final).ravel()],
               T_gt=[float(x) for x in geo.T_gt.ravel()], T_init=[float(x) for x in geo.T_init.ravel()])
    return rec


# ----------------------------------------------------------------------------------------------
# Records on disk
# ----------------------------------------------------------------------------------------------

def _check_config(out: Path, cfg: StudyConfig) -> None:
    """Refuse a folder whose ``config.json`` says its trials are of other settings (the names an
    older folder's fingerprint has; its trials' own settings are checked by :func:`check_resume`)."""
    p = out / "config.json"
    if not p.is_file():
        return
    try:
        old = json.loads(p.read_text()).get("fingerprint")
    except (json.JSONDecodeError, AttributeError):
        old = None
    if not isinstance(old, dict):
        return
    changes = settings_changes(old, cfg.fingerprint(), all_of_old=False)
    if changes:
        raise AutoalignError(f"{p}: this output folder holds trials of other settings ({changes}); "
                             "use another --out folder, or the same options to resume")


def _check_tasks(cfg: StudyConfig, tasks: list[dict[str, Any]]) -> None:
    """Refuse a study with no trials to run (it would write an empty report and exit 0)."""
    if "main" in cfg.parts and cfg.trials < 1:
        raise AutoalignError(f"--trials {cfg.trials}: the main condition needs at least 1 trial per model; give "
                             "--trials 1 or more")
    if not tasks:
        raise AutoalignError("no trials to run: give --trials (and --sweep-trials for the other parts) 1 or more")


def _write_config(out: Path, cfg: StudyConfig) -> None:
    """``config.json``: the folder's fingerprint and the last run's settings (the report reads them)."""
    last = {"trials": cfg.trials, "views": cfg.views, "methods": list(cfg.methods), "parts": list(cfg.parts),
            "sweep_trials": cfg.sweep_trials, "sigma_mm": cfg.sigma_mm, "paper": asdict(cfg.paper)}
    write_json_atomic(out / "config.json", {"fingerprint": cfg.fingerprint(), "last_run": last})


def run_study(cfg: StudyConfig, out_dir: str | Path, workers: int = 1, scheduler: str | None = None,
              progress: bool = True, task_fn: Callable[[dict[str, Any]], dict[str, Any]] | None = None,
              tasks: list[dict[str, Any]] | None = None) -> RunSummary:
    """Run every task of ``cfg`` whose id is not yet in ``OUT/trials.jsonl``.

    Args:
        cfg: the study.
        out_dir: output folder (created).
        workers: processes (1 = in this process); ignored with ``scheduler``.
        scheduler: a Dask scheduler address (``tcp://host:8786``) or a ``dask.distributed.Client``.
        progress: show a tqdm bar.
        task_fn: the function run per task (default :func:`run_task`; must be importable by
            worker processes when ``workers > 1``).
        tasks: an explicit task list instead of ``build_tasks(cfg)``.

    Raises :class:`AutoalignError` (nothing written then) when there is no trial to run, or when
    ``out_dir`` holds trials of other settings (:meth:`StudyConfig.fingerprint`, :func:`check_resume`).
    """
    out = Path(out_dir)
    all_tasks = tasks if tasks is not None else build_tasks(cfg)
    _check_tasks(cfg, all_tasks)
    _check_config(out, cfg)
    check_resume(all_tasks, out / RECORDS, "trial")  # before anything is written
    out.mkdir(parents=True, exist_ok=True)
    _write_config(out, cfg)
    return run_tasks(all_tasks, task_fn or run_task, out, RECORDS, workers=workers, scheduler=scheduler,
                     progress=progress, desc="simulate", unit="trial")
