"""The silhouette loss of every instance of a scene at once, occlusion-aware.

In a view a pixel belongs to the nearest surface among all the instances' meshes. Instance ``i``'s
*visible* soft silhouette is

    V_i(p) = S_i(p) * prod over j in front of i at p of (1 - S_j(p))

with ``S`` each mesh's own soft silhouette (:class:`~autoalign.rasterizers.soft_silhouette.SoftSilhouetteRasterizer`). Which of two meshes
is in front at a pixel is decided by ray casting both where both are hit there; on their soft
edges (one of them missed) by the order of the pair over the view's pixels where both are hit,
or, where they nowhere overlap, by which is hit nearer. ``V_i`` is compared with ``i``'s mask (the
L2 loss of :func:`autoalign.losses.l2`), and its derivatives are kept w.r.t. the twists of ``i``
and of every instance in front of it: a silhouette part a modelled object hides costs nothing,
and the contour between two objects moves with both.

Pixels another instance's mask claims and ``i``'s does not stay ignored for ``i`` (a mask that
strayed onto it, an unmodelled occluder), except under the soft silhouette of a modelled instance
in front of it: there the models say the pixel is hidden and its comparison with ``i``'s mask
(0) is what makes the shared contour pull on both objects.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any, Callable, TypeVar

import numpy as np
from numpy.typing import NDArray

from autoalign.engine.objective import Level, SilhouetteObjective
from autoalign.geometry.camera import Camera, pixel_centres
from autoalign.geometry.se3 import transform_points
from autoalign.io.instances import InstanceScenes
from autoalign.losses import robust_view_weights
from autoalign.losses.depth import DepthNoise
from autoalign.losses.mask_term import MaskTerm
from autoalign.losses.overlap import iou_from_counts
from autoalign.losses.region_term import RegionTerm
from autoalign.losses.term import Fragments, LevelViews, Measured, TermValues, ViewTermsRecord
from autoalign.rasterizers.camera_batch import CameraBatch
from autoalign.rasterizers.pyramid import MeshDetail, MeshPyramid
from autoalign.rasterizers.soft_silhouette import Silhouettes
from autoalign.runtime.parallel import side_by_side

V = TypeVar("V")


@dataclass
class ViewFit:
    """One instance in one view.

    Attributes:
        instances: (m,) the instances whose twists the view's loss depends on, this one first.
        loss: ``0.5 sum_p (V(p) - t(p))^2 / area(t)`` over the view (L2).
        grad: (6m,) its gradient w.r.t. the twists ``(v [mm], w [rad])`` of ``instances``, in order.
        gn: (6m, 6m) its Gauss-Newton matrix.
        iou: soft IoU of the visible silhouette with the mask.
        hard_iou: the same with the ray-cast visible silhouette and the mask thresholded at 0.5.
        n_band: pixels whose value depends on a pose.
    """

    instances: NDArray[np.int64]
    loss: float
    grad: NDArray[np.float64]
    gn: NDArray[np.float64]
    iou: float
    hard_iou: float
    n_band: int


@dataclass
class JointEvaluation:
    """The loss of every instance in every one of its views, with per-view robust weights.

    ``fits[i][k]`` is instance ``i`` in its ``k``-th view; ``weights[i]`` (one per view, mean 1)
    weigh them; ``value = sum_i sum_k weights[i][k] fits[i][k].loss``. ``own[i]``: what instance
    ``i``'s own terms beside the masks gave (:meth:`OcclusionObjective.evaluate`), already in its fits.
    """

    fits: list[list[ViewFit]]
    weights: list[NDArray[np.float64]]
    value: float
    robust: bool = True
    own: list[tuple[TermValues, ...]] | None = None

    def iou(self, i: int) -> NDArray[np.float64]:
        return np.array([f.iou for f in self.fits[i]])

    def hard_iou(self, i: int) -> NDArray[np.float64]:
        return np.array([f.hard_iou for f in self.fits[i]])

    @property
    def instance_values(self) -> list[float]:
        """Each instance's part of ``value``: its views' weighted loss."""
        return _instance_values(self.fits, self.weights)

    def record(self, i: int) -> ViewTermsRecord:
        """Instance ``i``'s terms per view (:class:`~autoalign.losses.term.ViewTermsRecord`): its own
        terms', and the masks' the rest of its fits."""
        loss = np.array([f.loss for f in self.fits[i]])
        own = {v.name: v.views.loss for v in self.own_values(i) if v.views is not None}
        for term_loss in own.values():
            loss = loss - term_loss
        return ViewTermsRecord({**own, "mask": loss}, self.weights[i])

    def own_values(self, i: int) -> tuple[TermValues, ...]:
        """What instance ``i``'s own terms beside the masks gave, in order."""
        return () if self.own is None else self.own[i]

    def measured(self, i: int) -> tuple[Measured, ...]:
        """What instance ``i``'s own terms measured (e.g. :class:`~autoalign.losses.depth.DepthTerms`), in order."""
        return tuple(v.measured for v in self.own_values(i) if v.measured is not None)

    def reweighted(self) -> "JointEvaluation":
        """The same fits with the weights computed from their own IoU (an IRLS step; none if not robust)."""
        if not self.robust:
            return self
        w = [robust_view_weights(self.iou(i)) for i in range(len(self.fits))]
        return JointEvaluation(self.fits, w, _weighted_value(self.fits, w), self.robust, self.own)


def _instance_values(fits: list[list[ViewFit]], weights: list[NDArray[np.float64]]) -> list[float]:
    return [float(w @ np.array([f.loss for f in fs])) for fs, w in zip(fits, weights)]


def _weighted_value(fits: list[list[ViewFit]], weights: list[NDArray[np.float64]]) -> float:
    return float(sum(_instance_values(fits, weights)))


@dataclass
class _Pair:
    """Instance ``j`` and ``i`` both soft-covering pixels of view ``g``: ``pi``/``pj`` index them in
    ``i``'s and ``j``'s crops, ``uv`` are their centres (internal pixel convention)."""

    i: int
    j: int
    g: int
    pi: NDArray[np.int64]
    pj: NDArray[np.int64]
    uv: NDArray[np.float64]
    front: NDArray[np.bool_] | None = None  # j in front of i at each pixel


class OcclusionObjective:
    """The occlusion-aware silhouette loss of all instances of ``found`` (see module doc).

    Args:
        found: the instances and their views (:func:`~autoalign.io.instances.read_instance_scenes`).
        pyramids: each instance's mesh pyramid, in ``found.instances`` order (drawn at ``detail.fine``).
        robust: weigh views by their fit (:func:`~autoalign.losses.robust_view_weights`); else all 1.
        detail: the meshes' detail (:class:`~autoalign.rasterizers.pyramid.MeshDetail`).
        depth: the depth sensor's noise; with it, an instance whose scene has measured depth adds
            the depth term (:mod:`autoalign.losses.depth`) to its own twist in each of its views.
        edges: the edge term's weight; with it, an instance whose scene carries photos (its masks
            withheld) adds the edge term (:mod:`autoalign.losses.edge`) the same way.
        regions: per instance its region term learned on its views (:mod:`autoalign.losses.region_term`),
            whose targets its silhouettes are compared with in its masks' place; ``None``: the masks.

    Each instance's own per-view terms are its objective's (:func:`~autoalign.engine.objective.view_terms`,
    the one list), but for the mask term, whose place the occlusion-aware fit takes: a term added
    there joins this stage too.
    """

    def __init__(self, found: InstanceScenes, pyramids: list[MeshPyramid], robust: bool = True,
                 detail: MeshDetail = MeshDetail(), depth: DepthNoise | None = None,
                 edges: float | None = None, regions: list[RegionTerm | None] | None = None) -> None:
        self.rasterizers = [p.fine(detail) for p in pyramids]
        self.robust = robust
        self.objectives = [SilhouetteObjective(p, s, detail=detail, depth=depth, edges=edges, region=r)
                           for p, s, r in zip(pyramids, found.scenes, regions or [None] * len(pyramids))]
        used = sorted({im for s in found.scenes for im in s.image_ids})
        by_id = dict(zip(found.image_ids, found.cameras))
        self.image_ids = used
        self.cameras = [by_id[im] for im in used]
        pos = {im: g for g, im in enumerate(used)}
        self.views_of = [np.array([pos[im] for im in s.image_ids], dtype=np.int64) for s in found.scenes]
        self.centres_m = [r.mesh.centre for r in self.rasterizers]
        self._last = _LastValues()

    def use_cameras(self, cameras: dict[int, Camera]) -> None:
        """Render through ``cameras`` (by image id) from now on."""
        self.cameras = [cameras[im] for im in self.image_ids]
        for o in self.objectives:
            o.use_cameras([cameras[im] for im in o.compared.image_ids])
        self._last.clear()

    def evaluate(self, poses: list[NDArray[np.float64]], level: Level,
                 weights: list[NDArray[np.float64]] | None = None) -> JointEvaluation:
        """Render every instance at its pose (world from model, mm) in every view and compare;
        without ``weights`` they are computed from the fit (robust).

        What depends only on instances whose poses are those of the previous call (their renders,
        their overlaps, the fits of the views none of them changed in) is taken from that call:
        the joint solve holds the objects that have converged while the others move."""
        cams = [c.scaled(level.scale) for c in self.cameras]
        batch = CameraBatch.of(cams)
        keys = [(level.scale, level.sigma, np.asarray(T, dtype=np.float64).tobytes()) for T in poses]
        sils = side_by_side(lambda i: self._last.get(("render", i), keys[i],
                                                     lambda: self.rasterizers[i].render(poses[i], cams, level.sigma)),
                            range(len(poses)))
        views = [o.at_scale(level.scale) for o in self.objectives]
        pairs = self._overlaps(sils, keys, poses, batch)
        by_view: dict[tuple[int, int], list[_Pair]] = {}
        for p in pairs:
            by_view.setdefault((p.i, p.g), []).append(p)
        band_rows = [_BandRows(s) for s in sils]
        fits = []
        for i, (sil, lv) in enumerate(zip(sils, views)):
            fits.append([])
            for k, g in enumerate(self.views_of[i]):
                here = by_view.get((i, int(g)), [])
                key = (keys[i], tuple((p.j, keys[p.j]) for p in here))
                fits[i].append(self._last.get(("fit", i, k), key,
                                              lambda: self._fit(i, k, int(g), sil, lv, sils, band_rows, here, level)))
        own = [self._own_terms(i, poses[i], keys[i], sils[i], fits[i], level) for i in range(len(poses))]
        if weights is None:
            weights = [robust_view_weights(np.array([f.iou for f in fs])) if self.robust else np.ones(len(fs))
                       for fs in fits]
        return JointEvaluation(fits, weights, _weighted_value(fits, weights), self.robust, own)

    def _own_terms(self, i: int, T_wm: NDArray[np.float64], key: tuple, sil: Silhouettes, fits: list[ViewFit],
                   level: Level) -> tuple[TermValues, ...]:
        """Instance ``i``'s own per-view terms beside the masks at ``T_wm`` (its objective's, the mask
        term left out: the occlusion-aware fit is its), added in place to its views' ``fits`` (its
        own twist comes first in each fit)."""
        terms = [t for t in self.objectives[i].terms if not isinstance(t, MaskTerm)]
        if not terms:
            return ()
        rast = self.rasterizers[i]
        fragments = Fragments(T_wm, transform_points(T_wm, self.centres_m[i][None])[0], level.scale,
                              self.objectives[i].at_scale(level.scale), sil, rast)
        values = tuple(self._last.get(("term", i, n), key, lambda term=term: term.residuals(fragments))
                       for n, term in enumerate(terms))
        for v in values:
            if v.views is None:
                continue
            for k, f in enumerate(fits):
                grad, gn = f.grad.copy(), f.gn.copy()
                grad[:6] += v.views.grad[k]
                gn[:6, :6] += v.views.gn[k]
                fits[k] = replace(f, loss=f.loss + float(v.views.loss[k]), grad=grad, gn=gn)
        return values

    # -------------------------------------------------------------------------------- steps
    def _overlaps(self, sils: list[Silhouettes], keys: list[tuple], poses: list[NDArray[np.float64]],
                  batch: CameraBatch) -> list[_Pair]:
        """Every (i, j, view of i) where both soft silhouettes cover some pixel, with which is in
        front there (:meth:`_order`); those of two instances at their previous poses are reused."""
        out, new, fresh = [], [], []
        for i in range(len(sils)):
            for j in range(len(sils)):
                if j == i:
                    continue
                found = self._last.find(("pairs", i, j), (keys[i], keys[j]))
                if found is None:
                    found = self._pairs(i, j, sils)
                    new.append(((i, j), found))
                    fresh += found
                out += found
        self._order(fresh, poses, batch, sils)
        for (i, j), found in new:
            self._last.put(("pairs", i, j), (keys[i], keys[j]), found)
        return out

    def _pairs(self, i: int, j: int, sils: list[Silhouettes]) -> list[_Pair]:
        """The views of ``i`` where the soft silhouettes of ``i`` and ``j`` both cover some pixel."""
        out = []
        si, sj = sils[i], sils[j]
        for g in self.views_of[i]:
            xi, yi, wi, hi = si.crops[g]
            xj, yj, wj, hj = sj.crops[g]
            x0, y0 = max(xi, xj), max(yi, yj)
            x1, y1 = min(xi + wi, xj + wj), min(yi + hi, yj + hj)
            if x1 <= x0 or y1 <= y0:
                continue
            # the shared rectangle as views of both crops (row-major, as the band's pixels)
            ci = si.soft[si.offsets[g]:si.offsets[g] + wi * hi].reshape(hi, wi)[y0 - yi:y1 - yi, x0 - xi:x1 - xi]
            cj = sj.soft[sj.offsets[g]:sj.offsets[g] + wj * hj].reshape(hj, wj)[y0 - yj:y1 - yj, x0 - xj:x1 - xj]
            yy, xx = np.nonzero((ci > 0) & (cj > 0))
            if len(yy):
                yy, xx = yy + y0, xx + x0
                out.append(_Pair(i, j, int(g), (yy - yi) * wi + (xx - xi), (yy - yj) * wj + (xx - xj),
                                 pixel_centres(xx, yy)))
        return out

    def _order(self, pairs: list[_Pair], poses: list[NDArray[np.float64]], batch: CameraBatch,
               sils: list[Silhouettes]) -> None:
        """Set ``front`` of every pair: one depth ray cast per instance for all its pixels."""
        queries: dict[int, list[tuple[_Pair, bool]]] = {}
        for p in pairs:
            queries.setdefault(p.i, []).append((p, True))
            queries.setdefault(p.j, []).append((p, False))
        depth: dict[tuple[int, bool], NDArray[np.float64]] = {}
        for inst, qs in queries.items():
            view = np.concatenate([np.full(len(p.uv), p.g, dtype=np.int64) for p, _ in qs])
            t = self.rasterizers[inst].caster.pixel_depths(poses[inst], batch, view, np.concatenate([p.uv for p, _ in qs]))
            for (p, own), part in zip(qs, np.split(t, np.cumsum([len(p.uv) for p, _ in qs])[:-1])):
                depth[(id(p), own)] = part
        for p in pairs:
            di, dj = depth[(id(p), True)], depth[(id(p), False)]
            both = np.isfinite(di) & np.isfinite(dj)
            if both.any():
                default = bool(np.mean(dj[both] < di[both]) > 0.5)
            elif np.isfinite(di).any() and np.isfinite(dj).any():
                default = bool(dj[np.isfinite(dj)].min() < di[np.isfinite(di)].min())
            else:
                zi, zj = (batch.R_w2c[p.g] @ transform_points(poses[k], self.centres_m[k][None])[0] for k in (p.i, p.j))
                default = bool(zj[2] < zi[2])
            p.front = np.where(both, dj < di, default)

    def _fit(self, i: int, k: int, g: int, sil: Silhouettes, lv: LevelViews, sils: list[Silhouettes],
             band_rows: list["_BandRows"], pairs: list[_Pair], level: Level) -> ViewFit:
        """Instance ``i`` in its ``k``-th view (global view ``g``): the loss and its derivatives."""
        x0, y0, w, h = sil.crops[g]
        o = sil.offsets[g]
        s = sil.soft[o:o + w * h]
        t = lv.targets[k][y0:y0 + h, x0:x0 + w].ravel().astype(np.float64)
        ignored = (lv.ignore[k][y0:y0 + h, x0:x0 + w].ravel() if lv.ignore is not None
                   else np.zeros(w * h, dtype=bool))
        hidden = np.ones(w * h)  # prod of (1 - S_j) over instances in front
        hidden_hard = np.zeros(w * h, dtype=bool)
        occluders = []  # (j, pixels of i's crop, S_j there, rows of j's band or -1)
        for p in pairs:
            px, pj = p.pi[p.front], p.pj[p.front]
            if len(px) == 0:
                continue
            sj = sils[p.j].soft[sils[p.j].offsets[g] + pj]
            hidden[px] *= 1.0 - sj
            hidden_hard[px] |= sils[p.j].hard[sils[p.j].offsets[g] + pj]
            occluders.append((p.j, px, sj, band_rows[p.j].rows(g, pj)))
        ignored &= hidden == 1.0
        V = np.where(ignored, 0.0, s * hidden)
        e = V - t
        total = float(lv.totals[k])
        norm = max(total, 1.0)
        outside = max(total - float(t.sum()), 0.0)
        loss = 0.5 * (float(e @ e) + outside) / norm
        iou = float(iou_from_counts(V @ t, V.sum(), total))  # soft counts

        # Jacobian rows: i's own band (times what hides it), and the occluders' bands (times -V_i / (1 - S_j))
        r0, r1 = band_rows[i].range(g)
        own_px = sil.band[r0:r1] - o
        own = (own_px, hidden[own_px] * ~ignored[own_px], sil.jac[r0:r1])
        terms = [(i,) + own]
        for j, px, sj, rows in occluders:
            keep = rows >= 0
            if not keep.any():
                continue
            others = np.ones(keep.sum())
            for j2, px2, sj2, _ in occluders:  # the product over the other occluders at these pixels
                if j2 != j:
                    lut = np.ones(w * h)
                    lut[px2] = 1.0 - sj2
                    others *= lut[px[keep]]
            terms.append((j, px[keep], -s[px[keep]] * others, sils[j].jac[rows[keep]]))
        involved = list(dict.fromkeys(term[0] for term in terms))
        col = {inst: c for c, inst in enumerate(involved)}
        used = np.zeros(w * h, dtype=bool)  # the crop's pixels any term has a row for, in order
        for term in terms:
            used[term[1]] = True
        pix = np.flatnonzero(used)
        J = np.zeros((len(pix), 6 * len(involved)))
        for inst, px, coeff, jac in terms:  # a term's pixels are distinct: a plain += adds each once
            c = 6 * col[inst]
            J[np.searchsorted(pix, px), c:c + 6] += coeff[:, None] * jac
        grad = J.T @ e[pix] / norm
        gn = J.T @ J / norm
        hard_iou = np.nan
        if level.scale == 1.0:
            hv = sil.hard[o:o + w * h] & ~hidden_hard & ~ignored
            hard_iou = float(iou_from_counts(np.count_nonzero(hv & (t > 0.5)), np.count_nonzero(hv),
                                             lv.hard_totals[k]))
        return ViewFit(np.array(involved, dtype=np.int64), loss, grad, gn, iou, hard_iou, len(pix))


class _LastValues:
    """The value last computed for each slot, with the key of the inputs it was computed from."""

    def __init__(self) -> None:
        self._slots: dict[tuple, tuple[object, object]] = {}

    def find(self, slot: tuple, key: object) -> Any:
        """The slot's value if it was computed from ``key``, else None."""
        held = self._slots.get(slot)
        return held[1] if held is not None and held[0] == key else None

    def put(self, slot: tuple, key: object, value: object) -> None:
        self._slots[slot] = (key, value)

    def get(self, slot: tuple, key: object, compute: Callable[[], V]) -> V:
        """The slot's value for ``key``, computed (and kept) unless it was the last one computed."""
        value = self.find(slot, key)
        if value is None:
            value = compute()
            self.put(slot, key, value)
        return value

    def clear(self) -> None:
        self._slots.clear()


class _BandRows:
    """Where a view's pixels are in a :class:`Silhouettes`' band (its rows of ``jac``)."""

    def __init__(self, sil: Silhouettes) -> None:
        self.sil = sil
        # band indices are grouped by view and increase within one (row-major crops)
        self.bounds = np.searchsorted(sil.band, sil.offsets)

    def range(self, g: int) -> tuple[int, int]:
        return int(self.bounds[g]), int(self.bounds[g + 1])

    def rows(self, g: int, local: NDArray[np.int64]) -> NDArray[np.int64]:
        """The band row of each crop pixel ``local`` of view ``g``, -1 where it is off the band."""
        r0, r1 = self.range(g)
        flat = self.sil.band[r0:r1]
        k = np.searchsorted(flat, self.sil.offsets[g] + local)
        k = np.minimum(k, max(len(flat) - 1, 0))
        hit = (len(flat) > 0) & (flat[k] == self.sil.offsets[g] + local) if len(flat) else np.zeros(len(local), bool)
        return np.where(hit, r0 + k, -1)
