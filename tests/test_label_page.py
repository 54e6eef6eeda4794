"""``autoalign label``: the page driven in a real headless Chromium (Debian's ``chromium`` through
Playwright), the server in a child process, on a synthetic scene whose masks open3d ray-cast.

Screenshots of each step go to ``$AUTOALIGN_LABEL_SCREENSHOTS`` if set (the README's come from
``AUTOALIGN_LABEL_SCREENSHOTS=experiments/results/label_page pytest tests/test_label_page.py``),
else to the test's temporary folder.
"""

from __future__ import annotations

import http.client
import json
import os
import signal
import socket
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import pytest
from playwright.sync_api import sync_playwright

from autoalign.experiments.benchmarks.bench_scene import make_bench_scene
from autoalign.experiments.pages.label_page_driver import (
    LabelServerProcess,
    click_view,
    launch_browser,
    mask_pixel,
    open_page,
    wait_drawn,
    wait_job_done,
    wait_state,
)
from autoalign.experiments.scenes.synthetic import shaded_photos
from autoalign.geometry.se3 import rotation_angle_deg
from autoalign.io.instances import Instance, read_instance_scenes
from autoalign.io.models import ModelSet

N_VIEWS = 12
W, H = 640, 480


@dataclass
class LabelScene:
    root: Path
    scene: Path
    models: Path
    truth: list[np.ndarray]


@pytest.fixture(scope="module")
def labelled(tmp_path_factory) -> LabelScene:
    """Two objects that hide each other in 12 views, with shaded stand-in photos in rgb/."""
    root = tmp_path_factory.mktemp("label")
    truth = make_bench_scene(root, 2, views=N_VIEWS)
    (root / "scene" / "scene_gt.json").unlink()  # a fresh capture: the page is told nothing of the objects
    models = ModelSet.read(root / "models")
    found = read_instance_scenes(root / "scene", [Instance(0, 1)])
    (root / "scene" / "rgb").mkdir()
    for im, img in zip(found.image_ids, shaded_photos([models.mesh(1), models.mesh(2)], truth, found.cameras,
                                           [(150, 165, 180), (110, 150, 120)])):
        cv2.imwrite(str(root / "scene" / "rgb" / f"{im:06d}.png"), img)
    return LabelScene(root, root / "scene", root / "models", truth)


def shots_dir(tmp_path: Path) -> Path:
    d = Path(os.environ.get("AUTOALIGN_LABEL_SCREENSHOTS") or tmp_path / "shots")
    d.mkdir(parents=True, exist_ok=True)
    return d


def session_instance(out: Path, index: int) -> dict:
    data = json.loads((out / "session.json").read_text())
    return next(i for i in data["instances"] if i["index"] == index)


def pose_error(T: np.ndarray, T_true: np.ndarray, centre_m: np.ndarray) -> tuple[float, float]:
    """(mm between the model centres, degrees between the orientations)."""
    c = T[:3, :3] @ centre_m + T[:3, 3]
    c_true = T_true[:3, :3] @ centre_m + T_true[:3, 3]
    return float(np.linalg.norm(c - c_true)), rotation_angle_deg(T[:3, :3], T_true[:3, :3])


def mask_of(scene: Path, im: int, k: int) -> np.ndarray:
    return cv2.imread(str(scene / "mask_visib" / f"{im:06d}_{k:06d}.png"), cv2.IMREAD_GRAYSCALE) > 0


@pytest.mark.slow
def test_click_nudge_refine_accept_export_in_a_real_browser(labelled, tmp_path):
    shots = shots_dir(tmp_path)
    out = tmp_path / "session"
    models = ModelSet.read(labelled.models)
    centre = models.mesh(1).centre
    with LabelServerProcess(labelled.scene, labelled.models, out) as server, sync_playwright() as pw:
        browser = launch_browser(pw)
        page = open_page(browser, server.url, N_VIEWS)
        page.wait_for_function("[...document.querySelectorAll('.view img.photo')].every(i => i.complete)")
        page.screenshot(path=str(shots / "1-opened.png"))

        # a click on the background: a one-line message on the page, nothing placed
        click_view(page, 0, 5, 5, W, H)
        page.wait_for_function("document.querySelector('#status').classList.contains('error')")
        assert "no instance mask under pixel 5,5 of image 0" in page.inner_text("#status")
        assert not (out / "session.json").exists()

        # choose object 1 and click instance 0 in view 0: placed, refined, outlined in every view; the
        # orientation search's pose is outlined first, dashed, then the refined one
        page.evaluate("window.searchedOutlines = 0; new MutationObserver((changes) => { for (const c of changes) "
                      "for (const n of c.addedNodes) if (n.classList && n.classList.contains('searched')) "
                      "window.searchedOutlines++; }).observe(document.querySelector('#views'), "
                      "{childList: true, subtree: true})")
        page.select_option("#object", "1")
        col, row = mask_pixel(mask_of(labelled.scene, 0, 0))
        click_view(page, 0, col, row, W, H)
        wait_drawn(page, 0)  # the searched pose's outlines, or already the refined pose's
        state = wait_job_done(page)
        assert state["job"]["error"] is None
        # the revision of the refined pose (the searched one before it had its own): counted from here
        rev = next(i for i in state["instances"] if i["index"] == 0)["pose_revision"]
        wait_drawn(page, 0, rev - 1)
        n_outlined = page.evaluate("document.querySelectorAll('.view polyline[data-instance=\"0\"]').length")
        assert n_outlined >= N_VIEWS  # at least one outline per view (the object is in all of them)
        page.wait_for_function("document.body.dataset.clickToContoursMs !== undefined && "
                               "document.body.dataset.clickToFirstOutlinesMs !== undefined")
        assert page.evaluate("window.searchedOutlines") >= N_VIEWS
        assert page.evaluate("document.querySelectorAll('.view polyline.searched').length") == 0
        # the refined pose is outlined before its uncertainty and verdict, solid, and the judged one last
        first, refined, judged = (float(page.evaluate(f"document.body.dataset.{k}")) for k in
                                  ("clickToFirstOutlinesMs", "clickToRefinedPoseMs", "clickToContoursMs"))
        assert first <= refined <= judged and first < judged, (first, refined, judged)
        page.screenshot(path=str(shots / "2-placed.png"))
        placed = session_instance(out, 0)
        assert placed["obj_id"] == 1 and placed["source"] == "click" and placed["verdict"] == "ok"
        mm, deg = pose_error(np.array(placed["T_wm"]), labelled.truth[0], centre)
        assert mm < 1.0 and deg < 1.0, (mm, deg)
        assert page.locator('.instance[data-index="0"] .verdict').inner_text() == "ok"
        assert "σ not shown" not in page.locator('.instance[data-index="0"]').inner_text()  # trusted: its sigma

        # nudge: three times right in view 0's axes (the keys act on the view under the mouse)
        page.hover('.view[data-image-id="0"] img.tint')
        for _ in range(3):
            page.keyboard.press("ArrowRight")
        wait_state(page, f"s.instances.find(i => i.index === 0).pose_revision >= {rev + 3}")
        rev = wait_drawn(page, 0, rev + 2)
        assert rev == next(i for i in wait_state(page, "true")["instances"] if i["index"] == 0)["pose_revision"]
        nudged = session_instance(out, 0)
        T0, T1 = np.array(placed["T_wm"]), np.array(nudged["T_wm"])
        from autoalign.io.bop import read_cameras

        _, R_w2c, _ = read_cameras(labelled.scene)[0]
        np.testing.assert_allclose(T1[:3, 3] - T0[:3, 3], R_w2c.T @ [3.0, 0.0, 0.0], atol=1e-6)
        np.testing.assert_allclose(T1[:3, :3], T0[:3, :3], atol=1e-9)
        assert nudged["verdict"] is None and nudged["source"] == "nudge"
        # a pose not judged (or not ok) shows no sigma: it would not be its precision
        page.wait_for_function("document.querySelector('.instance[data-index=\"0\"]').innerText.includes('σ not shown')")
        page.screenshot(path=str(shots / "3-nudged.png"))

        # Ctrl+Z undoes the last nudge
        page.keyboard.press("Control+z")
        wait_state(page, f"s.instances.find(i => i.index === 0).pose_revision >= {rev + 1}")
        rev = wait_drawn(page, 0, rev)
        undone = session_instance(out, 0)
        np.testing.assert_allclose(np.array(undone["T_wm"])[:3, 3] - T0[:3, 3], R_w2c.T @ [2.0, 0.0, 0.0], atol=1e-6)

        # refine from here (key r): back on the object
        page.keyboard.press("r")
        wait_drawn(page, 0, rev)
        state = wait_job_done(page)
        assert state["job"]["kind"] == "refine" and state["job"]["error"] is None
        refined = session_instance(out, 0)
        mm, deg = pose_error(np.array(refined["T_wm"]), labelled.truth[0], centre)
        assert mm < 1.0 and deg < 1.0 and refined["verdict"] == "ok", (mm, deg)
        page.screenshot(path=str(shots / "4-refined.png"))

        # accept it; place instance 1 and reject it: only instance 0 is exported
        page.click('.instance[data-index="0"] button[data-act="accept"]')
        page.wait_for_selector('.instance[data-index="0"][data-decision="accepted"]')
        page.select_option("#object", "2")
        col, row = mask_pixel(mask_of(labelled.scene, 3, 1))
        click_view(page, 3, col, row, W, H)
        wait_drawn(page, 1)
        wait_job_done(page)
        page.click('.instance[data-index="1"] button[data-act="reject"]')
        page.wait_for_selector('.instance[data-index="1"][data-decision="rejected"]')
        assert session_instance(out, 0)["decision"] == "accepted"
        page.screenshot(path=str(shots / "5-accepted.png"))

        # refining together needs two instances that are not rejected: said on the page
        page.click("#refine-all")
        page.wait_for_function("document.querySelector('#status').textContent.includes('needs two or more')")

        page.click("#export")
        state = wait_job_done(page)
        assert state["job"]["kind"] == "export" and state["job"]["error"] is None, state["job"]
        page.wait_for_function("document.querySelector('#status').textContent.startsWith('exported')")
        page.screenshot(path=str(shots / "6-exported.png"))

        # the 3D view (viser, in the page): it connects and draws
        page.click("#viewer-box summary")
        viewer = page.frame_locator("#viewer")
        viewer.locator("canvas").first.wait_for(timeout=60_000)
        viewer.get_by_text("Connected").first.wait_for(timeout=60_000)
        page.locator("#viewer").scroll_into_view_if_needed()
        page.screenshot(path=str(shots / "7-3d-view.png"))
        browser.close()
        assert server.stop() == 130  # Ctrl-C stops it

    # the page's export is 'autoalign export' of the labels it wrote
    labels = json.loads((out / "scene_gt.json").read_text())
    assert all([e["obj_id"] for e in entries] == [1] for entries in labels.values())
    ref = tmp_path / "reference"
    subprocess.run([sys.executable, "-m", "autoalign.cli.main", "export", str(labelled.scene), "--labels",
                    str(out / "scene_gt.json"), "--models", str(labelled.models), "--out", str(ref), "--quiet"],
                   check=True)
    ours = {p.relative_to(out / "bop") for p in (out / "bop").rglob("*") if p.is_file()}
    theirs = {p.relative_to(ref) for p in ref.rglob("*") if p.is_file()}
    assert ours == theirs and len(ours) > 3 * N_VIEWS
    for rel in sorted(ours - {Path("export.json")}):
        assert (out / "bop" / rel).read_bytes() == (ref / rel).read_bytes(), rel
    a, b = json.loads((out / "bop/export.json").read_text()), json.loads((ref / "export.json").read_text())
    assert {k: a[k] for k in ("images", "entries")} == {k: b[k] for k in ("images", "entries")} == \
        {"images": N_VIEWS, "entries": N_VIEWS}


@pytest.mark.slow
def test_a_click_shows_the_searched_pose_first_and_keeps_only_the_refined_one(labelled, tmp_path):
    """While a click is refined, the orientation search's pose is the instance's (so the page outlines
    it at once), marked as being refined, then the refined pose before its uncertainty and verdict,
    marked as being judged; neither is saved to session.json (not even by another change saved
    meanwhile) nor kept for undo; the judged pose replaces them. A click that fails after a pose was
    shown leaves the instance as it was."""
    from autoalign.errors import AutoalignError
    from autoalign.label.records import BEING_JUDGED, BEING_REFINED
    from autoalign.label.session import LabelSession

    models = ModelSet.read(labelled.models)
    session = LabelSession(labelled.scene, models, tmp_path / "out")
    col, row = mask_pixel(mask_of(labelled.scene, 0, 0))
    seen, shown = [], []
    put = session.state.put

    def watch(stage: str, done: int, total: int) -> None:  # on the refining thread, mid-refinement
        inst = session.instances[0]
        if inst.placed:
            session.mark_symmetric(1, False)  # a change of another instance, saved (as from another tab)
            saved = json.loads(session.session_path.read_text())["instances"]
            seen.append((inst.source, inst.reasons, inst.verdict, [i["obj_id"] for i in saved]))

    def put_watched(inst, shown_only: bool = False) -> None:
        if inst.index == 0:
            shown.append((inst.source, inst.reasons[:1] if inst.verdict is None else inst.verdict, shown_only,
                          inst.T_wm.copy()))
        put(inst, shown_only)

    session.state.put = put_watched
    assert session.place(1, 0, float(col), float(row), watch) == 0
    # mid-refinement: the search's pose, then the refined one, never judged
    marked = [(source, tuple(reasons), verdict) for source, reasons, verdict, _ in seen]
    assert marked[0] == ("search", (BEING_REFINED,), None), marked[:3]
    assert set(marked) <= {("search", (BEING_REFINED,), None), ("refining", (BEING_JUDGED,), None)}, set(marked)
    assert marked == sorted(marked, key=lambda m: m[0] == "refining"), marked
    assert {tuple(objs) for *_, objs in seen} == {(None, None)}  # saved meanwhile: instance 0 as it was
    # the search's pose, the refined ones before their uncertainty (the masks' pose, then the photos'),
    # then the judged one, saved
    refining = ("refining", [BEING_JUDGED], True)
    assert [s[:3] for s in shown] == [("search", [BEING_REFINED], True), refining, refining, ("click", "ok", False)], \
        [s[:3] for s in shown]
    assert np.array_equal(shown[2][3], shown[3][3])  # nothing moves the photos' pose after its preview
    shown_click = shown[3][3]
    placed = session_instance(tmp_path / "out", 0)
    assert placed["source"] == "click" and placed["verdict"] == "ok"
    mm, deg = pose_error(np.array(placed["T_wm"]), labelled.truth[0], models.mesh(1).centre)
    assert mm < 1.0 and deg < 1.0
    with pytest.raises(AutoalignError, match="nothing to undo"):  # the shown poses are no step back
        session.undo(0)
    # refined from where it is: the refined pose shown before its verdict, the person's decision kept
    session.decide(0, "accepted")
    shown.clear()
    session.refine_from_here(0)
    assert [s[:3] for s in shown] == [refining, ("refine", "ok", False)], [s[:3] for s in shown]
    assert session_instance(tmp_path / "out", 0)["decision"] == "accepted"
    session.undo(0)  # one step back: the click's pose, not the one shown meanwhile
    assert np.array_equal(session.instances[0].T_wm, shown_click) and session.instances[0].source == "click"

    class Stop(Exception):
        pass

    def fail_once_shown(stage: str, done: int, total: int) -> None:
        if session.instances[1].placed:
            raise Stop
    col, row = mask_pixel(mask_of(labelled.scene, 3, 1))
    with pytest.raises(Stop):
        session.place(2, 3, float(col), float(row), fail_once_shown)
    assert not session.instances[1].placed and session.contours(1)[1] == {}
    assert [i["index"] for i in json.loads(session.session_path.read_text())["instances"] if i["obj_id"]] == [0]


def _listening_address(port: int) -> str:
    """The local address a TCP socket listens on at ``port``, from /proc/net/tcp (the kernel's own view)."""
    for line in Path("/proc/net/tcp").read_text().splitlines()[1:]:
        local, state = line.split()[1], line.split()[3]
        addr, p = local.split(":")
        if int(p, 16) == port and state == "0A":  # LISTEN
            return socket.inet_ntoa(bytes.fromhex(addr)[::-1])
    raise AssertionError(f"nothing listens on port {port}")


def _get(port: int, path: str, host: str = "127.0.0.1") -> tuple[int, bytes]:
    conn = http.client.HTTPConnection("127.0.0.1", port, timeout=10)
    conn.putrequest("GET", path, skip_host=True)  # the path exactly as given: no client-side normalising
    conn.putheader("Host", f"{host}:{port}")
    conn.endheaders()
    r = conn.getresponse()
    return r.status, r.read()


@pytest.mark.slow
def test_restart_two_tabs_binding_and_paths(labelled, tmp_path):
    out = tmp_path / "session"
    (labelled.scene / "escape").symlink_to("/etc/hostname")
    with socket.socket() as probe:  # a free port, so that the restarted server is where the open tab looks
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    try:
        with LabelServerProcess(labelled.scene, labelled.models, out, ("--port", str(port))) as server, \
                sync_playwright() as pw:
            # listens on 127.0.0.1 only, the page and the 3D view alike
            assert _listening_address(server.port) == "127.0.0.1"
            state = json.loads(_get(server.port, "/api/state")[1])
            viewer_url, token = state["viewer_url"], {"X-Autoalign-Token": state["token"]}
            assert viewer_url.startswith("http://127.0.0.1:")
            assert _listening_address(int(viewer_url.rstrip("/").rsplit(":", 1)[1])) == "127.0.0.1"
            # files: the scene's and the models' yes, anything else no (dot-dot, encoded, a link out)
            assert _get(server.port, "/files/scene/scene_camera.json")[0] == 200
            assert _get(server.port, "/files/models/obj_000001.ply")[0] == 200
            for path in ("/files/scene/../../../../etc/passwd", "/files/scene/%2e%2e/%2e%2e/etc/passwd",
                         "/files/models/..%2f..%2fscene/scene_camera.json", "/files/scene/escape",
                         "/files/scene//etc/passwd", "/static/../../../etc/passwd"):
                status, body = _get(server.port, path)
                assert status in (403, 404) and b"root:" not in body and b"cam_K" not in body, path
            assert _get(server.port, "/api/state", host="attacker.example")[0] == 403
            conn = http.client.HTTPConnection("127.0.0.1", server.port, timeout=10)
            conn.request("POST", "/api/decide", body=b"{not json", headers={"Content-Type": "application/json", **token})
            r = conn.getresponse()
            assert r.status == 400 and "JSON object" in json.loads(r.read())["error"]
            conn.request("POST", "/api/decide", body=json.dumps({"instance": 0, "decision": "accepted"}), headers=token)
            r = conn.getresponse()  # nothing placed yet: refused, with the fix
            assert r.status == 400 and "click it in a view" in json.loads(r.read())["error"]

            # two tabs: each places one instance, then both nudge at once; no change is lost
            browser = launch_browser(pw)
            tab_a, tab_b = open_page(browser, server.url, N_VIEWS), open_page(browser, server.url, N_VIEWS)
            for tab, k, obj, im in ((tab_a, 0, "1", 0), (tab_b, 1, "2", 5)):
                tab.select_option("#object", obj)
                col, row = mask_pixel(mask_of(labelled.scene, im, k))
                click_view(tab, im, col, row, W, H)
                wait_drawn(tab, k)
                wait_job_done(tab)
            before = {k: np.array(session_instance(out, k)["T_wm"]) for k in (0, 1)}
            placed_rev = {k: session_instance(out, k)["pose_revision"] for k in (0, 1)}  # after 10 nudges: +10
            all_nudged = " && ".join(f"s.instances.find(i => i.index === {k}).pose_revision === {placed_rev[k] + 10}"
                                     for k in (0, 1))
            nudges = "Promise.all([...Array(10)].map(() => fetch('/api/nudge', {method: 'POST', " \
                     "headers: {'X-Autoalign-Token': token}, " \
                     "body: JSON.stringify({instance: %d, image_id: 0, move_mm: [0, 0, 1], turn_deg: [0, 0, 0]})})))"
            tab_a.evaluate(f"window.sent = {nudges % 0}")
            tab_b.evaluate(f"window.sent = {nudges % 1}")
            assert tab_a.evaluate("window.sent.then(rs => rs.every(r => r.ok))")  # the page's token: accepted
            assert tab_b.evaluate("window.sent.then(rs => rs.every(r => r.ok))")
            from autoalign.io.bop import read_cameras

            _, R_w2c, _ = read_cameras(labelled.scene)[0]
            for k in (0, 1):
                after = np.array(session_instance(out, k)["T_wm"])
                np.testing.assert_allclose(after[:3, 3] - before[k][:3, 3], R_w2c.T @ [0.0, 0.0, 10.0], atol=1e-6)
            for tab in (tab_a, tab_b):  # both tabs see the same state
                wait_state(tab, all_nudged)
                wait_drawn(tab, 0, placed_rev[0] + 9)
                wait_drawn(tab, 1, placed_rev[1] + 9)
            # a change to one instance leaves the other's row as it was: a click on a button that a
            # redraw replaced under it is lost (tab B's accept was, once, while tab A's arrived)
            tab_b.wait_for_function(all_nudged.replace("s.instances", "state.instances"), polling=200)  # the page's own
            tab_b.evaluate("window.kept = document.querySelector('.instance[data-index=\"1\"] button[data-act=\"accept\"]')")
            tab_a.click('.instance[data-index="0"] button[data-act="accept"]')
            tab_b.wait_for_selector('.instance[data-index="0"][data-decision="accepted"]')
            assert tab_b.evaluate("window.kept.isConnected")
            tab_b.click('.instance[data-index="1"] button[data-act="accept"]')
            tab_a.wait_for_selector('.instance[data-index="1"][data-decision="accepted"]')
            tab_a.check('.instance[data-index="1"] input[data-act="symmetric"]')  # the other tab follows
            tab_b.wait_for_function("document.querySelector('.instance[data-index=\"1\"] input[data-act=\"symmetric\"]')"
                                    ".checked", polling=200)
            saved = json.loads((out / "session.json").read_text())
            assert server.stop(signal.SIGKILL) == -signal.SIGKILL  # pulled the plug: no chance to save anything
            tab_a.wait_for_function("document.querySelector('#status').textContent.startsWith('lost the server')")

            # restart on the same session and port: the open tab finds it again, and a new one too;
            # everything accepted is there, at the same poses
            with LabelServerProcess(labelled.scene, labelled.models, out, ("--port", str(port), "--no-3d")):
                tab_a.wait_for_function("!document.querySelector('#status').textContent.startsWith('lost')")
                page = open_page(browser, f"http://127.0.0.1:{port}/", N_VIEWS)
                for tab in (tab_a, page):
                    tab.wait_for_selector('.instance[data-index="0"][data-decision="accepted"]')
                    tab.wait_for_selector('.instance[data-index="1"][data-decision="accepted"]')
                wait_drawn(page, 0, placed_rev[0] + 9)
                wait_drawn(page, 1, placed_rev[1] + 9)
                state = page.evaluate("fetch('/api/state').then(r => r.json())")
                for inst in saved["instances"]:
                    again = next(i for i in state["instances"] if i["index"] == inst["index"])
                    assert again["T_wm"] == inst["T_wm"] and again["decision"] == inst["decision"] == "accepted"
                # the tab opened before the restart still makes changes: it took the new server's token
                assert tab_a.evaluate("token") == state["token"] != token["X-Autoalign-Token"]
                assert tab_a.evaluate("post('/api/symmetric', {instance: 1, symmetric: false})") is not None
                assert session_instance(out, 1)["symmetric"] is False
            browser.close()
    finally:
        (labelled.scene / "escape").unlink()


@pytest.mark.slow
def test_label_input_errors_are_one_line(labelled, tmp_path):
    def run(*args):
        return subprocess.run([sys.executable, "-m", "autoalign.cli.main", "label", *map(str, args), "--no-browser"],
                              capture_output=True, text=True, timeout=120)

    r = run(labelled.scene, "--models", tmp_path / "nowhere")
    assert r.returncode == 2 and r.stderr.count("\n") == 1 and "models folder not found" in r.stderr
    r = run(labelled.scene, "--models", labelled.models, "--out", labelled.scene)
    assert r.returncode == 2 and "is the scene folder itself" in r.stderr
    bad = tmp_path / "bad"
    bad.mkdir()
    (bad / "session.json").write_text("{not json")
    r = run(labelled.scene, "--models", labelled.models, "--out", bad)
    assert r.returncode == 2 and r.stderr.count("\n") == 1 and "session.json" in r.stderr, r.stderr


def test_nudge_turns_about_the_object_centre_in_camera_axes():
    """nudged_pose against scipy: a turn of 3 degrees about the camera's y axis, and a move along its z."""
    from scipy.spatial.transform import Rotation

    from autoalign.geometry.camera import Camera
    from autoalign.geometry.se3 import make_pose
    from autoalign.label.page_geometry import nudged_pose

    rng = np.random.default_rng(4)
    R_w2c = Rotation.random(random_state=5).as_matrix()
    cam = Camera(np.array([[600.0, 0, 320], [0, 600.0, 240], [0, 0, 1]]), R_w2c, np.array([10.0, -20.0, 500.0]), W, H)
    T = make_pose(Rotation.random(random_state=6).as_matrix(), rng.normal(size=3) * 50)
    centre_m = np.array([5.0, -3.0, 12.0])
    T2 = nudged_pose(T, centre_m, cam, np.array([0.0, 0.0, 2.0]), np.array([0.0, 3.0, 0.0]))
    axis_w = R_w2c.T @ [0.0, 1.0, 0.0]
    R_expected = Rotation.from_rotvec(np.radians(3.0) * axis_w).as_matrix() @ T[:3, :3]
    np.testing.assert_allclose(T2[:3, :3], R_expected, atol=1e-12)
    c, c2 = T[:3, :3] @ centre_m + T[:3, 3], T2[:3, :3] @ centre_m + T2[:3, 3]
    np.testing.assert_allclose(c2 - c, R_w2c.T @ [0.0, 0.0, 2.0], atol=1e-9)  # the centre only moves by the move


@pytest.mark.slow
def test_3d_view_draws_the_session_and_its_gizmo_moves_the_object(labelled, tmp_path):
    """In-process: the viser scene follows the session, and a drag of the gizmo becomes the instance's pose."""
    import time

    import open3d as o3d
    from scipy.spatial.transform import Rotation

    from autoalign.cli.label_3d import SceneViewer
    from autoalign.label.session import LabelSession

    models = ModelSet.read(labelled.models)
    session = LabelSession(labelled.scene, models, tmp_path / "session")
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.random.default_rng(0).normal(size=(500, 3)) * 50))
    o3d.io.write_point_cloud(str(labelled.scene / "cloud.ply"), cloud)  # as 'autoalign recon' leaves it
    try:
        viewer = SceneViewer(session)
    finally:
        (labelled.scene / "cloud.ply").unlink()
    try:
        np.testing.assert_allclose(np.sort(viewer.cloud.points[:, 0]), np.sort(np.asarray(cloud.points)[:, 0]) / 1000,
                                   atol=1e-3)  # the cloud, in metres (stored as float16 by viser)
        cam = session.views[0]
        frustum = viewer.frustums[session.image_ids[0]]
        np.testing.assert_allclose(frustum.position, cam.centre / 1000.0, atol=1e-9)
        np.testing.assert_allclose(Rotation.from_quat(np.roll(frustum.wxyz, -1)).as_matrix(), cam.R_w2c.T, atol=1e-9)
        col, row = mask_pixel(mask_of(labelled.scene, 0, 0))
        session.place(1, 0, col, row)
        T, refined = session.instances[0].T_wm, (1, session.instances[0].pose_revision)
        t0 = time.monotonic()
        while viewer._shown.get(0) != refined and time.monotonic() - t0 < 10:  # the searched pose came first
            time.sleep(0.05)
        mesh = viewer._handles[0]
        np.testing.assert_allclose(mesh.position, T[:3, 3] / 1000.0, atol=1e-9)
        np.testing.assert_allclose(Rotation.from_quat(np.roll(mesh.wxyz, -1)).as_matrix(), T[:3, :3], atol=1e-9)
        centre = T[:3, :3] @ models.mesh(1).centre + T[:3, 3]
        # the gizmo goes to the instance selected on the page (hidden while that one is not placed)
        for index, visible in ((1, False), (0, True)):
            session.focus_on(index)
            t0 = time.monotonic()
            while (viewer.choice.value != str(index) or viewer.gizmo.visible != visible) and time.monotonic() - t0 < 10:
                time.sleep(0.05)
            assert viewer.choice.value == str(index) and viewer.gizmo.visible == visible
        np.testing.assert_allclose(viewer.gizmo.position, centre / 1000.0, atol=1e-9)
        # a drag: 2 mm along world x and 10 degrees about world z, about the object's centre
        turn = Rotation.from_rotvec([0.0, 0.0, np.radians(10.0)])
        viewer.gizmo.position = viewer.gizmo.position + np.array([0.002, 0.0, 0.0])
        viewer.gizmo.wxyz = np.roll((turn * Rotation.from_quat(np.roll(viewer.gizmo.wxyz, -1))).as_quat(), 1)
        viewer._dragged()
        moved = session.instances[0]
        np.testing.assert_allclose(moved.T_wm[:3, :3], turn.as_matrix() @ T[:3, :3], atol=1e-9)
        np.testing.assert_allclose(moved.T_wm[:3, :3] @ models.mesh(1).centre + moved.T_wm[:3, 3],
                                   centre + [2.0, 0.0, 0.0], atol=1e-6)
        assert moved.source == "3d" and moved.verdict is None
    finally:
        viewer.stop()


@pytest.mark.slow
def test_refine_together_puts_moved_instances_back_and_keeps_decisions(labelled, tmp_path):
    """In-process: two placed instances, one moved 3 mm and turned 3 degrees by hand; refining them
    together (occlusion-aware) brings both within 1 mm / 1 degree, judged, their decisions kept. Each
    instance's alone pose is shown as it comes, before any verdict, and saved only when judged."""
    from autoalign.label.records import BEING_JUDGED
    from autoalign.label.session import LabelSession

    models = ModelSet.read(labelled.models)
    session = LabelSession(labelled.scene, models, tmp_path / "session")
    for k, obj, im in ((0, 1, 0), (1, 2, 5)):
        col, row = mask_pixel(mask_of(labelled.scene, im, k))
        session.place(obj, im, col, row)
    session.decide(1, "accepted")
    session.nudge(0, 0, [3.0, 0.0, 0.0], [0.0, 3.0, 0.0])
    mm, deg = pose_error(session.instances[0].T_wm, labelled.truth[0], models.mesh(1).centre)
    assert mm > 2.5 and deg > 2.5
    shown, put = [], session.state.put

    def put_watched(inst, shown_only: bool = False) -> None:
        shown.append((inst.index, inst.source, tuple(inst.reasons[:1]), shown_only))
        put(inst, shown_only)

    session.state.put = put_watched
    session.refine_together()
    first_judged = next(j for j, s in enumerate(shown) if s[1] == "together")
    assert {s[0] for s in shown[:first_judged]} == {0, 1}  # both shown before either is judged
    assert {s[1:] for s in shown[:first_judged]} == {("refining", (BEING_JUDGED,), True)}, shown[:first_judged]
    assert [s[:2] for s in shown[first_judged:]] == [(0, "together"), (1, "together")]
    for k in (0, 1):
        inst = session.instances[k]
        mm, deg = pose_error(inst.T_wm, labelled.truth[k], models.mesh(k + 1).centre)
        assert mm < 1.0 and deg < 1.0, (k, mm, deg)
        assert inst.source == "together" and inst.verdict == "ok" and inst.sigma_mm is not None
    assert session.instances[1].decision == "accepted" and session.instances[0].decision == "open"
    saved = json.loads((tmp_path / "session" / "session.json").read_text())
    assert [i["source"] for i in saved["instances"]] == ["together", "together"]


@pytest.mark.slow
def test_click_where_the_mask_misses_the_object_places_it_from_the_photo(labelled, tmp_path):
    """In-process: instance 0's mask in a view loses the half of the object clicked; with the
    photos in rgb/ the click still means instance 0, and the placement ends within 1 mm / 1 deg.
    Without photos the same click is refused with a one-line reason."""
    import shutil

    from autoalign.errors import AutoalignError
    from autoalign.label.session import LabelSession

    scene = tmp_path / "scene"
    shutil.copytree(labelled.scene, scene)
    def cut_off(im: int) -> tuple[np.ndarray, int, int] | None:
        """Instance 0's mask in image ``im`` less the half away from instance 1, and a pixel of that
        half 8-15 px from what is left and clearly nearer it than instance 1's mask (if any)."""
        mask = mask_of(scene, im, 0)
        other_path = scene / "mask_visib" / f"{im:06d}_000001.png"
        other = mask_of(scene, im, 1) if other_path.is_file() else np.zeros_like(mask)
        d_other = cv2.distanceTransform((~other).astype(np.uint8), cv2.DIST_L2, 3)
        xs = np.nonzero(mask)[1]
        for side in (slice(int(np.median(xs)), None), slice(None, int(np.median(xs)))):
            cut = mask.copy()
            cut[:, side] = False
            d_cut = cv2.distanceTransform((~cut).astype(np.uint8), cv2.DIST_L2, 3)
            gy, gx = np.nonzero(mask & ~cut & (d_cut >= 8) & (d_cut <= 15) & (d_other > d_cut + 10))
            if len(gy):
                return cut, int(gx[len(gx) // 2]), int(gy[len(gy) // 2])
        return None

    im, (cut, col, row) = next((im, c) for im in range(N_VIEWS) if (c := cut_off(im)) is not None)
    cv2.imwrite(str(scene / "mask_visib" / f"{im:06d}_000000.png"), cut.astype(np.uint8) * 255)
    models = ModelSet.read(labelled.models)
    session = LabelSession(scene, models, tmp_path / "session")
    assert session.place(1, im, col, row) == 0
    mm, deg = pose_error(session.instances[0].T_wm, labelled.truth[0], models.mesh(1).centre)
    assert mm < 1.0 and deg < 1.0, (mm, deg)

    shutil.rmtree(scene / "rgb")
    blind = LabelSession(scene, models, tmp_path / "session_blind")
    with pytest.raises(AutoalignError, match=f"no instance mask under pixel {col},{row} of image {im}"):
        blind.place(1, im, col, row)


def test_a_placement_far_from_the_click_is_shown_as_such():
    """A placement whose outline in the clicked view passes more than FAR_FROM_CLICK_PX from the
    click is 'check' with the distance (or stays 'failed'); one over or near the click is left as judged."""
    from autoalign.label.records import FAR_FROM_CLICK_PX, Judgement, click_distance_px, far_from_click
    from autoalign.quality.verdict import Verdict

    sil = np.zeros((100, 200), bool)
    sil[40:60, 100:140] = True  # columns 100-139, rows 40-59
    assert click_distance_px(sil, 120.0, 50.0) == 0.0
    assert click_distance_px(sil, 60.0, 50.0) == pytest.approx(40.0)  # 40 columns left of column 100
    ok = Judgement(Verdict("ok"), None)
    assert far_from_click(ok, sil, 3, 120.0 - 0.0, 50.0) is ok
    assert far_from_click(ok, sil, 3, 100.0 - FAR_FROM_CLICK_PX + 1, 50.0) is ok
    far = far_from_click(ok, sil, 3, 60.0, 50.0)
    assert far.verdict.status == "check" and "image 3 is 40 px from the click" in far.verdict.reasons[-1]
    assert far_from_click(Judgement(Verdict("failed"), None), sil, 3, 60.0, 50.0).verdict.status == "failed"
    assert "not in the clicked view" in far_from_click(ok, np.zeros_like(sil), 3, 60.0, 50.0).verdict.reasons[-1]
