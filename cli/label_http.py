"""The web server of ``autoalign label``: the page, the views' images, and a small JSON API over a
:class:`~autoalign.label.session.LabelSession`.

Standard library ``http.server`` (threaded): one local user, a handful of requests a second, no
dependency to keep up to date; the 3D view is viser's own server (:mod:`autoalign.cli.label_3d`).

It listens on 127.0.0.1 only, answers only requests whose ``Host`` is that address or
``localhost`` (a web page elsewhere cannot reach it through DNS rebinding), and serves files
only from inside the scene folder, the models folder and the page's own folder (403 otherwise).

A change (every POST) must also come from the page itself: it carries the token this server drew
at its start (:data:`TOKEN_HEADER`; the page has it from its own HTML and from the state), and an
``Origin`` or ``Referer`` it sends must be this server's. A page on another site can send a POST
to 127.0.0.1 (a ``text/plain`` form needs no permission) but can read neither the page nor the
state, so it has no token; a custom header would need a CORS preflight, which is not answered.
A POST's body is at most :data:`MAX_BODY` bytes, with a ``Content-Length``; one refused before its
body was read closes the connection, so that the unread rest is never taken for the next request.
Every field is checked (:mod:`autoalign.label.fields`): a bad one is a 400 naming it.

API (JSON; pixel coordinates are OpenCV's, in the views' resolution; errors are
``{"error": one line}`` with status 400, or 409 while another job runs):

* ``GET /api/state?since=R``: the session (:meth:`LabelSession.snapshot`), as soon as its
  revision differs from ``R`` (at most :data:`POLL_S` later); ``viewer_url`` is the 3D view,
  ``token`` this server's (a tab open before a restart picks up the new one).
* ``GET /api/contours/K``: instance K's silhouette outline per view, ``{pose_revision, contours}``.
* ``GET /api/view/IM.jpg``, ``/api/tint/IM.png``: a view's photo (dark grey without one) and its
  masks tinted in the instances' colours (transparent elsewhere).
* ``GET /files/scene/PATH``, ``/files/models/PATH``: files of those folders.
* ``POST /api/place`` ``{obj_id, image_id, u, v}``; ``/api/refine`` ``{instance}``; ``/api/refine_all``
  (every placed instance not rejected, together, occlusion-aware); ``/api/export``: start the job
  (202); its progress is in the state's ``job``.
* ``POST /api/nudge`` ``{instance, image_id, move_mm: [3], turn_deg: [3]}`` (camera axes);
  ``/api/undo`` ``{instance}`` (back to before its last move); ``/api/decide`` ``{instance, decision}``;
  ``/api/symmetric`` ``{instance, symmetric}``;
  ``/api/focus`` ``{instance}`` (the instance selected on the page: the 3D view's gizmo goes to it).
"""

from __future__ import annotations

import hmac
import json
import mimetypes
import re
import secrets
import sys
import threading
from http import HTTPStatus
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path
from typing import Any
from urllib.parse import parse_qs, unquote, urlsplit

import cv2
import numpy as np

from autoalign.errors import AutoalignError
from autoalign.label.fields import MAX_MOVE_MM, MAX_PIXEL, MAX_TURN_DEG, flag, integer, number, text, vector3
from autoalign.label.session import LabelSession, Progress

HOST = "127.0.0.1"
POLL_S = 10.0
"""Longest wait of a ``/api/state?since=R`` request before it answers unchanged."""
PAGE_DIR = Path(__file__).resolve().parent / "label_page"
TOKEN_HEADER = "X-Autoalign-Token"
"""The header that carries the server's token on every POST."""
TOKEN_SLOT = "__AUTOALIGN_TOKEN__"
"""Where ``index.html`` gets the token."""
MAX_BODY = 1 << 20
"""The largest POST body accepted (bytes); the page's are under 1 KiB."""
TINT_ALPHA = 0.35
INSTANCE_COLOURS_RGB = ("#ffb43c", "#3c78ff", "#50dc50", "#dc50dc", "#e6e63c", "#50c8ff", "#ff7878", "#78ffc8",
                        "#ff50a0", "#a0a050")
"""Instance ``k``'s colour on the page (by its position among the scene's instances, cycled)."""


def instance_rgb(session: LabelSession, index: int) -> tuple[int, int, int]:
    """Instance ``index``'s colour (0-255 RGB): by its position among the scene's instances, as the page does."""
    hexa = INSTANCE_COLOURS_RGB[list(session.instances).index(index) % len(INSTANCE_COLOURS_RGB)]
    return int(hexa[1:3], 16), int(hexa[3:5], 16), int(hexa[5:7], 16)


def inside(root: Path, relative: str) -> Path | None:
    """``root / relative`` if that names an existing file inside ``root`` (links resolved), else ``None``."""
    try:
        path = (root / relative).resolve(strict=True)
    except (OSError, RuntimeError):
        return None
    return path if path.is_file() and path.is_relative_to(root.resolve()) else None


class LabelServer(ThreadingHTTPServer):
    """The HTTP server of one session (port 0: a free one)."""

    daemon_threads = True

    def __init__(self, session: LabelSession, port: int = 0, viewer_url: str | None = None) -> None:
        super().__init__((HOST, port), LabelHandler)
        self.session = session
        self.viewer_url = viewer_url
        self.roots = {"scene": session.scene_dir, "models": session.models.folder}
        self.token = secrets.token_urlsafe(32)  # drawn anew at each start: see the module doc
        self._images: dict[str, bytes] = {}
        self._images_lock = threading.Lock()

    @property
    def url(self) -> str:
        return f"http://{HOST}:{self.server_address[1]}/"

    @property
    def origins(self) -> tuple[str, ...]:
        """The origins of this server's own page."""
        return tuple(f"http://{host}:{self.server_address[1]}" for host in (HOST, "localhost"))

    def image(self, key: str, make: Any) -> bytes:
        """The encoded image ``key``, made once by ``make()``."""
        with self._images_lock:
            if key not in self._images:
                self._images[key] = make()
            return self._images[key]

    def view_photo(self, image_id: int) -> bytes:
        from autoalign.quality.overlay import photo_at

        s = self.session
        cam = s.views[s.image_ids.index(image_id)]
        photo = photo_at(s.scene_dir, image_id, cam.width, cam.height)
        img = photo if photo is not None else np.full((cam.height, cam.width, 3), 40, np.uint8)
        return cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, 90])[1].tobytes()

    def view_tint(self, image_id: int) -> bytes:
        s = self.session
        cam = s.views[s.image_ids.index(image_id)]
        rgba = np.zeros((cam.height, cam.width, 4), np.uint8)
        for k, m in s.masks_in_view(image_id).items():
            r, g, b = instance_rgb(s, k)
            rgba[m] = [b, g, r, int(255 * TINT_ALPHA)]  # BGRA for OpenCV
        return cv2.imencode(".png", rgba)[1].tobytes()


class LabelHandler(BaseHTTPRequestHandler):
    """One request (see module doc)."""

    server: LabelServer
    protocol_version = "HTTP/1.1"

    def log_message(self, format: str, *args: Any) -> None:  # noqa: A002 - the base class's name
        pass  # the terminal shows the session's progress, not every request

    # ------------------------------------------------------------------ replies

    def _send(self, status: int, body: bytes, content_type: str, cache: bool = False) -> None:
        self.send_response(status)
        self.send_header("Content-Type", content_type)
        self.send_header("Content-Length", str(len(body)))
        self.send_header("Cache-Control", "max-age=3600" if cache else "no-store")
        if self.close_connection:
            self.send_header("Connection", "close")
        self.end_headers()
        self.wfile.write(body)

    def _json(self, data: Any, status: int = 200) -> None:
        self._send(status, json.dumps(data, allow_nan=False).encode(), "application/json")

    def _error(self, status: int, message: str) -> None:
        self._json({"error": " ".join(message.split())}, status)

    def _refuse(self, status: int, message: str) -> None:
        """An error, then the connection closed: what is left of the request (a body not read) must
        not be parsed as the next one."""
        self.close_connection = True
        self._error(status, message)

    def _host_ok(self) -> bool:
        host = (self.headers.get("Host") or "").rsplit(":", 1)[0]
        if host in (HOST, "localhost"):
            return True
        self._refuse(HTTPStatus.FORBIDDEN, f"host {host!r} refused: autoalign label answers {HOST} only")
        return False

    # ------------------------------------------------------------------ GET

    def do_GET(self) -> None:  # noqa: N802 - http.server's name
        if self.headers.get("Content-Length", "0").strip() not in ("", "0") or "Transfer-Encoding" in self.headers:
            self.close_connection = True  # a GET's body is not read: it must not become the next request
        if not self._host_ok():
            return
        url = urlsplit(self.path)
        path = unquote(url.path)
        try:
            self._get(path, parse_qs(url.query))
        except AutoalignError as exc:
            self._error(HTTPStatus.BAD_REQUEST, str(exc))
        except (ValueError, KeyError, IndexError):
            self._error(HTTPStatus.NOT_FOUND, f"{path}: no such thing here")

    def _get(self, path: str, query: dict[str, list[str]]) -> None:
        s = self.server.session
        if path in ("/", "/index.html"):
            page = (PAGE_DIR / "index.html").read_text().replace(TOKEN_SLOT, self.server.token)
            return self._send(200, page.encode(), "text/html; charset=utf-8")
        if path.startswith("/static/"):
            return self._file(PAGE_DIR, path[len("/static/"):])
        if path.startswith("/files/"):
            root, _, rel = path[len("/files/"):].partition("/")
            if root not in self.server.roots:
                return self._error(HTTPStatus.NOT_FOUND, f"{path}: only /files/scene/ and /files/models/ are served")
            return self._file(self.server.roots[root], rel)
        if path == "/api/state":
            since = query.get("since", ["-1"])[0]
            if not re.fullmatch(r"-?[0-9]{1,18}", since):
                raise AutoalignError(f"since: {since[:20]!r} is not a revision (a whole number)")
            s.wait(int(since), POLL_S)
            return self._json({**s.snapshot(), "viewer_url": self.server.viewer_url,
                               "colours": INSTANCE_COLOURS_RGB, "token": self.server.token})
        if path.startswith("/api/contours/"):
            rev, polys = s.contours(int(path.rsplit("/", 1)[1]))
            return self._json({"pose_revision": rev, "contours": {str(k): v for k, v in polys.items()}})
        if path.startswith("/api/view/") and path.endswith(".jpg"):
            im = int(path[len("/api/view/"):-4])
            return self._send(200, self.server.image(f"v{im}", lambda: self.server.view_photo(im)), "image/jpeg", True)
        if path.startswith("/api/tint/") and path.endswith(".png"):
            im = int(path[len("/api/tint/"):-4])
            return self._send(200, self.server.image(f"t{im}", lambda: self.server.view_tint(im)), "image/png", True)
        self._error(HTTPStatus.NOT_FOUND, f"{path}: no such thing here")

    def _file(self, root: Path, relative: str) -> None:
        found = inside(root, relative)
        if found is None:
            return self._error(HTTPStatus.FORBIDDEN, f"{relative}: not a file inside {root}; only the scene's, the "
                                                     "models' and the page's own files are served")
        kind = mimetypes.guess_type(found.name)[0] or "application/octet-stream"
        self._send(200, found.read_bytes(), kind)

    # ------------------------------------------------------------------ POST

    def do_POST(self) -> None:  # noqa: N802 - http.server's name
        if not (self._host_ok() and self._origin_ok() and self._token_ok()):
            return
        body = self._body()
        if body is None:
            return
        try:
            self._post(urlsplit(self.path).path, body)
        except AutoalignError as exc:
            self._error(HTTPStatus.BAD_REQUEST, str(exc))
        except (KeyError, TypeError, ValueError) as exc:  # the fields are checked: this is a session's own refusal
            self._error(HTTPStatus.BAD_REQUEST, f"{self.path}: refused ({exc})")

    def _origin_ok(self) -> bool:
        """Whether the request's ``Origin`` (or, without one, its ``Referer``) is this server's page, if it names one."""
        origin = self.headers.get("Origin")
        if origin is None and self.headers.get("Referer"):
            ref = urlsplit(self.headers["Referer"])
            origin = f"{ref.scheme}://{ref.netloc}"
        if origin is None or origin in self.server.origins:
            return True
        self._refuse(HTTPStatus.FORBIDDEN, f"a change from {origin[:80]!r} refused: only the page at "
                                           f"{self.server.url} changes this session")
        return False

    def _token_ok(self) -> bool:
        given = self.headers.get(TOKEN_HEADER, "").encode("latin-1", "replace")
        if hmac.compare_digest(given, self.server.token.encode()):
            return True
        self._refuse(HTTPStatus.FORBIDDEN, f"missing or wrong {TOKEN_HEADER}: changes come only from the page this "
                                           f"server serves; reload {self.server.url}")
        return False

    def _body(self) -> dict[str, Any] | None:
        """The request's JSON object (``{}`` if empty), or ``None`` once refused (a body that is not
        read whole closes the connection)."""
        lengths = self.headers.get_all("Content-Length") or ["0"]
        if "Transfer-Encoding" in self.headers or len(lengths) > 1:
            self._refuse(HTTPStatus.LENGTH_REQUIRED, "send the body with one Content-Length, not chunked")
            return None
        try:
            n = int(lengths[0])
        except ValueError:
            n = -1
        if not 0 <= n <= MAX_BODY:
            self._refuse(HTTPStatus.REQUEST_ENTITY_TOO_LARGE if n > MAX_BODY else HTTPStatus.BAD_REQUEST,
                         f"a request body is 0 to {MAX_BODY} bytes with its Content-Length, not {lengths[0][:20]!r}")
            return None
        raw = self.rfile.read(n)
        if len(raw) < n:
            self.close_connection = True  # the client went away mid-body
            return None
        try:
            return json_object(raw)
        except AutoalignError as exc:
            self._error(HTTPStatus.BAD_REQUEST, str(exc))  # the body was read whole: the connection stays
            return None

    def _post(self, path: str, body: dict[str, Any]) -> None:
        s = self.server.session
        if path == "/api/place":
            obj, im = integer(body, "obj_id"), integer(body, "image_id")
            u, v = number(body, "u", MAX_PIXEL), number(body, "v", MAX_PIXEL)
            index = s.instance_at(im, u, v)  # a click off every mask is answered at once

            def place(progress: Progress) -> None:
                s.place(obj, im, u, v, progress)

            return self._job("place", index, place)
        if path == "/api/refine":
            index = integer(body, "instance")

            def polish(progress: Progress) -> None:
                s.refine_from_here(index, progress)

            return self._job("refine", index, polish)
        if path == "/api/refine_all":
            return self._job("refine together", None, s.refine_together)
        if path == "/api/export":
            def export(progress: Progress) -> None:
                export_session(s, progress)

            return self._job("export", None, export)
        if path == "/api/nudge":
            s.nudge(integer(body, "instance"), integer(body, "image_id"), vector3(body, "move_mm", MAX_MOVE_MM),
                    vector3(body, "turn_deg", MAX_TURN_DEG))
        elif path == "/api/decide":
            s.decide(integer(body, "instance"), text(body, "decision"))
        elif path == "/api/undo":
            s.undo(integer(body, "instance"))
        elif path == "/api/focus":
            s.focus_on(integer(body, "instance"))
        elif path == "/api/symmetric":
            s.mark_symmetric(integer(body, "instance"), flag(body, "symmetric"))
        else:
            return self._error(HTTPStatus.NOT_FOUND, f"{path}: no such action")
        self._json({"revision": s.revision})

    def _job(self, kind: str, index: int | None, work: Any) -> None:
        s = self.server.session
        if not s.start_job(kind, index, work):
            return self._error(HTTPStatus.CONFLICT, f"busy with {s.job.kind}; wait for it to finish")
        self._json({"job": s.job.number}, HTTPStatus.ACCEPTED)


def json_object(raw: bytes) -> dict[str, Any]:
    """A request body as a JSON object (``{}`` if empty); raises :class:`AutoalignError` (a 400) if it is not one."""
    try:
        body = json.loads(raw or b"{}", parse_constant=_not_json)
    except RecursionError:  # the decoder recurses per level: 100,000 nested lists would end the handler
        raise AutoalignError("the request body must be a JSON object, not nested this deeply") from None
    except ValueError:
        body = None
    if not isinstance(body, dict):
        raise AutoalignError("the request body must be a JSON object")
    return body


def _not_json(name: str) -> Any:
    """``json.loads``'s hook for ``NaN``, ``Infinity`` and ``-Infinity``, which JSON does not have."""
    raise ValueError(f"{name} is not a JSON number")


def export_session(session: Any, progress: Any = None) -> Path:
    """The page's "Export": the accepted labels to ``OUT_DIR/scene_gt.json`` (with the decisions in
    ``labels.json``), then ``autoalign export`` of them into ``OUT_DIR/bop`` (all or none). As with
    ``autoalign export``, an earlier export there is replaced as a whole (no mask or photo of a larger
    one is left behind), and a non-empty ``bop/`` without ``export.json`` is refused before anything
    is written."""
    from autoalign.io.atomic_files import write_files_atomic
    from autoalign.io.export import cameras_to_export, export_dataset
    from autoalign.io.out_folder import check_replaceable, replace_folder

    out = session.out_dir
    labels_path = out / "scene_gt.json"
    labels = session.accepted_labels()
    check_replaceable(out / "bop", "export.json")  # before anything is written or rendered
    out.mkdir(parents=True, exist_ok=True)
    write_files_atomic({labels_path: json.dumps(labels, indent=1).encode(),
                        out / "labels.json": json.dumps(session.state.decisions(), indent=1).encode()})
    cameras = cameras_to_export(session.scene_dir, labels_path, None)
    dataset = export_dataset(session.scene_dir, labels_path, session.models, cameras, progress=progress)
    replace_folder(out / "bop", dataset.files, marker="export.json")
    print(f"autoalign label: exported {dataset.entries} entries in {dataset.images} images to {out / 'bop'}",
          file=sys.stdout, flush=True)
    return out / "bop"
