"""The photos join masks that fit without pulling the pose away (issue 43, item 3).

Fused with fixed segmenter rates (the mask right 90% of the time where it says object, 20% of its
background near the outline the object), a view's target stood at 0.9 inside an exact mask and 0.2
outside it wherever the colours could not tell (a blurred edge): the soft silhouette's edge then
settles where the target's mean is 1/2, outwards, and on the bundled example the photos moved the
mug 0.1 mm / 0.36 deg from where its exact masks put it. A mask is now trusted as far as it fits
the pose (:func:`~autoalign.losses.region.mask_rates`), never less than segmenter masks typically are,
where the colours confirm the mask's own outline (its edge contrast): one eroded by 4 px, which a
pose far along the ray fits from one viewpoint, keeps the typical rates, and the colours complete it.
"""

from __future__ import annotations

import numpy as np
import pytest

from autoalign.experiments.studies.exact_masks_photos import example_case, photo_moves, study_case
from autoalign.losses.region import MASK_MISS, MASK_TRUST, mask_rates, region_target


def _disk(shape: tuple[int, int], centre: tuple[float, float], r: float) -> np.ndarray:
    yy, xx = np.mgrid[0:shape[0], 0:shape[1]]
    return (yy - centre[0]) ** 2 + (xx - centre[1]) ** 2 <= r * r


def test_a_mask_is_trusted_as_far_as_it_fits() -> None:
    """Counted in a band of 15 px either side of the silhouette's outline."""
    sil = _disk((120, 160), (60, 80), 30)
    band = _disk((120, 160), (60, 80), 45) & ~_disk((120, 160), (60, 80), 15)
    trust, miss = mask_rates(sil[band], sil[band])
    assert trust > 0.999 and miss < 0.001
    cut = sil.copy()
    cut[:, 80:] = False  # a mask missing half the object: right where it says object, typical where not
    trust, miss = mask_rates(cut[band], sil[band])
    assert trust > 0.999 and miss == MASK_MISS
    leaking = _disk((120, 160), (60, 80), 40)  # a mask a third wider: typical where it says object
    trust, miss = mask_rates(leaking[band], sil[band])
    assert trust == MASK_TRUST and miss < 0.001


def test_colours_that_cannot_tell_confirm_no_outline() -> None:
    """A grey photo says nothing of where the outline is: the mask keeps the typical rates (the
    colours at 1/2 leave it 0.9 inside and 0.2 outside), as before the rates were read from the fit."""
    sil = _disk((120, 160), (60, 80), 30)
    photo = np.full((120, 160, 3), 128, np.uint8)
    target = region_target(photo, sil, sil.astype(np.float32)).target
    ring = _disk((120, 160), (60, 80), 33) & ~_disk((120, 160), (60, 80), 27)
    assert np.allclose(target[ring & sil], MASK_TRUST, atol=0.02) and np.allclose(target[ring & ~sil], MASK_MISS, atol=0.02)


def test_a_mask_the_colours_show_eroded_is_held_to_the_typical_rates() -> None:
    """The object's colours on both sides of a mask's outline (eroded by 4 px): however well a pose
    far along the ray fits it, the colours complete it as before, beyond the mask's own outline."""
    sil = _disk((120, 160), (60, 80), 30)
    photo = np.full((120, 160, 3), (40, 160, 40), np.uint8)
    photo[sil] = (180, 40, 160)
    eroded = _disk((120, 160), (60, 80), 26)
    target = region_target(photo, eroded, eroded.astype(np.float32)).target  # the pose fits the eroded mask
    assert target[sil & ~eroded].min() > 0.5  # the object's colours beyond it: the object
    exact = region_target(photo, sil, sil.astype(np.float32)).target
    assert np.abs(exact - sil).max() < 0.01  # the colours confirm this outline: the mask as it is


@pytest.mark.slow
@pytest.mark.parametrize("case", ["example", "mug"])
def test_exact_masks_hold_against_the_photos(case: str) -> None:
    """The bundled example, and the refine study's mug with photos rendered by mitsuba: adding the
    photos moves the pose at most 0.02 mm / 0.05 deg from where the exact masks alone put it."""
    moves = photo_moves(example_case() if case == "example" else study_case(2))
    mm, deg = moves.photos_vs_masks
    assert mm <= 0.02 and deg <= 0.05, moves
