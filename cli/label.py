"""``autoalign label``: a local web page to place, check and correct every object of a scene, then
export it as a BOP dataset.

Start-up imports only the standard library and :mod:`autoalign.errors`; the rest loads inside
:func:`run_label`.
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import TYPE_CHECKING, Any

from autoalign.errors import AutoalignError

if TYPE_CHECKING:
    from autoalign.label.lock import SessionLock

_DESCRIPTION = """\
Open a local web page to label the objects of a scene by hand and by autoalign together: choose
an object, click it in any view, and autoalign places and refines it; its outline appears in every
view. Per instance the page shows autoalign's verdict, sigma and worst views; move or turn it with
the keys (or drag it in the 3D view), refine from there, and accept, reject or mark it symmetric.
"Export" writes the accepted labels as a BOP scene folder, exactly as 'autoalign export' would.
The session is saved after every change (OUT_DIR/session.json) and comes back when the page or
the server restarts."""

_EPILOG = """\
inputs:
  SCENE_DIR                    a BOP scene folder: scene_camera.json, mask_visib/{im:06d}_{k:06d}.png
                               instance masks with the same k for one object in every view (a
                               segmenter's, or 'autoalign recon --propose'), rgb/ photos (optional),
                               cloud.ply from 'autoalign recon' (optional, shown in 3D)
  --models MODELS_DIR          obj_{obj_id:06d}.ply (mm) and models_info.json

outputs (OUT_DIR, default SCENE_DIR/label_session):
  session.json                 every instance: object, pose (world from model, mm), decision,
                               verdict (rewritten after every change, atomically)
  scene_gt.json, labels.json   on Export: the accepted labels (BOP) and the decisions and verdicts
  bop/                         on Export: the BOP scene folder ('autoalign export' of scene_gt.json)
                               (an earlier export there is replaced as a whole)
  label.lock                   while the server runs (its pid, host and URL): a second server on the
                               same OUT_DIR is refused (exit status 2); one left by a killed server
                               is taken over

keys on the page (the selected instance, in the axes of the view last clicked or hovered):
  arrows move 1 mm in the image plane, PageUp/PageDown along the view, q/e w/s a/d turn 1 degree
  about the view's z / x / y axis; with Shift 5x; r refine from here, Ctrl+Z undo the last move,
  Enter accept, Delete reject

The server listens on 127.0.0.1 only (a free port unless --port), serves files from the scene and
models folders only, and takes changes from its own page only (a token drawn at its start). Stop it
with Ctrl-C (exit status 130); nothing accepted is lost."""


def add_label_parser(subparsers: Any) -> argparse.ArgumentParser:
    """Register ``autoalign label`` on an argparse subparsers object."""
    from autoalign.cli.common import HelpFormatter
    from autoalign.jobs.refine_arguments import add_units_argument

    p = subparsers.add_parser("label", help="a local web page to place, check and correct objects, then export",
                              description=_DESCRIPTION, epilog=_EPILOG, formatter_class=HelpFormatter)
    p.add_argument("scene", metavar="SCENE_DIR", help="BOP scene folder with scene_camera.json and mask_visib/")
    req = p.add_argument_group("required")
    req.add_argument("--models", metavar="MODELS_DIR", required=True, help="BOP models folder (obj_XXXXXX.ply, mm)")
    opt = p.add_argument_group("options")
    opt.add_argument("--out", metavar="OUT_DIR", default=None,
                     help="where the session and the export go (default: SCENE_DIR/label_session)")
    opt.add_argument("--instances", metavar="INSTANCES_JSON", default=None,
                     help='which object each instance is, to suggest it ({"instances": {"0": 5}})')
    add_units_argument(opt)
    opt.add_argument("--port", type=int, default=0, help="port of the page (default: a free one)")
    opt.add_argument("--no-browser", action="store_true", help="print the address instead of opening a browser")
    opt.add_argument("--no-3d", action="store_true", help="no 3D view (viser)")
    p.set_defaults(func=run_label)
    return p


def run_label(args: argparse.Namespace) -> int:
    """``autoalign label``: see ``autoalign label --help``."""
    from autoalign.runtime.interrupts import preload

    preload("numpy", "cv2", "trimesh")  # extension modules, with Ctrl-C deferred
    from autoalign.io.bop import check_scene_dir
    from autoalign.io.out_folder import check_outputs_spare_inputs
    from autoalign.jobs.job import OUTPUT_FILES
    from autoalign.label.lock import SessionLock
    from autoalign.runtime.backend import device

    if device() != "cpu":  # the page renders from its request threads, which drjit's CUDA backend refuses
        raise AutoalignError(f"AUTOALIGN_DEVICE={device()}: the label page renders on the CPU; unset "
                             "AUTOALIGN_DEVICE for `autoalign label`")
    scene = check_scene_dir(args.scene)
    out = Path(args.out) if args.out else scene / "label_session"
    check_outputs_spare_inputs(out, scene, [Path(args.instances)] if args.instances else [], OUTPUT_FILES)
    if not 0 <= args.port < 65536:
        raise AutoalignError(f"--port {args.port}: a port is 0 (any free one) to 65535")
    lock = SessionLock.acquire(out)  # before the session is read: a second server on it changes nothing
    try:
        return _serve(args, scene, out, lock)
    finally:
        lock.release()


def _serve(args: argparse.Namespace, scene: Path, out: Path, lock: SessionLock) -> int:
    """Read the session of ``out`` (locked by ``lock``) and serve its page until Ctrl-C."""
    from autoalign.cli.common import warn
    from autoalign.cli.label_http import LabelServer
    from autoalign.io.models import ModelSet
    from autoalign.label.session import LabelSession

    models = ModelSet.read(args.models, args.units)
    from autoalign.runtime.backend import mitsuba

    mitsuba()  # the renderer loads here, on the main thread (Ctrl-C safe), not on the first click
    session = LabelSession(scene, models, out, Path(args.instances) if args.instances else None)
    viewer = None
    if not args.no_3d:
        try:
            from autoalign.cli.label_3d import SceneViewer
        except ImportError:
            warn("no 3D view: viser is not installed (pip install 'autoalign[label]'); the page works without it")
        else:
            viewer = SceneViewer(session)
    try:
        server = LabelServer(session, args.port, viewer.url if viewer else None)
    except OSError as exc:
        if viewer is not None:
            viewer.stop()
        raise AutoalignError(f"--port {args.port}: cannot listen there ({exc.strerror or exc}); choose another "
                             "port or leave --port out") from None
    lock.announce(server.url)
    print(f"autoalign label: {server.url}  ({len(session.instances)} instances in {len(session.image_ids)} views; "
          f"session in {session.session_path}; Ctrl-C stops)", flush=True)
    if not args.no_browser:
        import webbrowser

        webbrowser.open(server.url)
    try:
        server.serve_forever(poll_interval=0.2)
    finally:
        server.server_close()
        if viewer is not None:
            viewer.stop()
    return 0
