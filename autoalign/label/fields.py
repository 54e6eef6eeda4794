"""The fields of the label page's requests, each checked before the session sees it: of the right
JSON type (a JSON ``true`` is not the number 1, a string is not a flag), finite, and within bounds
that no page sends, so that a bad request is a 400 with one line naming the field, never a pose
overflowed to NaN or an ``int(inf)`` inside the handler.

Every reader raises :class:`~autoalign.errors.AutoalignError`; the server answers it with 400.
"""

from __future__ import annotations

import json
import math
from typing import Any

import numpy as np
from numpy.typing import NDArray

from autoalign.errors import AutoalignError

MAX_ID = 2**31 - 1
"""The largest instance, object or image number accepted."""
MAX_PIXEL = 1e6
"""Pixel coordinates beyond this are refused outright (the view's own size is checked later)."""
MAX_MOVE_MM = 1000.0
"""The largest move of one nudge (a key moves 1 mm, or 5 with Shift)."""
MAX_TURN_DEG = 360.0
"""The largest turn of one nudge, per axis (a key turns 1 degree, or 5 with Shift)."""


def _present(body: dict[str, Any], key: str) -> Any:
    if key not in body:
        raise AutoalignError(f"{key}: missing from the request")
    return body[key]


def _is_number(x: Any) -> bool:
    return isinstance(x, (int, float)) and not isinstance(x, bool)


def integer(body: dict[str, Any], key: str) -> int:
    """``body[key]`` as a whole number in ``[0, MAX_ID]``."""
    x = _present(body, key)
    if isinstance(x, float) and x.is_integer():
        x = int(x)  # JSON has one number type: 3.0 is 3
    if not (isinstance(x, int) and not isinstance(x, bool)) or not 0 <= x <= MAX_ID:
        raise AutoalignError(f"{key}: {_shown(x)} is not a whole number from 0 to {MAX_ID}")
    return x


def number(body: dict[str, Any], key: str, bound: float) -> float:
    """``body[key]`` as a finite number within ``±bound``."""
    x = _present(body, key)
    if not _is_number(x) or not math.isfinite(float(x)) or abs(float(x)) > bound:
        raise AutoalignError(f"{key}: {_shown(x)} is not a finite number within ±{bound:g}")
    return float(x)


def vector3(body: dict[str, Any], key: str, bound: float) -> list[float]:
    """``body[key]`` (``[0, 0, 0]`` if absent) as three finite numbers, each within ``±bound``."""
    xs = body.get(key, [0, 0, 0])
    if not isinstance(xs, list) or len(xs) != 3 or not all(_is_number(x) for x in xs) \
            or not all(math.isfinite(float(x)) and abs(float(x)) <= bound for x in xs):
        raise AutoalignError(f"{key}: {_shown(xs)} is not three finite numbers, each within ±{bound:g}")
    return [float(x) for x in xs]


def flag(body: dict[str, Any], key: str) -> bool:
    """``body[key]`` as JSON ``true`` or ``false``."""
    x = _present(body, key)
    if not isinstance(x, bool):
        raise AutoalignError(f"{key}: {_shown(x)} is not true or false")
    return x


def text(body: dict[str, Any], key: str) -> str:
    """``body[key]`` as a string."""
    x = _present(body, key)
    if not isinstance(x, str):
        raise AutoalignError(f"{key}: {_shown(x)} is not a string")
    return x


def nudge_vectors(move_mm: Any, turn_deg: Any) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """A nudge's move (mm) and turn (degrees) as arrays of three, each within :data:`MAX_MOVE_MM` and
    :data:`MAX_TURN_DEG`; raises :class:`AutoalignError` otherwise (the session's own check, for every caller)."""
    move, turn = np.asarray(move_mm, dtype=np.float64), np.asarray(turn_deg, dtype=np.float64)
    if move.shape != (3,) or turn.shape != (3,) or not (np.isfinite(move).all() and np.isfinite(turn).all()) \
            or np.abs(move).max() > MAX_MOVE_MM or np.abs(turn).max() > MAX_TURN_DEG:
        raise AutoalignError(f"a nudge is three finite numbers to move (mm, each within ±{MAX_MOVE_MM:g}) and "
                             f"three to turn (degrees, each within ±{MAX_TURN_DEG:g})")
    return move, turn


def _shown(x: Any) -> str:
    """``x`` as JSON, cut short (the error is one line)."""
    try:
        s = json.dumps(x)
    except (TypeError, ValueError, RecursionError):
        s = type(x).__name__
    return s if len(s) <= 40 else s[:37] + "..."
