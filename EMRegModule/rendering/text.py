"""Text on the report's 2D figures, drawn with OpenCV and, on request, recorded as data.

Every label of a plot or a slice mosaic is drawn through :func:`put_text`. Inside :func:`recorded_text`
each call also appends a :class:`TextItem`: the string, where the caller anchored it and how (the layout's
decision), and the pixel box its glyphs cover (the rasteriser's). The golden-image tests compare the strings
and anchors exactly and the rest of the picture strictly, while the boxes' pixels, which change with the
version of OpenCV's font rasteriser, are compared with a tolerant measure.

Pixel coordinates: x to the right, y down, origin at the image's top-left corner.
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from contextvars import ContextVar
from dataclasses import asdict, dataclass, replace

import cv2
import numpy as np

FONT = cv2.FONT_HERSHEY_SIMPLEX
INK = (30, 30, 30)  # the figures' near-black


@dataclass(frozen=True)
class TextItem:
    """One label as drawn: ``anchor`` is the pixel the caller placed it at (before ``align``: the left end,
    centre or right end of its baseline; for ``rotated`` text, its centre column and its top or middle row),
    ``box`` the pixels
    ``(x0, y0, x1, y1)`` (exclusive ends) its glyphs may cover on the canvas."""

    text: str
    anchor: tuple[int, int]
    align: str
    scale: float
    color: tuple[int, int, int]
    box: tuple[int, int, int, int]
    rotated: bool = False

    def to_json(self) -> dict:
        return asdict(self)

    @classmethod
    def from_json(cls, data: dict) -> TextItem:
        return cls(str(data["text"]), tuple(data["anchor"]), str(data["align"]), float(data["scale"]),
                   tuple(data["color"]), tuple(data["box"]), bool(data.get("rotated", False)))

    def shifted(self, dx: int, dy: int) -> TextItem:
        """The same item on a canvas whose origin is ``(-dx, -dy)`` in this item's canvas."""
        x0, y0, x1, y1 = self.box
        return replace(self, anchor=(self.anchor[0] + dx, self.anchor[1] + dy),
                       box=(x0 + dx, y0 + dy, x1 + dx, y1 + dy))


_LEDGER: ContextVar[list[TextItem] | None] = ContextVar("emreg_text_ledger", default=None)


@contextmanager
def recorded_text() -> Iterator[list[TextItem]]:
    """Collect every :func:`put_text` of the enclosed drawing (in order) into the yielded list."""
    items: list[TextItem] = []
    token = _LEDGER.set(items)
    try:
        yield items
    finally:
        _LEDGER.reset(token)


def relay_text(items: Sequence[TextItem], dx: int, dy: int) -> None:
    """Record ``items``, drawn on a tile later pasted at ``(dx, dy)``, in the enclosing canvas's coordinates."""
    ledger = _LEDGER.get()
    if ledger is not None:
        ledger.extend(item.shifted(dx, dy) for item in items)


def text_size(text: str, scale: float, thickness: int = 1) -> tuple[int, int]:
    """Width and height (pixels above the baseline) of ``text`` at font ``scale``."""
    (width, height), _ = cv2.getTextSize(text, FONT, scale, thickness)
    return width, height


def _record(item: TextItem) -> None:
    ledger = _LEDGER.get()
    if ledger is not None:
        ledger.append(item)


def put_text(canvas: np.ndarray, text: str, x: float, y: float, scale: float = 0.42,
             color: tuple[int, int, int] = INK, align: str = "left", thickness: int = 1) -> None:
    """Draw ``text`` on ``canvas`` (RGB ``uint8``, in place) with its baseline at pixel row ``y``; ``x`` is the
    left end, the centre or the right end of the text for ``align`` ``"left"``, ``"center"`` or ``"right"``."""
    width, height = text_size(text, scale)  # aligned by the thin glyphs' width, whatever the thickness
    _, baseline = cv2.getTextSize(text, FONT, scale, thickness)
    left = x - width / 2 if align == "center" else x - width if align == "right" else x
    org = (int(round(left)), int(round(y)))
    cv2.putText(canvas, text, org, FONT, scale, color, thickness, cv2.LINE_AA)
    pad = thickness + 2  # anti-aliasing reaches a pixel or so past the metrics
    _record(TextItem(text, (int(round(x)), int(round(y))), align, float(scale), tuple(int(c) for c in color),
                     (org[0] - pad, org[1] - height - pad, org[0] + width + pad, org[1] + baseline + pad)))


def put_vertical_text(canvas: np.ndarray, text: str, x_center: float, y: float, scale: float = 0.4,
                      color: tuple[int, int, int] = INK, align: str = "top") -> None:
    """``text`` rotated 90 degrees counter-clockwise, centred on column ``x_center``; its right end at row ``y``
    (``align="top"``) or its middle there (``align="center"``)."""
    width, height = text_size(text, scale)
    y_top = y - width / 2 if align == "center" else y
    patch = np.full((height + 6, width + 4, 3), 255, dtype=np.uint8)
    cv2.putText(patch, text, (2, height + 2), FONT, scale, (0, 0, 0), 1, cv2.LINE_AA)
    patch = cv2.rotate(patch, cv2.ROTATE_90_COUNTERCLOCKWISE)
    h, w = patch.shape[:2]
    x0 = int(round(x_center - w / 2))
    y0 = int(round(y_top))
    x1, y1 = min(canvas.shape[1], x0 + w), min(canvas.shape[0], y0 + h)
    if x0 < 0 or y0 < 0 or x1 <= x0 or y1 <= y0:
        return
    ink = 1.0 - patch[: y1 - y0, : x1 - x0, :1].astype(float) / 255.0
    region = canvas[y0:y1, x0:x1].astype(float)
    canvas[y0:y1, x0:x1] = np.round(region * (1 - ink) + np.asarray(color, dtype=float) * ink).astype(np.uint8)
    _record(TextItem(text, (int(round(x_center)), int(round(y))), align, float(scale), tuple(int(c) for c in color),
                     (x0, y0, x1, y1), rotated=True))
