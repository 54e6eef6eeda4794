"""``autoalign recon``: camera poses, metric scale, table frame and fused cloud from a capture,
written as a BOP scene folder.

Start-up imports only the standard library and :mod:`autoalign.errors`; pycolmap, open3d and the
rest load inside :func:`run_recon`. Its helpers come from
:mod:`autoalign.cli.common` (:mod:`autoalign.cli.main` registers this module, never the other way round).
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from autoalign.errors import AutoalignError
from autoalign.runtime.interrupts import Interrupts, preload

_DESCRIPTION = """\
Reconstruct the cameras of a capture (a folder of frames or a video file, optionally with aligned
depth) and write a BOP scene folder for 'autoalign refine' and 'autoalign export': structure from
motion with pycolmap (SIFT features, exhaustive matching up to 120 frames and sequential beyond,
incremental mapping; intrinsics given or estimated), the metric scale from depth (the median
ratio of sensor depth to reconstructed depth at the keypoints), the table plane by RANSAC (the
world frame gets z up and the table at z = 0), and, with depth, TSDF fusion (open3d) into a
coloured cloud. With depth, --propose also proposes the object instances: the fused surface above
the table clustered (open3d DBSCAN), each cluster's visible mask in every view with the same id,
so that no segmenter is needed. Without depth the scale is unknown: the cameras are written in
the reconstruction's own unit, recon.json says so (then 'autoalign refine' solves the scale from
the objects' known size), and the command exits 3."""

_EPILOG = """\
inputs:
  CAPTURE                      a folder of frames (or its rgb/ subfolder), sorted by name; or a
                               video file OpenCV can read (--every N keeps every N-th frame)
  --depth DEPTH_DIR            16-bit depth PNGs named as the frames, registered to the colour
                               camera (default: CAPTURE/depth if it exists); --depth-scale S: a
                               depth value times S is mm (default 1)
  --intrinsics K_JSON          {"cam_K": 9 numbers} or {"fx", "fy", "cx", "cy"} in px, OpenCV
                               convention (the centre of the top-left pixel at 0,0); without it
                               a pinhole camera is estimated

outputs (in OUT_DIR, written all or none):
  scene_camera.json            per registered frame: cam_K, cam_R_w2c, cam_t_w2c (mm with depth),
                               depth_scale; image id = the frame's number
  rgb/, depth/                 the registered frames, named {im_id:06d}
  cloud.ply                    fused cloud (with depth) or the triangulated points, world frame
  mesh.ply                     the fused surface (with depth)
  recon.json                   frames registered, reprojection error, scale and its spread, plane
  trajectory.png               the camera path over the cloud, from above and from the side
  mask_visib/, proposals.json  with --propose: instance k's visible mask {im_id:06d}_{k:06d}.png,
                               and its centre and size (mm); map k to an obj_id in an instances
                               file for 'autoalign refine --instances'

examples:
  autoalign recon capture/ --intrinsics capture/intrinsics.json --depth-scale 0.1 --out scenes/000001
  autoalign recon video.mp4 --every 5 --out scenes/000002

exit status: 0 reconstructed with metric scale, 3 reconstructed without it (no depth), 2 a
mistake in the command or the inputs (nothing written)."""

SCALE_SPREAD_WARN = 0.02
"""A depth-to-reconstruction ratio spread above this (relative) is reported as doubtful."""


def add_recon_parser(subparsers: Any) -> argparse.ArgumentParser:
    """Register ``autoalign recon`` on an argparse subparsers object."""
    from autoalign.cli.common import HelpFormatter
    from autoalign.jobs.refine_arguments import positive_int

    p = subparsers.add_parser("recon", help="camera poses, scale, table frame and cloud from a capture (a BOP scene)",
                              description=_DESCRIPTION, epilog=_EPILOG, formatter_class=HelpFormatter)
    p.add_argument("capture", metavar="CAPTURE", help="folder of frames, or a video file")
    p.add_argument("--out", metavar="OUT_DIR", required=True, help="the BOP scene folder to write (not CAPTURE)")
    p.add_argument("--depth", metavar="DEPTH_DIR", default=None, help="aligned depth PNGs named as the frames")
    p.add_argument("--depth-scale", metavar="S", type=float, default=1.0, help="depth value times S is mm (default 1)")
    p.add_argument("--intrinsics", metavar="K_JSON", default=None, help="camera intrinsics (see 'inputs')")
    p.add_argument("--every", metavar="N", type=positive_int, default=1, help="keep every N-th frame (default 1)")
    p.add_argument("--propose", action="store_true",
                   help="with depth: propose the object instances on the table and write their masks")
    p.add_argument("--quiet", action="store_true", help="no progress bar or summary")
    p.set_defaults(func=run_recon)
    return p


def run_recon(args: argparse.Namespace) -> int:
    """``autoalign recon``: see ``autoalign recon --help``."""
    import importlib.util


    if importlib.util.find_spec("pycolmap") is None:
        raise AutoalignError("autoalign recon needs pycolmap; install it with: pip install 'autoalign[recon]'")
    preload("numpy", "cv2", "open3d", "pycolmap")  # extension modules, with Ctrl-C deferred
    from autoalign.cli.common import EXIT_FLAGGED, ProgressBar, warn
    from autoalign.io.out_folder import write_folder
    from autoalign.recon.capture import read_capture
    from autoalign.recon.pipeline import reconstruct, scene_files

    t0 = time.perf_counter()
    capture_path, out = Path(args.capture), Path(args.out)
    if not 0 < args.depth_scale < float("inf"):  # nan too
        raise AutoalignError(f"--depth-scale {args.depth_scale}: must be positive (a depth value times it is mm)")
    if out.resolve() == capture_path.resolve() or (capture_path.is_dir() and capture_path.resolve() in out.resolve().parents):
        raise AutoalignError(f"--out {out}: is inside the capture; choose a folder outside it")
    with tempfile.TemporaryDirectory(prefix="autoalign-recon-") as tmp:
        capture = read_capture(capture_path, Path(tmp), args.depth, args.depth_scale, args.intrinsics, args.every)
        if args.propose and capture.depth is None:
            raise AutoalignError(f"{capture_path}: --propose needs depth (a depth/ folder or --depth DEPTH_DIR); "
                                 "without it, give masks from a segmenter")
        bar = ProgressBar(enabled=not args.quiet)
        try:
            rec = reconstruct(capture, Path(tmp), progress=bar, propose=args.propose)
        finally:
            bar.close()
        files = scene_files(rec)
    write_folder(out, files)
    Interrupts.outputs_written()
    report = json.loads(files["recon.json"])
    if not args.quiet:
        scale = (f"scale {report['scale_mm_per_unit']:.4g} mm/unit (spread {report['scale_spread']:.2%})"
                 if report["metric"] else "scale unknown")
        print(f"{report['registered']} of {report['frames']} frames registered, reprojection "
              f"{report['reprojection_error_px']:.2f} px, {scale}, table inliers {report['table']['inliers']:.0%}, "
              f"{time.perf_counter() - t0:.1f} s; wrote {out}", file=sys.stdout, flush=True)
    flagged = False
    if not report["metric"]:
        warn("no depth, so the scale is unknown: the cameras are in the reconstruction's own unit, not mm; "
             "'autoalign refine' solves it from the objects' known size (recon.json says so), or give --depth")
        flagged = True
    elif report["scale_spread"] > SCALE_SPREAD_WARN:
        warn(f"the depth and the reconstruction disagree: the scale's spread is {report['scale_spread']:.1%} "
             "(depth not registered to the colour camera, or a wrong --depth-scale?)")
        flagged = True
    if args.propose and not report["proposals"]:
        warn("--propose found nothing standing on the table (clusters of fused points above it); check the "
             "table plane in trajectory.png")
        flagged = True
    if report["registered"] < report["frames"]:
        warn(f"{report['frames'] - report['registered']} frame(s) could not be registered and were left out: "
             + ", ".join(map(str, report["not_registered"][:20])))
    return EXIT_FLAGGED if flagged else 0
