"""A fixed set of 44 procedural object meshes (millimetres, BOP conventions) for simulated studies.

Every model is built from trimesh primitives, revolved profiles and gridded boxes, concatenated
without boolean operations (overlapping parts are fine; meshes need not be watertight). Each
is translated so its axis-aligned bounding-box centre is the model origin (BOP). 32 models are
truly asymmetric under proper rotations (an off-centre handle, knob, tab, bent tip, noise...)
and carry ``symmetry == "none"``; the other 12 list their symmetries the BOP ``models_info``
way: ``symmetries_discrete`` as 4x4 model-frame transforms (identity excluded, all group
elements listed) and ``symmetries_continuous`` as ``{"axis": [...], "offset": [...]}``.

Generation is deterministic (fixed seeds) and takes well under a second for the whole set.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import trimesh
from numpy.typing import ArrayLike, NDArray

__all__ = ["ProceduralModel", "procedural_models", "write_models", "load_bop_models_info",
           "models_info_entry"]


@dataclass
class ProceduralModel:
    """One procedural object.

    Attributes:
        name: short descriptive label.
        mesh: the triangle mesh in the model frame (mm), origin at its bounding-box centre.
        symmetry: ``"none"`` or a human-readable description of the rotational symmetries.
        symmetries_discrete: model-frame 4x4 transforms mapping the object onto itself
            (identity excluded), BOP style.
        symmetries_continuous: BOP ``{"axis": [x, y, z], "offset": [x, y, z] (mm)}`` entries.
    """

    name: str
    mesh: trimesh.Trimesh
    symmetry: str = "none"
    symmetries_discrete: list[NDArray[np.float64]] = field(default_factory=list)
    symmetries_continuous: list[dict[str, list[float]]] = field(default_factory=list)


# --------------------------------------------------------------------------------------------
# Transform helpers
# --------------------------------------------------------------------------------------------

def _rot(axis: ArrayLike, deg: float) -> NDArray[np.float64]:
    """4x4 rotation by ``deg`` degrees about ``axis`` through the origin."""
    return trimesh.transformations.rotation_matrix(np.radians(deg), np.asarray(axis, dtype=np.float64))


def _tr(x: float = 0.0, y: float = 0.0, z: float = 0.0) -> NDArray[np.float64]:
    return trimesh.transformations.translation_matrix([x, y, z])


def _place(tm: trimesh.Trimesh, *transforms: NDArray[np.float64]) -> trimesh.Trimesh:
    """Apply transforms in order (first given is applied first)."""
    for T in transforms:
        tm.apply_transform(T)
    return tm


def _dihedral_z(n: int) -> list[NDArray[np.float64]]:
    """Non-identity elements of the dihedral group D_n about z (n-fold turns, n in-plane flips)."""
    out = [_rot([0, 0, 1], 360.0 * k / n) for k in range(1, n)]
    for m in range(n):
        a = np.radians(180.0 * m / n)
        out.append(_rot([np.cos(a), np.sin(a), 0.0], 180.0))
    return out


def _flips_xyz() -> list[NDArray[np.float64]]:
    return [_rot([1, 0, 0], 180.0), _rot([0, 1, 0], 180.0), _rot([0, 0, 1], 180.0)]


Z_AXIS = {"axis": [0.0, 0.0, 1.0], "offset": [0.0, 0.0, 0.0]}


# --------------------------------------------------------------------------------------------
# Part builders (all mm, outward-facing triangles)
# --------------------------------------------------------------------------------------------

def _oriented(tm: trimesh.Trimesh) -> trimesh.Trimesh:
    """Flip a closed part whose triangles face inwards."""
    if tm.is_watertight and tm.volume < 0:
        tm.invert()
    return tm


def grid_box(extents: Sequence[float], cell: float = 10.0, centre: Sequence[float] = (0, 0, 0)) -> trimesh.Trimesh:
    """A closed box whose faces are regular grids of about ``cell`` mm (vertex set symmetric)."""
    ext = np.asarray(extents, dtype=np.float64)
    div = np.maximum(1, np.ceil(ext / cell).astype(int))
    verts, faces, off = [], [], 0
    for a in range(3):
        b, c = (a + 1) % 3, (a + 2) % 3  # e_b x e_c = e_a
        u = np.linspace(-ext[b] / 2, ext[b] / 2, div[b] + 1)
        v = np.linspace(-ext[c] / 2, ext[c] / 2, div[c] + 1)
        U, Vv = np.meshgrid(u, v, indexing="ij")
        nu, nv = len(u), len(v)
        idx = np.arange(nu * nv).reshape(nu, nv)
        q = np.stack([idx[:-1, :-1], idx[1:, :-1], idx[1:, 1:], idx[:-1, 1:]], axis=-1).reshape(-1, 4)
        tri = np.concatenate([q[:, [0, 1, 2]], q[:, [0, 2, 3]]])
        for s in (1.0, -1.0):
            P = np.zeros((nu * nv, 3))
            P[:, a] = s * ext[a] / 2
            P[:, b] = U.ravel()
            P[:, c] = Vv.ravel()
            verts.append(P)
            faces.append((tri if s > 0 else tri[:, ::-1]) + off)
            off += len(P)
    tm = trimesh.Trimesh(np.concatenate(verts) + np.asarray(centre, dtype=np.float64), np.concatenate(faces))
    return _oriented(tm)


def revolved(profile: ArrayLike, sections: int = 48, angle_deg: float | None = None) -> trimesh.Trimesh:
    """Revolve an ``(r, z)`` profile (mm) about the z axis; sections start at angle 0 (+x)."""
    ang = None if angle_deg is None else np.radians(angle_deg)
    return _oriented(trimesh.creation.revolve(np.asarray(profile, dtype=np.float64), angle=ang, sections=sections))


def _wall(r: float, z0: float, z1: float, n: int) -> list[tuple[float, float]]:
    """Profile points up a vertical wall at radius ``r`` in ``n`` segments (end points excluded)."""
    return [(r, z) for z in np.linspace(z0, z1, n + 1)[1:-1]]


def rod_profile(r: float, length: float, segments: int = 6) -> list[tuple[float, float]]:
    """Closed-at-axis profile of a solid cylinder centred on the origin."""
    h = length / 2
    return [(0.0, -h), (r, -h), *_wall(r, -h, h, segments), (r, h), (0.0, h)]


def ring_profile(r_in: float, r_out: float, z0: float, z1: float, segments: int = 1) -> list[tuple[float, float]]:
    """Closed counter-clockwise rectangle profile of an annulus / tube."""
    return [(r_in, z0), (r_out, z0), *_wall(r_out, z0, z1, segments), (r_out, z1), (r_in, z1),
            *_wall(r_in, z1, z0, segments), (r_in, z0)]


def cup_profile(r: float, h: float, wall: float, bottom: float, segments: int = 3) -> list[tuple[float, float]]:
    """Open-top cup (solid wall and bottom), closed at the axis."""
    return [(0.0, 0.0), (r, 0.0), *_wall(r, 0.0, h, segments), (r, h), (r - wall, h),
            *_wall(r - wall, h, bottom, segments), (r - wall, bottom), (0.0, bottom)]


def cyl(r: float, p0: Sequence[float], p1: Sequence[float], sections: int = 32) -> trimesh.Trimesh:
    """Solid cylinder of radius ``r`` from point ``p0`` to ``p1`` (mm)."""
    return _oriented(trimesh.creation.cylinder(radius=r, segment=np.array([p0, p1], dtype=np.float64),
                                               sections=sections))


def ball(r: float, centre: Sequence[float], subdivisions: int = 2) -> trimesh.Trimesh:
    return trimesh.creation.icosphere(subdivisions=subdivisions, radius=r).apply_translation(centre)


def tube_arc(R: float, r: float, angle_deg: float, sections: int = 16, tube_sections: int = 12) -> trimesh.Trimesh:
    """Closed bent tube (flat end caps): a circle of radius ``r`` at distance ``R`` from the z axis
    swept ``angle_deg`` about z, centred on +x (symmetric about the xz-plane)."""
    phi = 2 * np.pi * np.arange(tube_sections) / tube_sections
    th = np.radians(np.linspace(-angle_deg / 2, angle_deg / 2, sections + 1))
    rad = R + r * np.cos(phi)
    V = np.concatenate([np.column_stack([rad * np.cos(t), rad * np.sin(t), r * np.sin(phi)]) for t in th])
    ends = np.array([[R * np.cos(th[0]), R * np.sin(th[0]), 0.0], [R * np.cos(th[-1]), R * np.sin(th[-1]), 0.0]])
    n, m = tube_sections, sections
    k = np.arange(n)
    k1 = (k + 1) % n
    F = []
    for s in range(m):
        a, b = s * n, (s + 1) * n
        F.append(np.column_stack([a + k, b + k, b + k1]))
        F.append(np.column_stack([a + k, b + k1, a + k1]))
    c0, c1 = len(V), len(V) + 1
    F.append(np.column_stack([np.full(n, c0), k, k1]))
    F.append(np.column_stack([np.full(n, c1), m * n + k1, m * n + k]))
    return _oriented(trimesh.Trimesh(np.concatenate([V, ends]), np.concatenate(F)))


def star_prism(radii: ArrayLike, angles_deg: ArrayLike, z0: float, z1: float, nz: int = 1) -> trimesh.Trimesh:
    """Closed prism over a polygon that is star-shaped about the origin (counter-clockwise)."""
    r = np.asarray(radii, dtype=np.float64)
    a = np.radians(np.asarray(angles_deg, dtype=np.float64))
    P = np.column_stack([r * np.cos(a), r * np.sin(a)])
    n = len(P)
    zs = np.linspace(z0, z1, nz + 1)
    V = [np.column_stack([P, np.full(n, z)]) for z in zs]
    V.append(np.array([[0.0, 0.0, z0], [0.0, 0.0, z1]]))
    V = np.concatenate(V)
    cb, ct = len(V) - 2, len(V) - 1
    F = []
    k = np.arange(n)
    k1 = (k + 1) % n
    for lvl in range(nz):
        lo, hi = lvl * n, (lvl + 1) * n
        F.append(np.column_stack([lo + k, lo + k1, hi + k1]))
        F.append(np.column_stack([lo + k, hi + k1, hi + k]))
    top = nz * n
    F.append(np.column_stack([np.full(n, ct), top + k, top + k1]))
    F.append(np.column_stack([np.full(n, cb), k1, k]))
    return _oriented(trimesh.Trimesh(V, np.concatenate(F)))


def gear_outline(teeth: int, r_tip: float, r_root: float, tip_half_deg: float,
                 root_half_deg: float) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """(radii, angles in degrees) of a gear outline with teeth centred at 0, 360/teeth, ..."""
    pitch = 360.0 / teeth
    radii, angles = [], []
    for t in range(teeth):
        c = t * pitch
        for da, rr in ((-(pitch / 2 - root_half_deg), r_root), (-tip_half_deg, r_tip),
                       (tip_half_deg, r_tip), (pitch / 2 - root_half_deg, r_root)):
            angles.append(c + da)
            radii.append(rr)
    return np.array(radii), np.array(angles)


def blob(axes: Sequence[float], seed: int, amp: float = 0.12, terms: int = 5) -> trimesh.Trimesh:
    """A smooth random lump: an icosphere (1280 faces) with low-frequency radial noise, scaled to
    roughly ``axes`` (mm, full lengths)."""
    rng = np.random.default_rng(seed)
    ico = trimesh.creation.icosphere(subdivisions=3, radius=1.0)
    v = np.asarray(ico.vertices)
    rad = np.ones(len(v))
    for _ in range(terms):
        d = rng.standard_normal(3)
        d /= np.linalg.norm(d)
        rad += amp * rng.uniform(0.4, 1.0) * np.sin(rng.uniform(1.5, 3.5) * (v @ d) + rng.uniform(0, 2 * np.pi))
    v = v * rad[:, None] * (np.asarray(axes, dtype=np.float64) / 2.0)
    return _oriented(trimesh.Trimesh(v, ico.faces))


def _finish(parts: Sequence[trimesh.Trimesh]) -> trimesh.Trimesh:
    """Clean each part (merge its duplicate vertices, drop degenerate/duplicate faces), then
    concatenate the parts without merging across them (so every closed part stays a closed
    2-manifold even where parts touch) and centre the bounding box at the origin."""
    V, F, off = [], [], 0
    for p in parts:
        tm = trimesh.Trimesh(np.asarray(p.vertices), np.asarray(p.faces), process=True)
        tm.update_faces(tm.nondegenerate_faces())
        tm.update_faces(tm.unique_faces())
        tm.remove_unreferenced_vertices()
        V.append(np.asarray(tm.vertices))
        F.append(np.asarray(tm.faces) + off)
        off += len(tm.vertices)
    V = np.concatenate(V)
    V = V - (V.min(axis=0) + V.max(axis=0)) / 2.0
    return trimesh.Trimesh(V, np.concatenate(F), process=False)


# --------------------------------------------------------------------------------------------
# Symmetric models (12)
# --------------------------------------------------------------------------------------------

def _box_plain():
    return [grid_box((120, 80, 50))]


def _square_block():
    return [grid_box((70, 70, 110), cell=12)]


def _can_plain():
    return [revolved(rod_profile(33, 115, segments=4), sections=64)]


def _washer():
    return [revolved(ring_profile(20, 45, -5, 5), sections=64)]


def _bottle_plain():
    prof = [(0, -85), (31, -85), (34, -82), *_wall(34, -82, 20, 4), (34, 20), (30, 40), (22, 52), (14, 60),
            (12, 64), (12, 78), (13.5, 79), (13.5, 85), (0, 85)]
    return [revolved(prof, sections=48)]


def _bowl():
    prof = [(0, 0), (35, 0), (36, 3), (55, 15), (66, 35), (70, 48), (66, 48), (62, 36), (52, 19), (33, 7), (0, 7)]
    return [revolved(prof, sections=48)]


def _hex_bar():
    prof = [(0, -45), (12, -45), (24, -45), (35, -45), *_wall(35, -45, 45, 18), (35, 45), (24, 45), (12, 45), (0, 45)]
    return [revolved(prof, sections=6)]


def _gear_plain():
    r, a = gear_outline(10, 45, 37, 7.0, 8.0)
    return [star_prism(r, a, -7.5, 7.5, nz=2), revolved(rod_profile(15, 30, segments=2), sections=40)]


def _pipe():
    return [revolved(ring_profile(20, 25, -70, 70, segments=4), sections=64)]


def _plate_rect():
    return [grid_box((150, 90, 4))]


def _rod():
    return [revolved(rod_profile(6, 150, segments=6), sections=32)]


def _u_channel_plain():
    return [grid_box((140, 60, 5), centre=(0, 0, 2.5)),
            grid_box((140, 5, 40), centre=(0, 27.5, 20)),
            grid_box((140, 5, 40), centre=(0, -27.5, 20))]


# --------------------------------------------------------------------------------------------
# Asymmetric models (32)
# --------------------------------------------------------------------------------------------

def _box_knob():
    return [grid_box((110, 70, 45)), cyl(8, (30, 15, 20), (30, 15, 35))]


def _box_tab():
    return [grid_box((90, 60, 60)), grid_box((28, 20, 6), cell=7, centre=(57, 15, 20))]


def _stepped_block():
    return [grid_box((120, 60, 30), centre=(0, 0, 15)), grid_box((50, 60, 40), centre=(-35, 0, 50)),
            cyl(6, (30, 15, 28), (30, 15, 40))]


def _l_bracket():
    return [grid_box((70, 60, 5), cell=8, centre=(35, 0, 2.5)), grid_box((5, 60, 90), cell=8, centre=(2.5, 0, 45)),
            grid_box((22, 4, 22), cell=6, centre=(14, 24, 14))]


def _t_bracket():
    return [grid_box((70, 100, 6), cell=8, centre=(0, 0, 63)), grid_box((70, 6, 62), cell=8, centre=(0, 20, 31))]


def _z_bracket():
    return [grid_box((55, 50, 5), cell=8, centre=(27.5, 0, 2.5)), grid_box((5, 50, 70), cell=8, centre=(2.5, 0, 35)),
            grid_box((30, 50, 5), cell=8, centre=(-10, 0, 67.5))]


def _mug_parts(r, h, handle_R, handle_r, handle_z, wall=4.0, bottom=6.0):
    body = revolved(cup_profile(r, h, wall, bottom), sections=48)
    handle = _place(tube_arc(handle_R, handle_r, 180.0), _rot([1, 0, 0], 90.0), _tr(r - 2.0, 0, handle_z))
    return [body, handle]


def _mug():
    return _mug_parts(40, 95, 24, 6, 50)


def _travel_mug():
    parts = _mug_parts(35, 140, 20, 5.5, 85)
    lid = revolved([(0, 140), (37, 140), (37, 150), (0, 150)], sections=48)
    spout = cyl(5, (22, 0, 148), (22, 0, 156), sections=16)
    return parts + [lid, spout]


def _pitcher():
    prof = [(0, 0), (45, 0), (48, 10), (48, 60), (42, 100), (42, 120), (38, 120), (38, 100), (44, 60), (44, 10),
            (40, 5), (0, 5)]
    body = revolved(prof, sections=48)
    handle = _place(tube_arc(30, 6, 180.0), _rot([1, 0, 0], 90.0), _tr(40, 0, 70))
    spout = cyl(7, (-36, 0, 108), (-62, 0, 124), sections=16)
    return [body, handle, spout]


def _kettle():
    body = revolved([(0, 0), (60, 0), (65, 25), (60, 55), (40, 75), (0, 78)], sections=48)
    spout = cyl(7, (-50, 0, 25), (-88, 0, 70), sections=16)
    bail = _place(tube_arc(38, 5, 180.0), _rot([1, 0, 0], 90.0), _rot([0, 1, 0], -90.0), _tr(0, 0, 68))
    knob = ball(7, (12, 0, 80))
    return [body, spout, bail, knob]


def _spray_bottle():
    body = revolved([(0, 0), (30, 0), *_wall(30, 0, 100, 4), (30, 100), (14, 115), (14, 125), (0, 125)], sections=40)
    head = grid_box((40, 22, 26), cell=7, centre=(-10, 0, 138))
    nozzle = cyl(4, (-30, 0, 142), (-42, 0, 142), sections=12)
    trigger = grid_box((8, 10, 30), cell=5, centre=(-26, 0, 118))
    return [body, head, nozzle, trigger]


def _oil_can():
    can = revolved(rod_profile(33, 110, segments=4), sections=48)
    rim = revolved(ring_profile(28, 33, 53, 58), sections=48)
    spout = cyl(7, (17, 0, 50), (17, 0, 72), sections=20)
    cap = cyl(9, (17, 0, 72), (17, 0, 78), sections=20)
    return [can, rim, spout, cap]


def _blob_a():
    return [blob((100, 75, 60), seed=11)]


def _blob_b():
    return [blob((130, 70, 55), seed=22)]


def _blob_c():
    return [blob((75, 70, 110), seed=33, amp=0.15)]


def _blob_d():
    return [blob((90, 90, 70), seed=44, amp=0.18, terms=7)]


def _plate_boss():
    return [grid_box((120, 80, 5), cell=10, centre=(0, 0, 2.5)), cyl(10, (35, 20, 4), (35, 20, 20)),
            grid_box((60, 5, 10), cell=6, centre=(-20, -25, 9))]


def _rod_bent():
    tip = np.array([0.0, 0.0, 60.0]) + 40.0 * np.array([np.sin(np.radians(50)), 0.0, np.cos(np.radians(50))])
    return [revolved(rod_profile(6, 120, segments=6), sections=32), ball(6, (0, 0, 60)),
            cyl(6, (0, 0, 60), tip, sections=32)]


def _wrench():
    handle = grid_box((110, 16, 5), cell=8)
    ring = _place(revolved(ring_profile(9, 18, -3, 3), sections=32), _tr(-65, 0, 0))
    jaw_base = grid_box((14, 36, 6), cell=6, centre=(60, 0, 0))
    prong_a = grid_box((22, 8, 6), cell=6, centre=(76, 14, 0))
    prong_b = grid_box((16, 8, 6), cell=6, centre=(73, -14, 0))
    return [handle, ring, jaw_base, prong_a, prong_b]


def _hammer():
    handle = revolved(rod_profile(12, 130, segments=6), sections=32)
    head = grid_box((60, 24, 24), cell=8, centre=(0, 0, 70))
    face = cyl(14, (30, 0, 70), (45, 0, 70))
    claw = _place(grid_box((35, 20, 8), cell=7), _rot([0, 1, 0], 20.0), _tr(-45, 0, 66))
    return [handle, head, face, claw]


def _pen():
    body = revolved([(0, -70), (1, -70), (3.5, -62), (6, -50), *_wall(6, -50, 70, 6), (6, 70), (0, 70)], sections=32)
    clip = grid_box((3, 4, 45), cell=3, centre=(8, 0, 45))
    bridge = grid_box((5, 4, 4), cell=2, centre=(6.5, 0, 66))
    return [body, clip, bridge]


def _ladle():
    bowl = revolved([(0, 0), (20, 2), (32, 12), (36, 30), (33, 30), (29, 14), (18, 5), (0, 3)], sections=40)
    handle = cyl(4.5, (34, 0, 29), (110, 0, 95), sections=16)
    hook = ball(6, (110, 0, 95))
    return [bowl, handle, hook]


def _flashlight():
    prof = [(0, 0), (15, 0), *_wall(15, 0, 110, 5), (15, 110), (22, 130), (22, 150), (0, 150)]
    body = revolved(prof, sections=40)
    switch = grid_box((10, 14, 8), cell=4, centre=(16, 0, 85))
    return [body, switch]


def _pipe_elbow():
    a = cyl(15, (0, 0, 0), (80, 0, 0))
    b = cyl(15, (0, 0, 0), (0, 0, 50))
    joint = ball(15, (0, 0, 0))
    flange = _place(revolved(ring_profile(10, 26, -3, 3), sections=32), _rot([0, 1, 0], 90.0), _tr(78, 0, 0))
    return [a, b, joint, flange]


def _pipe_tee():
    main = revolved(ring_profile(10, 14, -65, 65, segments=4), sections=32)
    main.apply_transform(_rot([0, 1, 0], 90.0))
    branch = cyl(10, (20, 0, 0), (20, 55, 0))
    return [main, branch]


def _j_hook():
    stem = cyl(5, (0, 0, 0), (0, 0, 100), sections=24)
    bend = _place(tube_arc(20, 5, 180.0), _rot([0, 0, 1], -90.0), _rot([1, 0, 0], 90.0), _tr(20, 0, 0))
    lip = cyl(5, (40, 0, 0), (40, 0, 28), sections=24)
    plate = grid_box((30, 8, 40), cell=6, centre=(0, -5, 95))
    return [stem, bend, lip, plate]


def _star_knob():
    n = 5
    ang = np.arange(2 * n) * 180.0 / n
    rad = np.where(np.arange(2 * n) % 2 == 0, 40.0, 18.0)
    star = star_prism(rad, ang, 0, 16, nz=2)
    stem = cyl(8, (0, 0, -30), (0, 0, 0))
    pin = cyl(3, (30, 0, 15), (30, 0, 22), sections=12)
    return [star, stem, pin]


def _gear_keyed():
    r, a = gear_outline(12, 42, 35, 5.0, 6.0)
    return [star_prism(r, a, -6, 6, nz=2), cyl(14, (0, 0, 5), (0, 0, 25), sections=36),
            cyl(3, (24, 8, 5), (24, 8, 14), sections=12), grid_box((6, 4, 20), cell=3, centre=(14, 0, 15))]


def _hollow_frame():
    return [grid_box((120, 15, 8), centre=(0, 42.5, 0)), grid_box((120, 25, 8), centre=(0, -37.5, 0)),
            grid_box((15, 100, 8), centre=(52.5, 0, 0)), grid_box((15, 100, 8), centre=(-52.5, 0, 0)),
            grid_box((20, 20, 6), cell=5, centre=(55, 45, 7))]


def _toy_car():
    parts = [grid_box((120, 55, 30), centre=(0, 0, 25)), grid_box((55, 50, 25), centre=(-15, 0, 52))]
    for x in (-38, 38):
        for y in (-30, 30):
            parts.append(cyl(13, (x, y - 5, 13), (x, y + 5, 13), sections=24))
    return parts


def _camera_body():
    return [grid_box((110, 40, 65)), cyl(22, (25, 20, 0), (25, 55, 0), sections=40),
            cyl(6, (-35, 5, 32), (-35, 5, 40), sections=16), grid_box((30, 25, 14), cell=6, centre=(-5, 0, 38))]


def _pull_handle():
    bar = revolved(rod_profile(6, 128, segments=6), sections=24)
    bar.apply_transform(_rot([0, 1, 0], 90.0))
    posts = [cyl(5, (x, 0, 0), (x, 0, -30), sections=20) for x in (-50, 50)]
    cap = ball(9, (64, 0, 0))
    feet = [revolved(rod_profile(10, 4), sections=24).apply_translation((x, 0, -32)) for x in (-50, 50)]
    return [bar, *posts, cap, *feet]


# --------------------------------------------------------------------------------------------
# The set
# --------------------------------------------------------------------------------------------

_X, _Y = [1, 0, 0], [0, 1, 0]
# (name, builder, symmetry description, discrete symmetries factory, continuous symmetries)
_CATALOGUE: list[tuple[str, Callable[[], list[trimesh.Trimesh]], str,
                       Callable[[], list[NDArray[np.float64]]], list[dict[str, list[float]]]]] = [
    ("box_knob", _box_knob, "none", list, []),
    ("box_plain", _box_plain, "box: 180-degree turns about x, y and z", _flips_xyz, []),
    ("mug", _mug, "none", list, []),
    ("l_bracket", _l_bracket, "none", list, []),
    ("can_plain", _can_plain, "cylinder: continuous about z, 180-degree flip about x", lambda: [_rot(_X, 180)], [Z_AXIS]),
    ("blob_a", _blob_a, "none", list, []),
    ("t_bracket", _t_bracket, "none", list, []),
    ("box_tab", _box_tab, "none", list, []),
    ("bottle_plain", _bottle_plain, "bottle: continuous about z", list, [Z_AXIS]),
    ("hammer", _hammer, "none", list, []),
    ("z_bracket", _z_bracket, "none", list, []),
    ("gear_plain", _gear_plain, "10-tooth gear: dihedral D10 about z", lambda: _dihedral_z(10), []),
    ("travel_mug", _travel_mug, "none", list, []),
    ("stepped_block", _stepped_block, "none", list, []),
    ("blob_b", _blob_b, "none", list, []),
    ("washer", _washer, "washer: continuous about z, 180-degree flip about x", lambda: [_rot(_X, 180)], [Z_AXIS]),
    ("pitcher", _pitcher, "none", list, []),
    ("wrench", _wrench, "none", list, []),
    ("square_block", _square_block, "square prism: dihedral D4 about z", lambda: _dihedral_z(4), []),
    ("pen", _pen, "none", list, []),
    ("kettle", _kettle, "none", list, []),
    ("hex_bar", _hex_bar, "hexagonal prism: dihedral D6 about z", lambda: _dihedral_z(6), []),
    ("spray_bottle", _spray_bottle, "none", list, []),
    ("blob_c", _blob_c, "none", list, []),
    ("ladle", _ladle, "none", list, []),
    ("pipe", _pipe, "tube: continuous about z, 180-degree flip about x", lambda: [_rot(_X, 180)], [Z_AXIS]),
    ("oil_can", _oil_can, "none", list, []),
    ("plate_boss", _plate_boss, "none", list, []),
    ("flashlight", _flashlight, "none", list, []),
    ("plate_rect", _plate_rect, "plate: 180-degree turns about x, y and z", _flips_xyz, []),
    ("rod_bent", _rod_bent, "none", list, []),
    ("pipe_elbow", _pipe_elbow, "none", list, []),
    ("bowl", _bowl, "bowl: continuous about z", list, [Z_AXIS]),
    ("pipe_tee", _pipe_tee, "none", list, []),
    ("j_hook", _j_hook, "none", list, []),
    ("rod", _rod, "rod: continuous about z, 180-degree flip about x", lambda: [_rot(_X, 180)], [Z_AXIS]),
    ("star_knob", _star_knob, "none", list, []),
    ("gear_keyed", _gear_keyed, "none", list, []),
    ("u_channel_plain", _u_channel_plain, "U-channel: 180-degree turn about z", lambda: [_rot([0, 0, 1], 180)], []),
    ("hollow_frame", _hollow_frame, "none", list, []),
    ("blob_d", _blob_d, "none", list, []),
    ("toy_car", _toy_car, "none", list, []),
    ("camera_body", _camera_body, "none", list, []),
    ("pull_handle", _pull_handle, "none", list, []),
]

PROCEDURAL_COUNT = len(_CATALOGUE)
"""How many procedural models there are (BOP object ids 1 to this)."""


def procedural_models() -> list[ProceduralModel]:
    """The 44 procedural models, in a fixed order (BOP object id = position + 1).

    Deterministic: every call returns identical geometry. Units mm, origin at the bbox centre.
    """
    out = []
    for name, build, sym, discrete, continuous in _CATALOGUE:
        out.append(ProceduralModel(name=name, mesh=_finish(build()), symmetry=sym,
                                   symmetries_discrete=[np.asarray(T, dtype=np.float64) for T in discrete()],
                                   symmetries_continuous=[dict(axis=list(c["axis"]), offset=list(c["offset"]))
                                                          for c in continuous]))
    return out


# --------------------------------------------------------------------------------------------
# BOP models folder
# --------------------------------------------------------------------------------------------

def models_info_entry(model: ProceduralModel) -> dict[str, Any]:
    """BOP ``models_info.json`` entry: diameter, bbox min/size (mm) and any symmetries."""
    from autoalign.geometry.mesh import mesh_from_trimesh

    V = np.asarray(model.mesh.vertices, dtype=np.float64)
    lo, hi = V.min(axis=0), V.max(axis=0)
    info: dict[str, Any] = {"diameter": float(mesh_from_trimesh(model.mesh, model.name).diameter),
                            "min_x": float(lo[0]), "min_y": float(lo[1]), "min_z": float(lo[2]),
                            "size_x": float(hi[0] - lo[0]), "size_y": float(hi[1] - lo[1]),
                            "size_z": float(hi[2] - lo[2])}
    if model.symmetries_discrete:
        info["symmetries_discrete"] = [[float(x) for x in np.asarray(T).ravel()] for T in model.symmetries_discrete]
    if model.symmetries_continuous:
        info["symmetries_continuous"] = [{"axis": [float(x) for x in c["axis"]],
                                          "offset": [float(x) for x in c["offset"]]}
                                         for c in model.symmetries_continuous]
    return info


def write_models(out_dir: str | Path, models: Sequence[ProceduralModel] | None = None) -> dict[int, dict[str, Any]]:
    """Write a BOP models folder: ``obj_{id:06d}.ply`` (ids from 1) and ``models_info.json``.

    Also writes ``models_names.json`` (id -> name, symmetry description). Returns the
    models_info content keyed by integer id.
    """
    from autoalign.io.atomic_files import write_json_atomic

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    models = procedural_models() if models is None else list(models)
    info, names = {}, {}
    for i, m in enumerate(models, start=1):
        m.mesh.export(str(out_dir / f"obj_{i:06d}.ply"))
        info[i] = models_info_entry(m)
        names[str(i)] = {"name": m.name, "symmetry": m.symmetry}
    write_json_atomic(out_dir / "models_info.json", {str(k): v for k, v in info.items()})
    write_json_atomic(out_dir / "models_names.json", names)
    return info


def load_bop_models_info(models_dir: str | Path) -> dict[int, dict[str, Any]]:
    """Read ``models_info.json`` from a BOP models folder (or the file itself), keyed by int id.

    Each entry keeps its JSON fields; ``symmetries_discrete`` becomes a list of 4x4 float arrays
    (translation in mm) and both symmetry keys are always present (empty lists when absent).
    """
    from autoalign.io.models import read_models_info

    p = Path(models_dir)
    if p.is_dir():
        p = p / "models_info.json"
    out = {}
    for k, v in read_models_info(p).items():  # checked: a malformed symmetry is a one-line error, not a traceback
        e = dict(v)
        e["symmetries_discrete"] = [np.asarray(T, dtype=np.float64).reshape(4, 4)
                                    for T in v.get("symmetries_discrete", [])]
        e["symmetries_continuous"] = [{"axis": list(c["axis"]), "offset": list(c.get("offset", [0.0, 0.0, 0.0]))}
                                      for c in v.get("symmetries_continuous", [])]
        out[int(k)] = e
    return out
