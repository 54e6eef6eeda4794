"""The README's examples are tests (issues 15 and 26): every ```bash and ```python block runs here
as written, one test per block, against the bundled example, with its outputs checked.

The blocks run in one temporary folder laid out like the repository root for them: the bundled
example copied to ``autoalign/data/example``, outputs going to ``out/`` (which git ignores in a
checkout). After each block nothing outside ``out/`` has changed there, and neither the bundled
example nor ``experiments/results/simulate`` of the repository has changed (``git status``).

Three blocks cannot run exactly as pasted, and are run as close to it as a test can:

* ``bash .ci/install && COMMAND``: ``.ci/install`` installs system and Python packages (apt-get,
  pip), which a test must not; the test runs ``COMMAND`` (CI runs ``.ci/install`` for real first).
* ``bash .ci/install && pytest``: the whole suite, this test among it; running it from here would
  recurse, so the test checks that ``.ci/run`` (what CI runs) runs this very line.
* ``autoalign label ...`` serves a page until Ctrl-C and opens a browser; the test adds
  ``--no-browser``, reads the address it prints, places the object with one click through the
  page's API, and stops it with SIGINT.

The PyTorch and JAX blocks run in their own tests (the last two), which also check that they reach
1 mm / 1 degree. Every runnable block must have a check in :data:`CHECKS`: a new example without one
fails :func:`test_every_block_is_marked_and_every_example_is_checked`.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import signal
import subprocess
import sys
import time
import urllib.request
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

import cv2
import numpy as np
import pytest

import autoalign
from autoalign.cli.label_http import TOKEN_HEADER

README = Path(__file__).resolve().parents[1] / "README.md"
REPO = README.parent
EXAMPLE = Path(autoalign.__file__).resolve().parent / "data" / "example"
RUNNABLE = ("bash", "sh", "shell", "python")
INSTALL = "bash .ci/install && "
WATCHED = ("autoalign/data", "experiments/results/simulate")
"""Where in the repository a README example could write through the package's defaults."""


@dataclass(frozen=True)
class Block:
    """One fenced block of the README."""

    lang: str
    code: str
    line: int
    heading: str

    @property
    def id(self) -> str:
        return f"{re.sub(r'[^a-z0-9]+', '-', self.heading.lower()).strip('-')}-L{self.line}"


def readme_blocks() -> list[Block]:
    """Every fenced block of the README with its language, first line number and section heading."""
    lines = README.read_text().splitlines()
    blocks, heading, i = [], "", 0
    while i < len(lines):
        if lines[i].startswith("```"):
            end = next(j for j in range(i + 1, len(lines)) if lines[j].startswith("```"))
            blocks.append(Block(lines[i][3:].strip(), "\n".join(lines[i + 1:end]) + "\n", i + 1, heading))
            i = end + 1
            continue
        if lines[i].startswith("#"):
            heading = lines[i].lstrip("#").strip()
        i += 1
    return blocks


def python_blocks(marker: str) -> list[str]:
    """The README's ```python blocks that contain ``marker``."""
    return [b.code for b in readme_blocks() if b.lang == "python" and marker in b.code]


def run_block(marker: str) -> dict:
    """Execute the one README block containing ``marker``; its variables."""
    (block,) = python_blocks(marker)
    scope: dict = {}
    exec(compile(block, str(README), "exec"), scope)  # noqa: S102 - the README's own example
    return scope


# ----------------------------------------------------------------------------------------------
# The folder the examples run in, and what they may change there
# ----------------------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def workdir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A folder holding a copy of the bundled example at ``autoalign/data/example``."""
    root = tmp_path_factory.mktemp("readme")
    shutil.copytree(EXAMPLE, root / "autoalign" / "data" / "example")
    return root


def files_outside_out(root: Path) -> dict[str, tuple[int, int]]:
    """Every file under ``root`` but in ``out/``: relative path -> (size, mtime_ns)."""
    return {p.relative_to(root).as_posix(): (p.stat().st_size, p.stat().st_mtime_ns)
            for p in root.rglob("*") if p.is_file() and p.relative_to(root).parts[0] != "out"}


def repo_status() -> str | None:
    """``git status`` of the repository's :data:`WATCHED` paths (``None`` outside a git checkout)."""
    try:
        run = subprocess.run(["git", "status", "--porcelain", "--untracked-files=all", "--", *WATCHED], cwd=REPO,
                             capture_output=True, text=True, timeout=60)
    except FileNotFoundError:
        return None
    return run.stdout if run.returncode == 0 else None


def environment() -> dict[str, str]:
    """This interpreter's ``autoalign`` command first on PATH."""
    return {**os.environ, "PATH": f"{Path(sys.executable).parent}{os.pathsep}{os.environ.get('PATH', '')}"}


def shell(code: str, cwd: Path, timeout: float = 300) -> str:
    """Run ``code`` in bash (``-e -o pipefail``) in ``cwd``; its stdout (the test fails on a non-zero exit)."""
    run = subprocess.run(["bash", "-e", "-o", "pipefail", "-c", code], cwd=cwd, env=environment(),
                         capture_output=True, text=True, timeout=timeout)
    assert run.returncode == 0, f"exit {run.returncode}\n{code}\nstdout:\n{run.stdout[-3000:]}\nstderr:\n{run.stderr[-3000:]}"
    return run.stdout


def setup_block() -> Block:
    """The Set up block that refines the bundled example into ``out/example``."""
    (block,) = [b for b in readme_blocks() if b.lang == "bash" and b.code.startswith(INSTALL + "autoalign refine")]
    return block


def ensure_refined(root: Path) -> None:
    """``out/example`` as the Set up example makes it (run it, after ``&&``, if that has not happened)."""
    if not (root / "out" / "example" / "scene_gt.json").is_file():
        shell(setup_block().code.removeprefix(INSTALL), root)


# ----------------------------------------------------------------------------------------------
# Running the blocks that cannot run exactly as written
# ----------------------------------------------------------------------------------------------

@dataclass
class LabelRun:
    """What the label example did: its address line, page, state after a click, exit and stderr."""

    address: str
    page: str
    state: dict[str, Any]
    returncode: int
    stderr: str


def http(url: str, body: dict[str, Any] | None = None, token: str = "") -> bytes:
    """GET ``url``, or POST ``body`` as JSON to it with the page's ``token``, as the page does; the response body."""
    data = None if body is None else json.dumps(body).encode()
    req = urllib.request.Request(url, data=data, headers={"Content-Type": "application/json", TOKEN_HEADER: token},
                                 method="GET" if body is None else "POST")
    with urllib.request.urlopen(req, timeout=60) as r:
        return r.read()


def run_label(code: str, cwd: Path) -> LabelRun:
    """Start the label example with ``--no-browser``, wait for its address, click the deepest pixel
    of the mug's mask in image 0 as object 1 (``POST /api/place``, what a click on the page sends),
    wait for the placement, and stop the server with SIGINT (Ctrl-C)."""
    args = code.split() + ["--no-browser"]
    assert args[:2] == ["autoalign", "label"] and "\n" not in code.strip(), code
    proc = subprocess.Popen(args, cwd=cwd, env=environment(), stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True)
    try:
        address = ""
        for line in proc.stdout:  # viser prints its own banner first
            if line.startswith("autoalign label: http"):
                address = line.strip()
                break
        assert address, proc.stderr.read() if proc.poll() is not None else "no address printed"
        url = re.search(r"http://\S+", address).group(0).rstrip("/")
        page = http(url + "/").decode()
        mask = cv2.imread(str(cwd / "autoalign/data/example/scene/mask_visib/000000_000000.png"), cv2.IMREAD_GRAYSCALE)
        depth = cv2.distanceTransform((mask > 0).astype(np.uint8), cv2.DIST_L2, 5)
        row, col = np.unravel_index(int(depth.argmax()), depth.shape)
        token = json.loads(http(url + "/api/state"))["token"]
        http(url + "/api/place", {"obj_id": 1, "image_id": 0, "u": float(col), "v": float(row)}, token)
        deadline = time.monotonic() + 180
        while True:
            state = json.loads(http(url + "/api/state"))
            if state["instances"][0]["T_wm"] is not None and not state["job"]["running"]:
                break
            assert time.monotonic() < deadline, state["job"]
            time.sleep(0.3)
    finally:
        proc.send_signal(signal.SIGINT)
        _, stderr = proc.communicate(timeout=60)
    return LabelRun(address, page, state, proc.returncode, stderr)


# ----------------------------------------------------------------------------------------------
# What each example must have done
# ----------------------------------------------------------------------------------------------

def truth_and(scene_gt: Path) -> tuple[np.ndarray, np.ndarray]:
    """The example's true world-from-model pose and the one of ``scene_gt`` (first image's entry)."""
    scene = autoalign.read_scene(EXAMPLE / "scene")
    return (autoalign.read_init_pose(EXAMPLE / "scene" / "scene_gt.json", scene),
            autoalign.read_init_pose(scene_gt, scene))


def assert_close(T: np.ndarray, T_true: np.ndarray, mm: float = 0.5, deg: float = 0.5) -> None:
    """``T`` within ``mm`` (at the mug's centre) and ``deg`` of ``T_true``."""
    from autoalign.geometry.se3 import rotation_angle_deg

    c = autoalign.load_mesh(EXAMPLE / "model.ply").centre
    err_mm = float(np.linalg.norm(T[:3, :3] @ c + T[:3, 3] - T_true[:3, :3] @ c - T_true[:3, 3]))
    err_deg = rotation_angle_deg(T[:3, :3], T_true[:3, :3])
    assert err_mm < mm and err_deg < deg, (err_mm, err_deg)


def check_refine(root: Path, stdout: str) -> None:
    out = root / "out" / "example"
    T_true, T = truth_and(out / "scene_gt.json")
    assert_close(T, T_true)
    record = json.loads((out / "refine.json").read_text())
    assert record["verdict"] == "ok" and record["min_iou_after"] > 0.99
    assert cv2.imread(str(out / "overlay.png")).shape[2] == 3
    assert "wrote scene_gt.json, refine.json, overlay.png to out/example" in stdout
    # the fit as printed stays as good or gets better (the photos joined masks that fit), and the verdict is said
    before, after = map(float, re.search(r"IoU over 24 views: mean ([0-9.]+) -> ([0-9.]+)", stdout).groups())
    assert after >= before, stdout
    assert "\nverdict: ok\n" in stdout, stdout


def check_click(root: Path, stdout: str) -> None:
    """Seeded by one click in image 0, the mug is found as from no seed."""
    out = root / "out" / "example_click"
    T_true, T = truth_and(out / "scene_gt.json")
    assert_close(T, T_true)
    record = json.loads((out / "refine.json").read_text())
    assert record["verdict"] == "ok" and record["seed"]["kind"] == "click"
    assert record["seed"]["click"] == {"image_id": 0, "u": 320.0, "v": 240.0}
    assert "wrote scene_gt.json, refine.json, overlay.png to out/example_click" in stdout


def check_models(root: Path, stdout: str) -> None:
    """Every instance of the scene (the mug) refined from the coarse poses and judged ``ok``."""
    out = root / "out" / "example_models"
    T_true, T = truth_and(out / "scene_gt.json")
    assert_close(T, T_true)
    (rec,) = json.loads((out / "refine.json").read_text())["instances"]
    assert rec["obj_id"] == 1 and rec["verdict"] == "ok", rec["verdict"]
    assert cv2.imread(str(out / "overlay.png")) is not None
    assert "obj   1 (instance 0): ok" in stdout


def check_batch(root: Path, stdout: str) -> None:
    """The listed scene refined into ``OUT/scene`` with its own ``--init``, and recorded as done."""
    out = root / "out" / "example_batch"
    (rec,) = [json.loads(line) for line in (out / "batch.jsonl").read_text().splitlines()]
    assert rec["status"] == 0 and rec["out"] == "out/example_batch/scene"
    assert not (out / "errors.jsonl").is_file() or not (out / "errors.jsonl").read_text().strip()
    T_true, T = truth_and(out / "scene" / "scene_gt.json")
    assert_close(T, T_true)
    assert "1 scene(s) refined, 0 already done, 0 failed" in stdout


def check_recon(root: Path, stdout: str) -> None:
    """Every frame of the rendered capture registered, metric from depth, the trajectory drawn."""
    out = root / "out" / "capture_scene"
    record = json.loads((out / "recon.json").read_text())
    assert record["frames"] == record["registered"] == 30 and record["metric"] and record["units"] == "mm"
    assert record["scale_spread"] < 0.02
    assert len(json.loads((out / "scene_camera.json").read_text())) == 30
    assert cv2.imread(str(out / "trajectory.png")) is not None and (out / "cloud.ply").stat().st_size > 0
    assert "30 of 30 frames registered" in stdout


def check_check(root: Path, stdout: str) -> None:
    """The refined labels fit the example's photos: enough SIFT matches, sub-pixel distances."""
    report = json.loads((root / "out" / "example_check" / "check.json").read_text())
    (inst,) = report["instances"]
    assert report["image_ids"] == [0, 8, 15, 23] and inst["median_iou"] > 0.99
    assert not inst["too_few_matches"] and inst["n_matches"] >= 30 and inst["mean_px"] < 1.5, inst
    assert inst["edge_px"] < 1.2, inst
    assert cv2.imread(str(root / "out" / "example_check" / "check.png")) is not None
    assert "feature distance px" in stdout


def check_against(root: Path, stdout: str) -> None:
    """Our labels against the example's true poses: paired over the 8 views, no clear difference."""
    out = root / "out" / "example_compare"
    (cmp,) = json.loads((out / "check.json").read_text())["against"]["comparison"]
    assert cmp["views"] == 8 and cmp["verdict"] == "no clear difference", cmp
    assert abs(cmp["gain_px"]) < 0.1 and cmp["gain_ci95"][0] <= 0 <= cmp["gain_ci95"][1], cmp
    assert cv2.imread(str(out / "compare.png")) is not None
    assert "no clear difference" in stdout


def check_split_half(root: Path, stdout: str) -> None:
    """Our labels' two halves (12 views each) reach one solution, well under a millimetre apart."""
    block = json.loads((root / "out" / "example_split" / "check.json").read_text())["split_half"]
    assert block["halves"] == {"a": list(range(0, 24, 2)), "b": list(range(1, 24, 2))}
    (inst,) = block["instances"]
    assert inst["same_basin"] and inst["a"]["views"] == inst["b"]["views"] == 12, inst
    assert inst["translation_mm"] < 0.5 and inst["rotation_deg"] < 0.5 and len(inst["z"]) == 6, inst
    assert "same solution" in stdout and "sigma A" in stdout


def check_export(root: Path, stdout: str) -> None:
    """A BOP scene of the 24 labelled images whose visible masks are the example's own."""
    out = root / "out" / "example_bop"
    gt = json.loads((out / "scene_gt.json").read_text())
    assert sorted(map(int, gt)) == list(range(24)) and all(len(v) == 1 for v in gt.values())
    coco = json.loads((out / "scene_gt_coco.json").read_text())
    assert len(coco["images"]) == len(coco["annotations"]) == 24
    assert len(list((out / "rgb").glob("*.jpg"))) == 24
    for im in (0, 12):
        name = f"{im:06d}_000000.png"
        a = cv2.imread(str(out / "mask_visib" / name), cv2.IMREAD_GRAYSCALE) > 0
        b = cv2.imread(str(EXAMPLE / "scene" / "mask_visib" / name), cv2.IMREAD_GRAYSCALE) > 0
        assert (a & b).sum() / (a | b).sum() > 0.98


def check_label(root: Path, run: LabelRun) -> None:
    """The page was served, one click placed the mug where it is (verdict ok), Ctrl-C stopped the
    server with the usual one line, and the session was saved in ``--out``."""
    assert "out/example_label/session.json" in run.address and "<html" in run.page.lower()
    inst = run.state["instances"][0]
    assert inst["obj_id"] == 1 and inst["verdict"] == "ok" and inst["source"] == "click"
    T_true, _ = truth_and(EXAMPLE / "scene" / "scene_gt.json")
    assert_close(np.array(inst["T_wm"]), T_true)
    assert run.returncode == 130 and run.stderr.strip().splitlines()[-1] == "autoalign: interrupted", run.stderr
    session = json.loads((root / "out" / "example_label" / "session.json").read_text())
    assert session["instances"][0]["T_wm"] == inst["T_wm"]


def check_simulate(root: Path, stdout: str) -> None:
    """Four trials of autoalign, reported; results.md names the search these trials ran with."""
    out = root / "out" / "simulate"
    records = [json.loads(line) for line in (out / "trials.jsonl").read_text().splitlines()]
    assert len(records) == 4 and {r["method"] for r in records} == {"autoalign"}
    assert sum(r["success_cols"] for r in records) >= 3 and all(r["views"] == 8 for r in records)
    md = (out / "results.md").read_text()
    assert "| autoalign | 4 |" in md
    assert "hypotheses (best 16 climbed on hard IoU)" in md and "n_starts was" not in md
    assert len((out / "trials.csv").read_text().splitlines()) == 5
    assert (out / "plots" / "success_vs_initial_error.png").stat().st_size > 1000
    assert "4 trials run, 0 already done, 0 failed" in stdout


def check_python_api(root: Path, scope: dict[str, Any]) -> None:
    T_true, _ = truth_and(EXAMPLE / "scene" / "scene_gt.json")
    assert_close(scope["result"].T_wm, T_true)
    assert scope["result"].iou_after.min() > 0.99 and not scope["result"].ambiguous


def check_several_objects(root: Path, scope: dict[str, Any]) -> None:
    (r,) = scope["refined"].results
    assert r.instance.obj_id == 1 and r.verdict.status == "ok"
    T_true, _ = truth_and(EXAMPLE / "scene" / "scene_gt.json")
    assert_close(r.result.T_wm, T_true)
    assert np.all(r.result.uncertainty.sigma_mm < 0.1)


CHECKS: list[tuple[str, Callable[[Path, Any], None]]] = [
    ("autoalign refine autoalign/data/example/scene --model autoalign/data/example/model.ply --out out/example\n",
     check_refine),
    ("--click 0:320,240 --out out/example_click", check_click),
    ("--out out/example_models", check_models),
    ("autoalign refine --batch out/scenes.txt", check_batch),
    ("autoalign recon out/capture", check_recon),
    ("--images 4 --out out/example_check", check_check),
    ("--against autoalign/data/example/scene/scene_gt.json", check_against),
    ("--split-half --out out/example_split", check_split_half),
    ("autoalign export autoalign/data/example/scene", check_export),
    ("autoalign label autoalign/data/example/scene", check_label),
    ("autoalign simulate --max-models", check_simulate),
    ("result = autoalign.refine(scene, mesh, seed=seed)", check_python_api),
    ("refined = refine_scene(", check_several_objects),
]
"""A marker of each runnable example and the check of what it did."""

OWN_TESTS = {"from autoalign.torch import": "test_pytorch_loop_reaches_1mm_1deg",
             "import autoalign.jax as aj": "test_jax_solve_reaches_1mm_1deg"}
"""Examples run by a test of their own (below), by a marker of each."""


def check_of(block: Block) -> Callable[[Path, Any], None] | None:
    (fn,) = [fn for marker, fn in CHECKS if marker in block.code] or [None]
    return fn


def example_blocks() -> list[Block]:
    """The runnable blocks :func:`test_readme_example` runs (all but the PyTorch and JAX ones, and the
    test command, which :func:`test_the_test_command_is_what_ci_runs` takes)."""
    return [b for b in readme_blocks() if b.lang in RUNNABLE and not any(m in b.code for m in OWN_TESTS)
            and b.code.strip() != INSTALL + "pytest"]


# ----------------------------------------------------------------------------------------------
# The tests
# ----------------------------------------------------------------------------------------------

def test_every_block_is_marked_and_every_example_is_checked() -> None:
    """Every fence names its language; ```text blocks are synopses (with placeholders such as
    SCENE_DIR) or the commands that made the stored simulation results; every ```bash / ```python
    block is an example with exactly one check here, or has its own test."""
    blocks = readme_blocks()
    assert len(blocks) >= 15
    for b in blocks:
        assert b.lang in (*RUNNABLE, "text", "json"), f"README line {b.line}: fence without a language ({b.lang!r})"
        if b.lang == "text":
            assert re.search(r"\b[A-Z][A-Z_]{2,}\b", b.code) or "experiments/results/" in b.code, b.id
    runnable = [b for b in blocks if b.lang in RUNNABLE]
    assert len(runnable) == len(example_blocks()) + len(OWN_TESTS) + 1
    for b in runnable:
        covered = [m for m in OWN_TESTS if m in b.code] + [m for m, _ in CHECKS if m in b.code]
        assert len(covered) + (b.code.strip() == INSTALL + "pytest") == 1, f"{b.id}: no check, or several"


def test_the_instances_file_shown_is_one_refine_takes(tmp_path: Path) -> None:
    from autoalign.io.instances import Instance, read_instances

    (block,) = [b for b in readme_blocks() if b.lang == "json"]
    (tmp_path / "instances.json").write_text(block.code)
    assert read_instances(tmp_path, tmp_path / "instances.json") == [Instance(0, 5), Instance(3, 8)]


def test_the_test_command_is_what_ci_runs() -> None:
    """``bash .ci/install && pytest`` is not run from within the suite it starts (it would recurse);
    CI runs it: ``.ci/run`` ends with this very line."""
    (block,) = [b for b in readme_blocks() if b.code.strip() == INSTALL + "pytest"]
    run = (REPO / ".ci" / "run").read_text().strip().splitlines()
    assert run[-1] == block.code.strip()


@pytest.mark.slow
@pytest.mark.parametrize("block", example_blocks(), ids=lambda b: b.id)
def test_readme_example(block: Block, workdir: Path, capsys: pytest.CaptureFixture[str],
                        monkeypatch: pytest.MonkeyPatch) -> None:
    """Run the block as written (see the module doc for the two that cannot be), check its outputs,
    and check that it changed nothing but ``out/`` and nothing of the repository."""
    check = check_of(block)
    assert check is not None, f"{block.id}: add a check of this example to CHECKS"
    if "out/example/" in block.code and block.line != setup_block().line:
        ensure_refined(workdir)  # the examples that take the Set up example's labels
    before, status = files_outside_out(workdir), repo_status()
    if block.lang == "python":
        monkeypatch.chdir(workdir)
        scope: dict[str, Any] = {}
        exec(compile(block.code, f"{README}:{block.line}", "exec"), scope)  # noqa: S102 - the README's example
        check(workdir, scope)
    elif block.code.startswith("autoalign label "):
        check(workdir, run_label(block.code, workdir))
    else:
        check(workdir, shell(block.code.removeprefix(INSTALL), workdir))
    assert files_outside_out(workdir) == before, "the example wrote outside out/"
    assert repo_status() == status, "the example changed files of the repository"


SKIP_MARKS_PLUGIN = '''
from _pytest.skipping import evaluate_skip_marks


def pytest_collection_modifyitems(session, config, items):
    for item in items:
        if evaluate_skip_marks(item) is not None:
            print("SKIPPED", item.nodeid.split("::")[0])
'''
"""A pytest plugin printing each collected test that a skip mark skips in this environment."""


@pytest.mark.slow
def test_the_readme_counts_the_tests_that_need_the_shared_folder(tmp_path: Path) -> None:
    """The Tests section's count of the tests skipped without ``shared/real`` is right: the test
    files that use the shared folder are collected with it absent, and their skip marks evaluated."""
    files = sorted(p for p in (REPO / "tests").glob("test_*.py") if "shared_data" in p.read_text())
    (tmp_path / "skip_marks.py").write_text(SKIP_MARKS_PLUGIN)
    env = {**environment(), "AUTOALIGN_SHARED": str(tmp_path / "absent"),
           "PYTHONPATH": os.pathsep.join([str(tmp_path), *filter(None, [os.environ.get("PYTHONPATH")])])}
    run = subprocess.run([sys.executable, "-m", "pytest", "--collect-only", "-q", "-n", "0", "-p", "skip_marks",
                          *map(str, files)],
                         cwd=REPO, env=env, capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stdout[-2000:] + run.stderr[-2000:]
    counted: dict[str, int] = {}
    for line in run.stdout.splitlines():
        if line.startswith("SKIPPED "):
            name = Path(line.split()[1]).name
            counted[name] = counted.get(name, 0) + 1
    text = " ".join(README.read_text().split())
    m = re.search(r"(\d+) tests are skipped: (.*?) \(pytest's summary", text)
    assert m, "the Tests section no longer says how many tests need shared/real"
    said = {name: int(n) for n, name in re.findall(r"(\d+) in `tests/([\w.]+)`", m.group(2))}
    assert said == counted and int(m.group(1)) == sum(counted.values()), (m.group(0), counted)


def test_stored_simulation_report_says_which_search_its_trials_ran() -> None:
    """The stored results.md is what the report makes of the stored trials, and says that their
    search started from the best 8 orientations (the engine keeps 16 now, as the README says)."""
    from autoalign.batch import read_records
    from autoalign.engine.refine import RefineOptions
    from autoalign.experiments.studies.report import markdown

    folder = REPO / "experiments" / "results" / "simulate"
    if not (folder / "trials.jsonl").is_file():
        pytest.skip("no stored simulation results (an installed package without the repository)")
    md = markdown(read_records(folder / "trials.jsonl"), json.loads((folder / "config.json").read_text()))
    assert md == (folder / "results.md").read_text()
    assert RefineOptions().search.n_starts == 16
    assert ("hypotheses (best 8 climbed on hard IoU; RefineOptions.search.n_starts was 8 in these "
            "trials and is 16 now)") in md


@pytest.mark.slow
def test_pytorch_loop_reaches_1mm_1deg():
    scope = run_block("from autoalign.torch import")
    assert scope["err_mm"] < 1.0 and scope["err_deg"] < 1.0, (scope["err_mm"], scope["err_deg"])


@pytest.mark.slow
def test_jax_solve_reaches_1mm_1deg():
    scope = run_block("import autoalign.jax as aj")
    assert scope["grad"].shape == (4, 4) and float(abs(scope["grad"]).sum()) > 0
    assert scope["err_mm"] < 1.0 and scope["err_deg"] < 1.0, (scope["err_mm"], scope["err_deg"])


def test_the_readme_stays_short() -> None:
    """The README is the tour, not the reference (issue 44): at most 450 lines; the detail lives in
    docs/commands.md, docs/how-it-works.md and docs/results.md."""
    assert len(README.read_text().splitlines()) <= 450
