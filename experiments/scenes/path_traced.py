"""Photos path-traced with mitsuba (issue 45's test scenes): glass, frosted glass, polished and
brushed metal, and textured opaque objects on a textured table, lit by a procedural environment
(a sky with two bright windows), optionally in front of a mirror-like backdrop.

Materials (:data:`MATERIALS`), each a mitsuba BSDF:

* ``opaque``: ``diffuse``, coloured by a solid texture (:class:`~.photo_scene.TintedTexture`)
  evaluated at the vertices (a ``mesh_attribute``);
* ``glass``: ``dielectric``, index 1.5; ``frosted``: ``roughdielectric``, GGX alpha 0.12;
* ``metal``: ``conductor`` (aluminium); ``brushed``: ``roughconductor`` (aluminium, alpha 0.08).

The sensor is mitsuba's ``perspective`` camera set from a :class:`~autoalign.geometry.camera.Camera`
(:func:`mitsuba_sensor`): mitsuba's camera frame is x left, y up, z forward, OpenCV's x right,
y down, z forward; its film's pixel ``(row i, col j)`` covers ``[j, j+1) x [i, i+1)``, as the
internal convention does, and its principal point is moved from the film's centre by
``principal_point_offset`` (a fraction of the film, added to the sample position). Square pixels
only. :func:`coverage_images` renders each object's pixel coverage through the same sensor,
which the tests compare with open3d's ray-cast masks.

World frame: z up, the table top at z = 0 (as :mod:`~.photo_scene`).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from autoalign.geometry.camera import Camera
from autoalign.geometry.mesh import Mesh
from autoalign.runtime.backend import mitsuba

MATERIALS = ("opaque", "glass", "frosted", "metal", "brushed")
"""What :func:`path_traced_photos` can make an object of."""
SEE_THROUGH = ("glass", "frosted")
"""Materials a depth sensor measures through."""
SPECULAR = ("glass", "frosted", "metal", "brushed")
"""Materials on which a depth sensor leaves blobs of holes."""

TABLE_MM = 700.0


@dataclass(frozen=True)
class PathTracing:
    """How the photos are path-traced: samples per pixel, the longest path (glass needs several
    bounces: in, out, and what lies behind), and whether a mirror-like backdrop stands behind the
    table at ``backdrop_y_mm`` (a vertical aluminium plane facing -y, 400 mm high): only cameras
    on its front side see the objects unoccluded, so a scene with it takes its cameras from
    :func:`facing_backdrop`."""

    spp: int = 64
    max_depth: int = 12
    backdrop_y_mm: float | None = None
    seed: int = 0


def bsdf_of(material: str, colours: NDArray[np.float64] | None = None) -> dict[str, Any]:
    """The mitsuba BSDF dictionary of ``material`` (:data:`MATERIALS`); an opaque one reads its
    colour from the mesh's ``vertex_color`` attribute (``colours`` given to :func:`_object`)."""
    if material == "opaque":
        return {"type": "diffuse", "reflectance": {"type": "mesh_attribute", "name": "vertex_color"}}
    if material == "glass":
        return {"type": "dielectric", "int_ior": 1.5, "ext_ior": 1.0}
    if material == "frosted":
        return {"type": "roughdielectric", "distribution": "ggx", "alpha": 0.12, "int_ior": 1.5, "ext_ior": 1.0}
    if material == "metal":
        return {"type": "conductor", "material": "Al"}
    if material == "brushed":
        return {"type": "roughconductor", "material": "Al", "distribution": "ggx", "alpha": 0.08}
    raise ValueError(f"unknown material {material!r}: one of {', '.join(MATERIALS)}")


def mitsuba_sensor(cam: Camera, spp: int, seed: int = 0, sampler: str = "independent") -> dict[str, Any]:
    """A mitsuba ``perspective`` sensor that sees what ``cam`` sees (module doc), with a box pixel
    filter (each pixel integrates its own square) and ``spp`` samples per pixel drawn by
    ``sampler`` (mitsuba's ``stratified`` needs a square ``spp``)."""
    mi = mitsuba()
    K = cam.K
    if abs(K[0, 0] - K[1, 1]) > 1e-9 * K[0, 0] or abs(K[0, 1]) > 0.0:
        raise ValueError("mitsuba's perspective camera needs square pixels without skew (fx = fy)")
    fov_x = float(np.degrees(2.0 * np.arctan(cam.width / (2.0 * K[0, 0]))))
    c2w = np.linalg.inv(cam.T_cw) @ np.diag([-1.0, -1.0, 1.0, 1.0])  # mitsuba camera: x left, y up
    return {"type": "perspective", "fov": fov_x, "fov_axis": "x",
            "principal_point_offset_x": 0.5 - K[0, 2] / cam.width,
            "principal_point_offset_y": 0.5 - K[1, 2] / cam.height,
            "near_clip": 1.0, "far_clip": 1e5, "to_world": mi.ScalarTransform4f(c2w.tolist()),
            "sampler": {"type": sampler, "sample_count": int(spp), "seed": int(seed)},
            "film": {"type": "hdrfilm", "width": cam.width, "height": cam.height, "pixel_format": "rgb",
                     "rfilter": {"type": "box"}}}


def _object(name: str, mesh: Mesh, T_wm: NDArray[np.float64], bsdf: dict[str, Any] | None,
            colours: NDArray[np.float64] | None = None, emitter: dict[str, Any] | None = None) -> Any:
    """A mitsuba mesh of ``mesh`` placed by ``T_wm`` (world-from-model, mm) with ``bsdf`` (and
    per-vertex ``colours`` (V, 3) in [0, 1] when it reads them), or an area ``emitter``."""
    mi = mitsuba()
    props = mi.Properties()
    if bsdf is not None:
        props["bsdf"] = mi.load_dict(bsdf)
    if emitter is not None:
        props["emitter"] = mi.load_dict(emitter)
    V = mesh.vertices @ T_wm[:3, :3].T + T_wm[:3, 3]
    m = mi.Mesh(name, len(V), len(mesh.faces), props=props, has_vertex_normals=False, has_vertex_texcoords=False)
    params = mi.traverse(m)
    params["vertex_positions"] = mi.Float(np.ascontiguousarray(V, dtype=np.float32).ravel())
    params["faces"] = mi.UInt32(np.ascontiguousarray(mesh.faces, dtype=np.uint32).ravel())
    params.update()
    if colours is not None:
        m.add_attribute("vertex_color", 3, mi.Float(np.ascontiguousarray(colours, dtype=np.float32).ravel()))
    return m


def sky(rng: np.random.Generator, width: int = 256) -> NDArray[np.float32]:
    """A latitude-longitude environment (``width`` x ``width / 2``, linear RGB, y up as mitsuba's
    ``envmap`` reads it): a bluish sky fading to a dim floor, and two bright windows at random
    azimuths, which give glass and metal their highlights."""
    h = width // 2
    lat = (0.5 - (np.arange(h) + 0.5) / h) * np.pi  # +pi/2 at the top row
    lon = (np.arange(width) + 0.5) / width * 2 * np.pi
    up = np.clip(np.sin(lat), 0.0, 1.0)[:, None, None]
    img = np.broadcast_to(0.25 + 0.55 * up * np.array([0.8, 0.9, 1.0]) + 0.05 * (lat[:, None, None] < 0), (h, width, 3)).copy()
    for _ in range(2):
        a, e = rng.uniform(0, 2 * np.pi), rng.uniform(0.3, 0.9)
        dlon = np.angle(np.exp(1j * (lon - a)))
        win = (np.abs(dlon)[None, :] < 0.25) & (np.abs(lat - e)[:, None] < 0.2)
        img[win] = rng.uniform(4.0, 8.0)
    return img.astype(np.float32)


def _table_texture(rng: np.random.Generator, size: int = 1024) -> NDArray[np.float32]:
    """The table's colour (RGB in [0, 1], ``size`` x ``size`` texels over :data:`TABLE_MM`): the
    wood-like texture of :mod:`~.photo_scene`'s table, sampled on its top."""
    from autoalign.experiments.scenes.photo_scene import TintedTexture

    tex = TintedTexture(rng, np.array([0.55, 0.42, 0.3]), 0.5, grey=True)
    s = (np.arange(size) + 0.5) / size * TABLE_MM - TABLE_MM / 2
    X, Y = np.meshgrid(s, s)
    return tex(np.stack([X.ravel(), Y.ravel(), np.zeros(X.size)], 1)).reshape(size, size, 3).astype(np.float32)


def _scene_dict(meshes: Sequence[Mesh], poses: Sequence[NDArray[np.float64]], materials: Sequence[str],
                rng: np.random.Generator, tracing: PathTracing) -> dict[str, Any]:
    """The mitsuba scene (without its sensor) of the meshes on the table under :func:`sky`."""
    from autoalign.experiments.scenes.photo_scene import TintedTexture

    mi = mitsuba()
    T_sky = mi.ScalarTransform4f().rotate([1.0, 0.0, 0.0], 90.0)  # the envmap's +y to the world's +z
    scene: dict[str, Any] = {
        "type": "scene",
        "integrator": {"type": "path", "max_depth": tracing.max_depth},
        "sky": {"type": "envmap", "bitmap": mi.Bitmap(sky(rng)), "to_world": T_sky},
        "table": {"type": "rectangle", "to_world": mi.ScalarTransform4f().scale([TABLE_MM / 2, TABLE_MM / 2, 1.0]),
                  "bsdf": {"type": "diffuse", "reflectance": {"type": "bitmap", "bitmap": mi.Bitmap(_table_texture(rng)),
                                                              "raw": True}}}}
    if tracing.backdrop_y_mm is not None:
        T_back = (mi.ScalarTransform4f().translate([0.0, tracing.backdrop_y_mm, 200.0])
                  @ mi.ScalarTransform4f().rotate([1.0, 0.0, 0.0], 90.0)
                  @ mi.ScalarTransform4f().scale([TABLE_MM / 2, 200.0, 1.0]))  # normal -y (towards the table)
        scene["backdrop"] = {"type": "rectangle", "to_world": T_back, "bsdf": bsdf_of("metal")}
    for j, (mesh, T, material) in enumerate(zip(meshes, poses, materials)):
        colours = None
        if material == "opaque":
            hsv = np.uint8([[[int(rng.uniform(0, 180)), int(rng.uniform(120, 230)), int(rng.uniform(120, 230))]]])
            base = cv2.cvtColor(hsv, cv2.COLOR_HSV2RGB)[0, 0] / 255.0
            colours = TintedTexture(rng, base)(mesh.vertices @ np.asarray(T)[:3, :3].T + np.asarray(T)[:3, 3])
        scene[f"object_{j}"] = _object(f"object_{j}", mesh, np.asarray(T, dtype=np.float64), bsdf_of(material),
                                       colours)
    return scene


def _render(scene: Any, sensor: dict[str, Any], seed: int) -> NDArray[np.float32]:
    """``scene`` seen by ``sensor``: linear RGB (H, W, 3)."""
    mi = mitsuba()
    return np.asarray(mi.render(scene, sensor=mi.load_dict(sensor), seed=seed), dtype=np.float32)


def path_traced_photos(meshes: Sequence[Mesh], poses: Sequence[NDArray[np.float64]], materials: Sequence[str],
                       cameras: Sequence[Camera], rng: np.random.Generator, tracing: PathTracing = PathTracing(),
                       noise: float = 2.0) -> list[NDArray[np.uint8]]:
    """Photos (BGR uint8, sRGB) of ``meshes`` at world-from-model ``poses`` (mm), each of its
    ``materials`` entry (:data:`MATERIALS`), on the textured table, path-traced as ``tracing``
    says, plus sensor noise (``noise`` grey levels)."""
    for material in materials:
        bsdf_of(material)  # a wrong name fails before any rendering
    mi = mitsuba()
    scene = mi.load_dict(_scene_dict(meshes, poses, materials, rng, tracing))
    photos = []
    for i, cam in enumerate(cameras):
        linear = _render(scene, mitsuba_sensor(cam, tracing.spp, tracing.seed + i), tracing.seed + i)
        srgb = np.where(linear <= 0.0031308, 12.92 * linear, 1.055 * np.power(np.maximum(linear, 0.0031308), 1 / 2.4) - 0.055)
        img = np.clip(srgb * 255.0 + rng.normal(0.0, noise, srgb.shape), 0, 255).round().astype(np.uint8)
        photos.append(img[:, :, ::-1].copy())
    return photos


def coverage_images(meshes: Sequence[Mesh], poses: Sequence[NDArray[np.float64]], cameras: Sequence[Camera],
                    spp: int = 64) -> list[list[NDArray[np.float32]]]:
    """Per camera and object, the share (H, W) of each pixel's square that sees the object,
    through :func:`mitsuba_sensor`: every object a white area light in turn, the others black
    occluders, nothing else in the scene; the samples stratified (``spp`` a square), so that a
    pixel's share is near exact. Compared with ray-cast masks, it checks the sensor's camera
    convention."""
    mi = mitsuba()
    out: list[list[NDArray[np.float32]]] = [[] for _ in cameras]
    black = {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.0, 0.0, 0.0]}}
    for j in range(len(meshes)):
        scene = {"type": "scene", "integrator": {"type": "direct", "emitter_samples": 1, "bsdf_samples": 1}}
        for k, (mesh, T) in enumerate(zip(meshes, poses)):
            glow = {"type": "area", "radiance": {"type": "rgb", "value": [1.0, 1.0, 1.0]}} if k == j else None
            scene[f"object_{k}"] = _object(f"object_{k}", mesh, np.asarray(T, dtype=np.float64), black, emitter=glow)
        loaded = mi.load_dict(scene)
        for i, cam in enumerate(cameras):
            out[i].append(_render(loaded, mitsuba_sensor(cam, spp, i, "stratified"), i)[:, :, 0])
    return out


def facing_backdrop(cameras: Sequence[Camera], backdrop_y_mm: float) -> list[Camera]:
    """The cameras on the backdrop's front side (y below ``backdrop_y_mm`` by at least 100 mm)."""
    return [c for c in cameras if c.centre[1] < backdrop_y_mm - 100.0]
