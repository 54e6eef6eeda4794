"""Mask files read by several threads give what reading them one by one gives, and the same errors."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from autoalign.errors import AutoalignError
from autoalign.io.block_mean import Pad, block_mean
from autoalign.io.bop import downscale_factor, read_mask, read_masks


def _write_masks(folder: Path, n: int, size: tuple[int, int]) -> dict[tuple[int, int], Path]:
    """``n`` random 0/255 masks of ``size`` (H, W), every fifth one empty."""
    rng = np.random.default_rng(3)
    folder.mkdir(parents=True, exist_ok=True)
    paths = {}
    for k in range(n):
        m = np.zeros(size, np.uint8)
        if k % 5:
            y, x = rng.integers(0, size[0] // 2), rng.integers(0, size[1] // 2)
            m[y:y + size[0] // 3, x:x + size[1] // 4] = 255
        p = folder / f"{k:06d}_000000.png"
        cv2.imwrite(str(p), m)
        paths[(k, 0)] = p
    return paths


@pytest.mark.parametrize("max_pixels", [None, 120 * 90])
def test_masks_read_by_threads_match_one_by_one(tmp_path: Path, max_pixels: int | None) -> None:
    paths = _write_masks(tmp_path, 23, (240, 320))
    got = read_masks(paths, max_pixels)
    f = downscale_factor(320, 240, max_pixels)
    assert got.factor == f and got.size == (240, 320)
    assert got.empty == [key for key in paths if key[0] % 5 == 0]
    assert list(got.masks) == [key for key in paths if key[0] % 5]
    for key, m in got.masks.items():
        one, kind = read_mask(paths[key])
        assert kind == "0/255"
        want = block_mean(one.astype(np.float32), f, Pad.ZEROS) > 0.5 if f > 1 else one
        assert m.dtype == bool and np.array_equal(m, want)


def test_a_mask_of_another_size_is_named_as_in_file_order(tmp_path: Path) -> None:
    paths = _write_masks(tmp_path, 12, (60, 80))
    for k in (7, 9):  # two wrong sizes: the first in the files' order is the one named
        cv2.imwrite(str(paths[(k, 0)]), np.full((61, 80), 255, np.uint8))
    with pytest.raises(AutoalignError, match=r"000007_000000\.png: mask is 80x61 but 000000_000000\.png is 80x60"):
        read_masks(paths)


def test_an_unreadable_mask_is_named(tmp_path: Path) -> None:
    paths = _write_masks(tmp_path, 8, (60, 80))
    paths[(3, 0)].write_bytes(b"not a png")
    with pytest.raises(AutoalignError, match=r"000003_000000\.png: cannot read the mask image"):
        read_masks(paths)
