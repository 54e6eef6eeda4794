"""``autoalign label``'s server against what a careless or hostile request does (issue 43, items 5
and 10): a second server on the same session folder, a body too large for its connection, a change
from another site, numbers that overflow a pose, JSON nested 100,000 levels, a ``session.json``
with a broken pose, and viser's own URL printed above the page's.

Most run against one server in this process, on a small synthetic scene whose instance 0 is saved
as placed; each checks both the refusal and that ``session.json`` did not change, and where a
refusal could hide a test that cannot fail, the same request done right is shown to work.
"""

from __future__ import annotations

import http.client
import json
import os
import re
import signal
import socket
import subprocess
import sys
import threading
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

from autoalign.cli.label_http import MAX_BODY, TOKEN_HEADER, LabelServer
from autoalign.errors import AutoalignError
from autoalign.experiments.benchmarks.bench_scene import make_bench_scene
from autoalign.experiments.pages.label_page_driver import LabelServerProcess
from autoalign.io.models import ModelSet
from autoalign.label.lock import LOCK_NAME, SessionLock
from autoalign.label.records import LabelledInstance
from autoalign.label.session import LabelSession
from autoalign.label.session_file import SessionFile


@dataclass
class Served:
    scene: Path
    models: Path
    out: Path
    truth: list[np.ndarray]
    session: LabelSession
    server: LabelServer

    @property
    def port(self) -> int:
        return self.server.server_address[1]

    @property
    def token(self) -> dict[str, str]:
        return {TOKEN_HEADER: self.server.token}

    def saved(self) -> bytes:
        return (self.out / "session.json").read_bytes()


@pytest.fixture(scope="module")
def served(tmp_path_factory) -> Iterator[Served]:
    """A server in this process on two objects in 6 views, instance 0 saved as object 1 at its true pose."""
    root = tmp_path_factory.mktemp("label_server")
    truth = make_bench_scene(root, 2, views=6)
    models = ModelSet.read(root / "models")
    out = root / "session"
    SessionFile(out, root / "scene", models.folder).write(3, [LabelledInstance(0, 1, truth[0]), LabelledInstance(1)])
    session = LabelSession(root / "scene", models, out)
    server = LabelServer(session, 0)
    thread = threading.Thread(target=server.serve_forever, kwargs={"poll_interval": 0.1}, daemon=True)
    thread.start()
    try:
        yield Served(root / "scene", root / "models", out, truth, session, server)
    finally:
        server.shutdown()
        server.server_close()


def post(served: Served, path: str, body: bytes | dict, headers: dict[str, str] | None = None,
         conn: http.client.HTTPConnection | None = None) -> tuple[int, dict]:
    """POST ``body`` (a dict as JSON) with ``headers`` (default: the page's token); (status, JSON reply)."""
    conn = conn or http.client.HTTPConnection("127.0.0.1", served.port, timeout=30)
    data = json.dumps(body).encode() if isinstance(body, dict) else body
    conn.request("POST", path, body=data, headers=served.token if headers is None else headers)
    r = conn.getresponse()
    return r.status, json.loads(r.read() or b"{}")


def raw_request(method: str, path: str, body: bytes, headers: dict[str, str]) -> bytes:
    head = "".join(f"{k}: {v}\r\n" for k, v in {"Host": "127.0.0.1", **headers}.items())
    return f"{method} {path} HTTP/1.1\r\n{head}\r\n".encode() + body


def read_to_end(sock: socket.socket) -> bytes:
    """Everything the server sends until it closes (a reset counts as closed)."""
    got = b""
    try:
        while chunk := sock.recv(65536):
            got += chunk
    except ConnectionResetError:
        pass
    return got


# ---------------------------------------------------------------------------------------------- item 10: desync

REJECT_0 = json.dumps({"instance": 0, "decision": "rejected"}).encode()


@pytest.mark.parametrize("method, path, headers, status", [
    ("POST", "/api/symmetric", {"Content-Length": str(2 * MAX_BODY)}, 413),  # the issue's: over 1 MiB
    ("POST", "/api/symmetric", {"Content-Length": str(MAX_BODY + 1)}, 413),
    ("POST", "/api/symmetric", {"Content-Length": "-5"}, 400),
    ("POST", "/api/symmetric", {"Content-Length": "lots"}, 400),
    ("POST", "/api/symmetric", {"Transfer-Encoding": "chunked"}, 411),
    ("POST", "/api/symmetric", {"Content-Length": "10", "Origin": "http://evil.example"}, 403),  # refused unread
    ("GET", "/api/state?since=-5", {"Content-Length": str(len(REJECT_0) + 200)}, 200),  # a GET's body is not read
])
def test_a_body_left_unread_is_never_taken_for_the_next_request(served, method, path, headers, status):
    """The rest of the body, a request of its own (with the page's token), is sent after the reply:
    the server closed the connection, so it never runs. Sent on a connection of its own, it does."""
    embedded = raw_request("POST", "/api/decide", REJECT_0,
                           {**served.token, "Content-Type": "application/json", "Content-Length": str(len(REJECT_0))})
    before = served.saved()
    with socket.create_connection(("127.0.0.1", served.port), timeout=30) as sock:
        sock.sendall(raw_request(method, path, b"", {**served.token, "Content-Type": "text/plain", **headers}))
        reply = read_to_end(sock)
        assert reply.startswith(f"HTTP/1.1 {status} ".encode()), reply[:200]
        assert b"\r\nConnection: close\r\n" in reply
        try:
            sock.sendall(embedded)
            after = read_to_end(sock)
        except (BrokenPipeError, ConnectionResetError):
            after = b""
        assert after == b""
    assert served.saved() == before and served.session.instances[0].decision == "open"

    with socket.create_connection(("127.0.0.1", served.port), timeout=30) as sock:  # the control: it would run
        sock.sendall(embedded)
        assert sock.recv(65536).startswith(b"HTTP/1.1 200 ")
    assert served.session.instances[0].decision == "rejected"
    assert post(served, "/api/decide", {"instance": 0, "decision": "open"})[0] == 200


def test_an_oversized_post_sent_in_one_piece_runs_nothing_of_its_body(served):
    """The issue's attack as sent: the headers of a 2 MiB POST and, as its body, a request of its own."""
    embedded = raw_request("POST", "/api/decide", REJECT_0,
                           {**served.token, "Content-Type": "application/json", "Content-Length": str(len(REJECT_0))})
    before = served.saved()
    with socket.create_connection(("127.0.0.1", served.port), timeout=30) as sock:
        sock.sendall(raw_request("POST", "/api/symmetric", embedded,
                                 {**served.token, "Content-Type": "text/plain", "Content-Length": str(2 * MAX_BODY)}))
        reply = read_to_end(sock)
    assert reply.count(b"HTTP/1.1 ") <= 1 and b"HTTP/1.1 200" not in reply, reply[:300]  # one refusal at most
    assert served.saved() == before and served.session.instances[0].decision == "open"


# ---------------------------------------------------------------------------------------------- item 10: origin

EVIL = "http://evil.example"


@pytest.mark.parametrize("with_token, headers", [
    (False, {"Content-Type": "text/plain"}),  # what a form on any web page sends: no token
    (False, {"Content-Type": "text/plain", "Origin": EVIL}),
    (False, {"Content-Type": "text/plain", TOKEN_HEADER: "not-the-token"}),
    (True, {"Origin": EVIL}),  # the token itself, from the wrong page
    (True, {"Referer": EVIL + "/attack.html"}),
    (True, {"Origin": "null"}),
    (True, {"Origin": "http://127.0.0.1:1"}),  # another local port
])
def test_a_change_without_the_token_or_from_another_origin_is_refused(served, with_token, headers):
    headers = {**(served.token if with_token else {}), **headers}
    before, job = served.saved(), served.session.job.number
    for path, body in (("/api/decide", {"instance": 0, "decision": "accepted"}), ("/api/export", {})):
        status, reply = post(served, path, body, headers)
        assert status == 403 and ("token" in reply["error"].lower() or "refused" in reply["error"]), reply
    assert served.saved() == before and served.session.job.number == job
    assert served.session.instances[0].decision == "open"


def test_the_page_carries_the_token_and_its_own_origin_is_let_through(served):
    conn = http.client.HTTPConnection("127.0.0.1", served.port, timeout=30)
    conn.request("GET", "/")
    page = conn.getresponse().read().decode()
    assert f'<meta name="autoalign-token" content="{served.server.token}">' in page
    conn.request("OPTIONS", "/api/decide", headers={"Origin": EVIL, "Access-Control-Request-Method": "POST",
                                                    "Access-Control-Request-Headers": TOKEN_HEADER})
    r = conn.getresponse()
    r.read()
    assert r.status >= 400 and r.getheader("Access-Control-Allow-Origin") is None  # no preflight: no custom header
    for origin in (f"http://127.0.0.1:{served.port}", f"http://localhost:{served.port}"):
        status, _ = post(served, "/api/decide", {"instance": 0, "decision": "accepted"}, {**served.token, "Origin": origin})
        assert status == 200 and served.session.instances[0].decision == "accepted"
        assert json.loads(served.saved())["instances"][0]["decision"] == "accepted"
        assert post(served, "/api/decide", {"instance": 0, "decision": "open"})[0] == 200


# ---------------------------------------------------------------------------------------------- item 10: numbers

NUDGE = '{"instance": 0, "image_id": 0, %s}'


@pytest.mark.parametrize("path, body, field", [
    ("/api/nudge", NUDGE % '"move_mm": [1e308, 0, 0]', "move_mm"),  # the issue's: overflowed to NaN
    ("/api/nudge", NUDGE % '"move_mm": [1e400, 0, 0]', "move_mm"),  # read as inf
    ("/api/nudge", NUDGE % '"move_mm": [Infinity, 0, 0]', "JSON"),  # not JSON, though Python reads it
    ("/api/nudge", NUDGE % '"turn_deg": [NaN, 0, 0]', "JSON"),
    ("/api/nudge", NUDGE % '"turn_deg": [0, 0, 1e5]', "turn_deg"),
    ("/api/nudge", NUDGE % '"move_mm": ["1", 0, 0]', "move_mm"),
    ("/api/nudge", NUDGE % '"move_mm": [1, 0]', "move_mm"),
    ("/api/nudge", '{"instance": 1e308, "image_id": 0, "move_mm": [1, 0, 0]}', "instance"),
    ("/api/nudge", '{"instance": 0, "image_id": -1, "move_mm": [1, 0, 0]}', "image_id"),
    ("/api/place", '{"obj_id": 1, "image_id": 0, "u": 1e308, "v": 10}', "u"),
    ("/api/place", '{"obj_id": 1, "image_id": 0, "u": 10, "v": -1e400}', "v"),
    ("/api/place", '{"obj_id": true, "image_id": 0, "u": 10, "v": 10}', "obj_id"),
    ("/api/decide", '{"instance": 0, "decision": 5}', "decision"),
    ("/api/symmetric", '{"instance": 0, "symmetric": "false"}', "symmetric"),
    ("/api/undo", '{"instance": 0.5}', "instance"),
    ("/api/focus", "{}", "instance"),
])
def test_a_bad_number_is_a_400_naming_it_and_nothing_is_written(served, path, body, field):
    before, revision, job = served.saved(), served.session.revision, served.session.job.number
    status, reply = post(served, path, body.encode())
    assert status == 400 and field in reply["error"] and "\n" not in reply["error"], reply
    assert served.saved() == before and served.session.revision == revision and served.session.job.number == job
    assert np.isfinite(served.session.instances[0].T_wm).all()


def test_a_sane_nudge_still_moves_the_pose_exactly(served):
    T0 = served.session.instances[0].T_wm.copy()
    status, _ = post(served, "/api/nudge", {"instance": 0, "image_id": 0, "move_mm": [1.0, 0, 0]})
    assert status == 200
    R_w2c = served.session.view(0).R_w2c
    np.testing.assert_allclose(served.session.instances[0].T_wm[:3, 3] - T0[:3, 3], R_w2c.T @ [1.0, 0, 0], atol=1e-9)
    assert json.loads(served.saved())["instances"][0]["T_wm"] == served.session.instances[0].T_wm.tolist()
    assert post(served, "/api/undo", {"instance": 0})[0] == 200
    np.testing.assert_array_equal(served.session.instances[0].T_wm, T0)


def test_the_session_refuses_a_pose_out_of_bounds_from_any_caller(served):
    """In-process callers (the 3D view's gizmo, a script) meet the same bounds as the page."""
    before, T0 = served.saved(), served.session.instances[0].T_wm.copy()
    far, nan = T0.copy(), T0.copy()
    far[0, 3], nan[1, 3] = 2e6, np.nan
    with pytest.raises(AutoalignError, match="nudge is three finite numbers"):
        served.session.nudge(0, 0, [1e308, 0.0, 0.0], [0.0, 0.0, 0.0])
    with pytest.raises(AutoalignError, match="mm from the origin"):
        served.session.set_pose(0, far)
    with pytest.raises(AutoalignError, match="not finite"):
        served.session.set_pose(0, nan)
    assert served.saved() == before
    np.testing.assert_array_equal(served.session.instances[0].T_wm, T0)


# ---------------------------------------------------------------------------------------------- item 10: nesting

DEEP = b"[" * 100_000 + b"]" * 100_000


@pytest.mark.parametrize("body", [DEEP, b'{"instance": ' + DEEP + b"}"], ids=["list", "in-a-field"])
def test_json_nested_100000_levels_is_a_400_and_the_connection_stays_up(served, body):
    before = served.saved()
    conn = http.client.HTTPConnection("127.0.0.1", served.port, timeout=30)
    status, reply = post(served, "/api/decide", body, conn=conn)
    assert status == 400 and "nested" in reply["error"], reply
    conn.request("GET", "/api/state?since=-5")  # the same connection: the body was read whole
    assert conn.getresponse().status == 200
    assert served.saved() == before


# ---------------------------------------------------------------------------------------------- item 10: session.json

EYE = [[1.0, 0.0, 0.0, 0.0], [0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0], [0.0, 0.0, 0.0, 1.0]]


def _with_entry(matrix: str, where: tuple[int, int], value: str) -> str:
    rows = [list(map(repr, r)) for r in json.loads(matrix)]
    rows[where[0]][where[1]] = value
    return "[" + ", ".join("[" + ", ".join(r) + "]" for r in rows) + "]"


@pytest.mark.parametrize("t_wm, why", [
    ("null", "T_wm is null"),  # what a NaN pose was saved as
    (_with_entry(json.dumps(EYE), (2, 3), "null"), "not finite"),
    (_with_entry(json.dumps(EYE), (0, 3), "NaN"), "not finite"),
    (_with_entry(json.dumps(EYE), (1, 3), "1e400"), "not finite"),
    (_with_entry(json.dumps(EYE), (0, 3), "1e300"), "from the origin"),
    (_with_entry(json.dumps(EYE), (0, 0), "2.0"), "not a rigid transform"),
    (_with_entry(json.dumps(EYE), (3, 0), "1.0"), "not a rigid transform"),
    ("[[1, 0, 0], [0, 1, 0], [0, 0, 1]]", "not 4x4"),
    ('"identity"', "not a 4x4 matrix"),
])
def test_a_session_json_with_a_bad_pose_is_refused_at_load(served, tmp_path, t_wm, why):
    out = tmp_path / "session"
    out.mkdir()
    record = {**LabelledInstance(0, 1, np.eye(4)).record(), "T_wm": "@T@"}
    text = json.dumps({"kind": "autoalign label session", "scene_dir": str(served.scene), "revision": 35,
                       "instances": [record]}).replace('"@T@"', t_wm)
    (out / "session.json").write_text(text)
    with pytest.raises(AutoalignError) as err:
        LabelSession(served.scene, ModelSet.read(served.models), out)
    msg = str(err.value)
    assert msg.startswith(f"{out / 'session.json'}: instance 0 is malformed") and why in msg, msg
    assert "\n" not in msg and "correct or remove that entry" in msg
    assert (out / "session.json").read_text() == text


def test_the_command_exits_2_on_a_session_json_with_a_nan_pose(served, tmp_path):
    out = tmp_path / "session"
    out.mkdir()
    text = json.dumps({"kind": "autoalign label session", "scene_dir": str(served.scene), "revision": 35,
                       "instances": [{**LabelledInstance(0, 1, np.eye(4)).record(), "T_wm": [[float("nan")] * 4] * 4}]})
    (out / "session.json").write_text(text)
    r = subprocess.run([sys.executable, "-m", "autoalign.cli.main", "label", str(served.scene), "--models",
                        str(served.models), "--out", str(out), "--no-browser", "--no-3d"],
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 2 and r.stderr.count("\n") == 1, r.stderr
    assert f"{out / 'session.json'}: instance 0 is malformed (T_wm is not finite" in r.stderr
    assert (out / "session.json").read_text() == text and not (out / LOCK_NAME).exists()
    assert "http://" not in r.stdout


# ---------------------------------------------------------------------------------------------- item 5: the lock

def _dead_pid() -> int:
    p = subprocess.Popen([sys.executable, "-c", "pass"])
    p.wait()
    return p.pid


def test_the_lock_refuses_a_second_holder_and_takes_over_a_dead_ones(tmp_path):
    out = tmp_path / "out"
    first = SessionLock.acquire(out)
    first.announce("http://127.0.0.1:4242/")
    with pytest.raises(AutoalignError) as err:
        SessionLock.acquire(out)  # another open file: flock refuses it, in this process too
    msg = str(err.value)
    assert msg.startswith(f"{out}: another autoalign label server") and "http://127.0.0.1:4242/" in msg
    assert f"pid {os.getpid()} on {socket.gethostname()}" in msg and "--out" in msg and "\n" not in msg
    first.release()
    assert not (out / LOCK_NAME).exists() and not out.exists()  # the lock made the folder: nothing else is there

    (out).mkdir()
    (out / LOCK_NAME).write_text(json.dumps({"pid": _dead_pid(), "host": socket.gethostname(), "url": "http://x/"}))
    with SessionLock.acquire(out):  # left by a server that was killed: taken over
        held = json.loads((out / LOCK_NAME).read_text())
        assert held["pid"] == os.getpid() and held["url"] is None
    assert out.is_dir() and not (out / LOCK_NAME).exists()  # a folder it did not make stays


def _urls(text: str) -> list[str]:
    return re.findall(r"\b(?:https?|wss?)://[^\s'\"()]+", text)


@pytest.mark.slow
def test_a_second_server_on_the_same_out_is_refused_and_the_first_keeps_its_work(served, tmp_path):
    """The issue's case: the first server has a change saved (revision 4); the second exits 2 naming
    the folder, the first's URL and pid, and writes nothing; the first carries on. Only the page's URL
    is printed (not viser's, of its 3D view)."""
    out = tmp_path / "session"
    with LabelServerProcess(served.scene, served.models, out) as first:  # with its 3D view
        conn = http.client.HTTPConnection("127.0.0.1", first.port, timeout=30)
        conn.request("GET", "/api/state")
        state = json.loads(conn.getresponse().read())
        assert state["viewer_url"] and state["viewer_url"] != first.url
        token = {TOKEN_HEADER: state["token"]}
        for flag in (True, False, True, False):
            conn.request("POST", "/api/symmetric", body=json.dumps({"instance": 0, "symmetric": flag}), headers=token)
            r = conn.getresponse()
            assert r.status == 200, r.read()
            r.read()
        before = (out / "session.json").read_bytes()
        assert json.loads(before)["revision"] == 4
        held = json.loads((out / LOCK_NAME).read_text())
        assert held["pid"] == first.proc.pid and held["url"] == first.url

        second = subprocess.run([sys.executable, "-m", "autoalign.cli.main", "label", str(served.scene), "--models",
                                 str(served.models), "--out", str(out), "--no-browser", "--no-3d"],
                                capture_output=True, text=True, timeout=300)
        assert second.returncode == 2 and second.stderr.count("\n") == 1, second.stderr
        for part in (f"{out}: another autoalign label server", first.url, f"pid {first.proc.pid}", "--out"):
            assert part in second.stderr, (part, second.stderr)
        assert (out / "session.json").read_bytes() == before

        conn.request("POST", "/api/symmetric", body=json.dumps({"instance": 0, "symmetric": True}), headers=token)
        r = conn.getresponse()
        assert r.status == 200 and json.loads(r.read())["revision"] == 5
        assert json.loads((out / "session.json").read_text())["revision"] == 5
        assert first.stop() == 130
    assert not (out / LOCK_NAME).exists()
    assert _urls(first.output) == [first.url] and "viser" not in first.output, first.output


@pytest.mark.slow
def test_a_lock_left_by_a_killed_server_is_taken_over(served, tmp_path):
    out = tmp_path / "session"
    with LabelServerProcess(served.scene, served.models, out, ("--no-3d",)) as killed:
        assert killed.stop(signal.SIGKILL) == -signal.SIGKILL
    assert json.loads((out / LOCK_NAME).read_text())["pid"] == killed.proc.pid  # left behind, its pid dead
    with LabelServerProcess(served.scene, served.models, out, ("--no-3d",)) as again:
        held = json.loads((out / LOCK_NAME).read_text())
        assert held["pid"] == again.proc.pid and held["url"] == again.url
        assert again.stop() == 130


# ---------------------------------------------------------------------------------------------- the page's export

def test_a_second_export_with_fewer_objects_replaces_the_first_as_a_whole(served, tmp_path):
    """The page's "Export" writes OUT_DIR/bop as 'autoalign export' does: an export of one object after
    one of two leaves no mask of the second behind, and a bop/ it did not make is refused untouched."""
    from autoalign.cli.label_http import export_session

    out = tmp_path / "session"
    SessionFile(out, served.scene, served.models).write(
        1, [LabelledInstance(0, 1, served.truth[0], decision="accepted"),
            LabelledInstance(1, 2, served.truth[1], decision="accepted")])
    session = LabelSession(served.scene, ModelSet.read(served.models), out)
    bop = export_session(session)

    def files() -> set[str]:
        return {p.relative_to(bop).as_posix() for p in bop.rglob("*") if p.is_file()}

    first = files()
    assert any(name.startswith("mask_visib/") and name.endswith("_000001.png") for name in first)
    session.decide(1, "rejected")
    assert export_session(session) == bop
    second = files()
    masks = sorted(name for name in second if name.startswith(("mask/", "mask_visib/")))
    assert masks and all(name.endswith("_000000.png") for name in masks), masks  # nothing of instance 1 is left
    assert len(second) < len(first) and second <= first
    gt = json.loads((bop / "scene_gt.json").read_text())
    assert {e["obj_id"] for entries in gt.values() for e in entries} == {1}
    assert not [p for p in out.iterdir() if p.name.startswith(".bop.")]  # no temporary folder left beside it

    other = tmp_path / "other"
    (other / "bop").mkdir(parents=True)
    (other / "bop" / "notes.txt").write_text("mine")
    SessionFile(other, served.scene, served.models).write(1, [LabelledInstance(0, 1, served.truth[0], decision="accepted")])
    with pytest.raises(AutoalignError, match="has no export.json"):
        export_session(LabelSession(served.scene, ModelSet.read(served.models), other))
    assert [p.name for p in (other / "bop").iterdir()] == ["notes.txt"]
    assert not (other / "scene_gt.json").exists()  # refused before anything was written
