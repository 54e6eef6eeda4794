"""The renderer on a GPU: whole ``refine`` commands with ``AUTOALIGN_DEVICE=cpu`` and ``=cuda``
(:mod:`autoalign.runtime.backend`) alternating run by run on one machine, their wall times (median of
the repeats, after one untimed run each that warms drjit's kernel cache and the mesh cache), and how
far the CUDA run's poses, sigmas and verdicts are from the CPU run's.

The cases: the imports and the backend's start; the bundled example seeded and unseeded;
``bench_scene``'s 1, 4 and 8 objects x 40 views from 10 mm / 15 deg off, with the uncertainty (made in
``--scenes`` where missing, which needs open3d; a machine without it can be given them made elsewhere).

``python -m autoalign.experiments.benchmarks.bench_device [--repeats 3] [--scenes DIR]``. Needs an NVIDIA
GPU and driver; CI never runs it. Results: ``experiments/results/bench_device.md``.

A GPU machine without a libLLVM for the CPU backend runs ``--devices cuda --keep DIR``; a CPU run elsewhere
then compares with those labels (``--devices cpu --against DIR``), its times those of another machine.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from autoalign.experiments import RESULTS
from autoalign.experiments.benchmarks.bench_speed import EXAMPLE, INIT_CODE
from autoalign.experiments.commands import CommandRun
from autoalign.experiments.result_files import write_results
from autoalign.geometry.se3 import rotation_angle_deg

DEVICES = ("cpu", "cuda")


@dataclass
class DeviceCase:
    """One command, its wall times on each device, and its outputs' folder per device."""

    name: str
    argv: list[str]
    writes: bool = True
    first: dict[str, float] = field(default_factory=dict)
    walls: dict[str, list[float]] = field(default_factory=dict)

    @property
    def slug(self) -> str:
        """The case's name as a file name."""
        return "".join(c if c.isalnum() else "_" for c in self.name)


def device_cases(scenes: Path) -> list[DeviceCase]:
    """The commands timed; the bench scenes are read from ``scenes/bench_N`` (made there if missing)."""
    refine = ["-m", "autoalign.cli.main", "refine"]
    ex = EXAMPLE
    out = [DeviceCase("imports and the backend's start", ["-c", INIT_CODE], writes=False),
           DeviceCase("example seeded", [*refine, str(ex / "scene"), "--model", str(ex / "model.ply"), "--init",
                                         str(ex / "init_gt.json"), "--quiet"]),
           DeviceCase("example unseeded", [*refine, str(ex / "scene"), "--model", str(ex / "model.ply"), "--quiet"])]
    for n in (1, 4, 8):
        root = scenes / f"bench_{n}"
        if not (root / "init_gt.json").is_file():
            from autoalign.experiments.benchmarks.bench_scene import make_bench_scene  # needs open3d

            make_bench_scene(root, n)
        out.append(DeviceCase(f"bench_scene {n} object(s) x 40 views",
                              [*refine, str(root / "scene"), "--models", str(root / "models"), "--init",
                               str(root / "init_gt.json"), "--quiet"]))
    return out


def run_on(device: str, case: DeviceCase, out: Path, env: dict[str, str]) -> float:
    """Wall time (s) of ``case`` rendering on ``device``, its outputs written to ``out``."""
    argv = list(case.argv)
    if case.writes:
        shutil.rmtree(out, ignore_errors=True)
        argv += ["--out", str(out)]
    t0 = time.perf_counter()
    p = subprocess.run([sys.executable, *argv], env={**env, "AUTOALIGN_DEVICE": device}, capture_output=True,
                       text=True)
    wall = time.perf_counter() - t0
    CommandRun([sys.executable, *argv], wall, p.returncode, p.stderr).check()
    return wall


def labels_of(refine_json: Path) -> list[dict]:
    """Each instance's pose (world from model, 4x4, mm), sigmas and verdict from a ``refine.json``."""
    d = json.loads(refine_json.read_text())
    found = d["instances"] if "instances" in d else [d]
    return [{"T": np.array(i["pose"]["T_wm"]), "sigma_mm": i["uncertainty"]["sigma_mm"],
             "sigma_deg": i["uncertainty"]["sigma_deg"], "verdict": i["verdict"]} for i in found]


def agreement(cpu: Path, cuda: Path) -> dict:
    """How far the CUDA run's labels (its ``refine.json``) are from the CPU run's: the largest position
    (mm) and rotation (deg) difference, the largest relative sigma difference, and the instances whose
    verdicts differ."""
    a, b = labels_of(cpu), labels_of(cuda)
    mm = max(float(np.linalg.norm(x["T"][:3, 3] - y["T"][:3, 3])) for x, y in zip(a, b))
    deg = max(rotation_angle_deg(x["T"][:3, :3], y["T"][:3, :3]) for x, y in zip(a, b))
    rel = max(float(np.max(np.abs(np.array(y[k]) / np.array(x[k]) - 1.0)))
              for x, y in zip(a, b) for k in ("sigma_mm", "sigma_deg"))
    return {"instances": len(a), "max_mm": mm, "max_deg": deg, "max_sigma_rel": rel,
            "verdicts_differ": [k for k, (x, y) in enumerate(zip(a, b)) if x["verdict"] != y["verdict"]],
            "verdicts": {"cpu": [x["verdict"] for x in a], "cuda": [y["verdict"] for y in b]}}


def measure(devices: list[str], scenes: Path, work: Path, repeats: int, keep: Path,
            against: Path | None) -> list[dict]:
    """Every case: once per device untimed, then ``repeats`` times each, the devices alternating; each
    device's last ``refine.json`` kept as ``keep/DEVICE-CASE.json``, and compared with the CUDA run's
    (here, or kept in ``against``)."""
    env = {**{k: v for k, v in os.environ.items() if k not in ("PYTHONDONTWRITEBYTECODE", "AUTOALIGN_DEVICE")},
           "AUTOALIGN_CACHE_DIR": str(work / "mesh_cache"), "PYTHONPYCACHEPREFIX": str(work / "bytecode")}
    rows = []
    for case in device_cases(scenes):
        outs = {d: work / f"out_{d}" for d in devices}
        for d in devices:
            case.first[d] = run_on(d, case, outs[d], env)
            case.walls[d] = []
        for _ in range(repeats):
            for d in devices:
                case.walls[d].append(run_on(d, case, outs[d], env))
        kept = {}
        if case.writes:
            keep.mkdir(parents=True, exist_ok=True)
            for d in devices:
                shutil.copy(outs[d] / "refine.json", keep / f"{d}-{case.slug}.json")
                kept[d] = keep / f"{d}-{case.slug}.json"
            for d in DEVICES:
                if d not in kept and against is not None and (against / f"{d}-{case.slug}.json").is_file():
                    kept[d] = against / f"{d}-{case.slug}.json"
        rows.append({"case": case.name, "first": case.first, "walls": case.walls,
                     "agreement": agreement(kept["cpu"], kept["cuda"]) if len(kept) == 2 else None})
        walls = ", ".join(f"{d} {statistics.median(case.walls[d]):.2f} s" for d in devices)
        print(f"{case.name}: {walls}", flush=True)
    return rows


def device_table(payload: dict) -> list[str]:
    """The results' table from their JSON ``payload`` (as :func:`main` writes it)."""
    med = statistics.median
    devices = payload["devices"]
    table = ["# The renderer on the CPU and on a GPU", "",
             f"On {payload['machine']}: whole commands rendering on {' and '.join(devices)} "
             "(`AUTOALIGN_DEVICE`: `cpu` is drjit's LLVM backend on every core, `cuda` mitsuba's `cuda_ad_rgb`, "
             f"drjit's CUDA backend with OptiX), median wall of {payload['repeats']} runs each after one untimed "
             "run (its wall is the first-run column), the devices alternating run by run. Agreement: the CUDA "
             "run's labels against the CPU run's (largest position and rotation difference over the instances, "
             "largest relative sigma difference, verdicts that differ)"
             + (f", the other from {payload['against']}." if payload.get("against") else "."), "",
             "| command | " + " | ".join(f"first run {d} s | wall {d} s" for d in devices)
             + " | largest difference mm / deg | sigma | verdicts that differ |",
             "|---|" + "---|---|" * len(devices) + "---|---|---|"]
    for r in payload["rows"]:
        ag = r["agreement"]
        times = " | ".join(f"{r['first'][d]:.2f} | {med(r['walls'][d]):.2f}" for d in devices)
        diff = "-" if ag is None else f"{ag['max_mm']:.4f} / {ag['max_deg']:.4f}"
        sig = "-" if ag is None else f"{100 * ag['max_sigma_rel']:.2f}%"
        ver = "-" if ag is None else f"{len(ag['verdicts_differ'])} of {ag['instances']}"
        table.append(f"| {r['case']} | {times} | {diff} | {sig} | {ver} |")
    return table


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--devices", default=",".join(DEVICES), help="which to time, of cpu and cuda (default both)")
    ap.add_argument("--scenes", type=Path, help="where the bench scenes are (made there if missing; default: a "
                                                "temporary folder)")
    ap.add_argument("--keep", type=Path, help="where to keep each case's refine.json per device (default: --out)")
    ap.add_argument("--against", type=Path, help="a --keep folder of another machine's run, to compare labels with")
    ap.add_argument("--out", type=Path, default=RESULTS)
    args = ap.parse_args(argv)
    devices = [d for d in args.devices.split(",") if d]
    if not devices or any(d not in DEVICES for d in devices):
        ap.error(f"--devices {args.devices}: a comma-separated list of {', '.join(DEVICES)}")
    try:
        gpu = subprocess.run(["nvidia-smi", "--query-gpu=name", "--format=csv,noheader"], capture_output=True,
                             text=True).stdout.strip()
    except FileNotFoundError:
        gpu = ""
    machine = f"{platform.node()} ({os.cpu_count()} cores, {gpu or 'no GPU found'})"
    with tempfile.TemporaryDirectory() as tmp:
        rows = measure(devices, args.scenes or Path(tmp) / "scenes", Path(tmp), args.repeats,
                       args.keep or args.out / "bench_device_labels", args.against)
    payload = {"machine": machine, "devices": devices, "repeats": args.repeats,
               "against": None if args.against is None else str(args.against), "rows": rows}
    write_results("bench_device", payload, device_table(payload), args.out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
