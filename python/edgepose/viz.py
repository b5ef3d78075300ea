"""Pictures of a pose estimate that a person can judge at a glance, and
optional live logging to the rerun viewer.

:func:`draw_result` overlays the observed points (blue) and the model posed
by the estimate (orange) in three panels: the camera's view (projected with
the real intrinsics over the depth image when they are known), a view from
above and a view from the side, with the error against the truth when it is
known. Pure numpy z-buffer splatting; pillow writes the PNG and the text.

:func:`recorder` returns a rerun logger, or a no-op one when rerun is not
wanted or not installed (the ``viz`` extra), chosen once so callers never
branch on "visualise?".

Units are metres; camera frames follow OpenCV (x right, y down, z forward).
"""

from __future__ import annotations

import os
import sys
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol

import numpy as np

#: Colours (RGB) of the observed points and of the model at the estimate.
OBSERVED = (70, 160, 255)
MODEL = (255, 140, 30)
BACKGROUND = (24, 24, 28)
PANEL = 300
HEADER = 64


@dataclass(frozen=True)
class Frame:
    """What one picture shows: a cloud, the model points posed by ``T_est``,
    and optionally the truth, the camera and its depth image."""

    cloud: np.ndarray
    """(N, 3) observed points, camera frame, metres."""
    model_points: np.ndarray
    """(M, 3) model surface points, object (mesh) frame, metres."""
    T_est: np.ndarray
    """(4, 4) estimated T_cam_obj."""
    K: np.ndarray | None = None
    """(3, 3) intrinsics, when the cloud came from a depth image."""
    depth: np.ndarray | None = None
    """(H, W) depth image (any units; only its shading is drawn)."""


def draw_result(frame: Frame, lines: Sequence[str] = ()) -> np.ndarray:
    """(H, W, 3) uint8 picture of ``frame``: a header with ``lines`` of text
    and a legend, then the camera, top and side panels."""
    cloud = np.asarray(frame.cloud, dtype=np.float64)
    T = np.asarray(frame.T_est, dtype=np.float64)
    model = np.asarray(frame.model_points, dtype=np.float64) @ T[:3, :3].T + T[:3, 3]
    panels = [
        _camera_panel(cloud, model, frame.K, frame.depth),
        # From above (−y): x to the right, far (z) up; nearer the viewer = smaller y.
        _ortho_panel(cloud, model, horizontal=(0, 1.0), vertical=(2, -1.0), toward_viewer=(1, -1.0)),
        # From the camera's right (+x): depth z to the right, y down; nearer = larger x.
        _ortho_panel(cloud, model, horizontal=(2, 1.0), vertical=(1, 1.0), toward_viewer=(0, 1.0)),
    ]
    titles = ["camera view", "from above (x right, depth up)", "from the side (depth right, y down)"]
    image = np.full((HEADER + PANEL, PANEL * len(panels) + 2 * (len(panels) - 1), 3), 60, np.uint8)
    for i, panel in enumerate(panels):
        image[HEADER:, i * (PANEL + 2) : i * (PANEL + 2) + PANEL] = panel
    return _annotate(image, list(lines), titles, len(cloud))


def save_result_png(path: str | os.PathLike, frame: Frame, lines: Sequence[str] = ()) -> Path:
    """Write :func:`draw_result` as a PNG; returns the path."""
    from edgepose.io import write_png

    path = Path(path)
    write_png(path, draw_result(frame, lines))
    return path


def _camera_panel(cloud: np.ndarray, model: np.ndarray, K: np.ndarray | None, depth: np.ndarray | None) -> np.ndarray:
    """Perspective view from the camera, cropped to the object: real pixels
    (and the depth image behind) when K is known, else a virtual camera."""
    virtual = K is None
    if K is None:
        z = float(np.median(cloud[:, 2]))
        K = np.array([[PANEL * z, 0, 0], [0, PANEL * z, 0], [0, 0, 1.0]])  # 1 m at 1 m ≈ one panel
    both = np.concatenate([cloud, model])
    front = both[:, 2] > 1e-6
    uv = (both[front] @ K.T)[:, :2] / both[front, 2:3]
    lo, hi = np.percentile(uv, 1, axis=0), np.percentile(uv, 99, axis=0)
    centre, half = (lo + hi) / 2, max(float((hi - lo).max()) * 0.65, 8.0)
    scale = PANEL / (2 * half)
    origin = centre - half  # image pixel at the panel's top-left corner
    panel = np.empty((PANEL, PANEL, 3), np.uint8)
    panel[:] = BACKGROUND
    if depth is not None and not virtual:
        _draw_depth(panel, np.asarray(depth, dtype=np.float64), origin, scale)

    def to_panel(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        keep = points[:, 2] > 1e-6
        p = points[keep]
        pix = ((p @ K.T)[:, :2] / p[:, 2:3] - origin) * scale
        return pix, p[:, 2]

    # The observed surface, then the model's camera-facing points as dots on top:
    # where the estimate is right, the dots sit on the observed shape.
    _splat(panel, [to_panel(cloud)], [OBSERVED])
    pix, depth = to_panel(model)
    front = _visible(pix, depth, radius=3, tolerance=0.05 * float(np.ptp(depth) + 1e-9))
    _splat(panel, [(pix[front], depth[front])], [MODEL], radius=0, shade=False)
    panel[_outline(pix, radius=3)] = MODEL
    return panel


def _outline(pix: np.ndarray, radius: int) -> np.ndarray:
    """(PANEL, PANEL) bool: the 2-pixel border of the region the points cover
    (each point widened to a square of ``radius``)."""
    covered = np.zeros((PANEL + 2 * radius + 2, PANEL + 2 * radius + 2), bool)
    base = np.round(pix).astype(np.int64) + radius + 1
    ok = (base >= radius).all(axis=1) & (base < PANEL + radius + 2).all(axis=1)
    for dy in range(-radius, radius + 1):
        for dx in range(-radius, radius + 1):
            covered[base[ok, 1] + dy, base[ok, 0] + dx] = True
    inner = covered.copy()
    for _ in range(2):  # erode twice by a 3×3 cross
        inner[1:-1, 1:-1] &= inner[:-2, 1:-1] & inner[2:, 1:-1] & inner[1:-1, :-2] & inner[1:-1, 2:]
    border = covered & ~inner
    return border[radius + 1 : radius + 1 + PANEL, radius + 1 : radius + 1 + PANEL]


def _visible(pix: np.ndarray, depth: np.ndarray, radius: int, tolerance: float) -> np.ndarray:
    """Mask of points within ``tolerance`` of the nearest depth splatted
    (squares of ``radius``) on their pixel: the surface facing the viewer."""
    base = np.round(pix).astype(np.int64)
    inside = (base >= 0).all(axis=1) & (base < PANEL).all(axis=1)
    zbuffer = np.full(PANEL * PANEL, np.inf)
    for dy in range(-radius, radius + 1):
        for dx in range(-radius, radius + 1):
            p = base + (dx, dy)
            ok = (p >= 0).all(axis=1) & (p < PANEL).all(axis=1)
            np.minimum.at(zbuffer, p[ok, 1] * PANEL + p[ok, 0], depth[ok])
    flat = np.clip(base[:, 1], 0, PANEL - 1) * PANEL + np.clip(base[:, 0], 0, PANEL - 1)
    return inside & (depth <= zbuffer[flat] + tolerance)


def _ortho_panel(cloud, model, horizontal, vertical, toward_viewer) -> np.ndarray:
    """Orthographic view: panel axes are camera axes (index, sign); nearer
    the viewer along ``toward_viewer`` hides what is behind."""
    (h, hs), (v, vs), (d, ds) = horizontal, vertical, toward_viewer
    both = np.concatenate([cloud, model])
    coords = np.stack([hs * both[:, h], vs * both[:, v]], axis=1)
    lo, hi = np.percentile(coords, 1, axis=0), np.percentile(coords, 99, axis=0)
    centre, half = (lo + hi) / 2, max(float((hi - lo).max()) * 0.65, 1e-3)
    scale = PANEL / (2 * half)

    def to_panel(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        pix = (np.stack([hs * points[:, h], vs * points[:, v]], axis=1) - centre + half) * scale
        return pix, -ds * points[:, d]  # smaller = nearer the viewer

    panel = np.empty((PANEL, PANEL, 3), np.uint8)
    panel[:] = BACKGROUND
    return _splat(panel, [to_panel(cloud), to_panel(model)], [OBSERVED, MODEL])


def _splat(
    panel: np.ndarray,
    layers: list[tuple[np.ndarray, np.ndarray]],
    colours: list[tuple[int, int, int]],
    radius: int = 1,
    shade: bool = True,
) -> np.ndarray:
    """Draw points as (2·radius+1)² squares with a z-buffer (smaller depth
    wins), shaded darker with distance so the shape reads."""
    pixels, depths, colour_index = [], [], []
    offsets = [(dx, dy) for dy in range(-radius, radius + 1) for dx in range(-radius, radius + 1)]
    for k, (pix, depth) in enumerate(layers):
        base = np.round(pix).astype(np.int64)
        for dx, dy in offsets:
            pixels.append(base + (dx, dy))
            depths.append(depth)
            colour_index.append(np.full(len(depth), k))
    if not pixels:
        return panel
    pix, depth, which = np.concatenate(pixels), np.concatenate(depths), np.concatenate(colour_index)
    inside = (pix[:, 0] >= 0) & (pix[:, 0] < PANEL) & (pix[:, 1] >= 0) & (pix[:, 1] < PANEL)
    pix, depth, which = pix[inside], depth[inside], which[inside]
    if len(depth) == 0:
        return panel
    flat = pix[:, 1] * PANEL + pix[:, 0]
    order = np.lexsort((depth, flat))  # per pixel, nearest first
    first = np.ones(len(order), bool)
    first[1:] = flat[order][1:] != flat[order][:-1]
    chosen = order[first]
    near, far = np.percentile(depth, 2), np.percentile(depth, 98)
    factor = (
        1.0 - 0.55 * np.clip((depth[chosen] - near) / max(far - near, 1e-9), 0, 1) if shade else np.ones(len(chosen))
    )
    rgb = np.asarray(colours, dtype=np.float64)[which[chosen]] * factor[:, None]
    panel.reshape(-1, 3)[flat[chosen]] = rgb.astype(np.uint8)
    return panel


def _draw_depth(panel: np.ndarray, depth: np.ndarray, origin: np.ndarray, scale: float) -> None:
    """The depth image behind the points, grey (near = lighter), resampled to the crop."""
    height, width = depth.shape
    grid = np.arange(PANEL) / scale
    cols = np.floor(origin[0] + grid).astype(np.int64)
    rows = np.floor(origin[1] + grid).astype(np.int64)
    valid_c, valid_r = (cols >= 0) & (cols < width), (rows >= 0) & (rows < height)
    crop = np.zeros((PANEL, PANEL))
    crop[np.ix_(valid_r, valid_c)] = depth[np.ix_(rows[valid_r], cols[valid_c])]
    seen = np.isfinite(crop) & (crop > 0)
    if not seen.any():
        return
    near, far = np.percentile(crop[seen], 1), np.percentile(crop[seen], 99)
    grey = 110 - 70 * np.clip((crop - near) / max(far - near, 1e-9), 0, 1)
    panel[seen] = grey[seen, None].astype(np.uint8)


def _annotate(image: np.ndarray, lines: list[str], titles: list[str], n_points: int) -> np.ndarray:
    from PIL import Image, ImageDraw, ImageFont

    picture = Image.fromarray(image)
    draw = ImageDraw.Draw(picture)
    font = _font(ImageFont, 13)
    small = _font(ImageFont, 11)
    for i, text in enumerate(lines[:3]):
        draw.text((8, 4 + 16 * i), text, fill=(235, 235, 235), font=font)
    x = image.shape[1] - 250
    draw.rectangle((x, 8, x + 10, 18), fill=OBSERVED)
    draw.text((x + 16, 5), f"observed points ({n_points})", fill=(235, 235, 235), font=font)
    draw.rectangle((x, 28, x + 10, 38), fill=MODEL)
    draw.text((x + 16, 25), "model at the estimated pose", fill=(235, 235, 235), font=font)
    for i, title in enumerate(titles):
        draw.text((i * (PANEL + 2) + 6, HEADER + 4), title, fill=(200, 200, 200), font=small)
    return np.asarray(picture)


def _font(image_font, size: int):
    try:
        return image_font.load_default(size=size)
    except TypeError:  # pillow < 10.1: one bitmap size
        return image_font.load_default()


# ----------------------------------------------------------------- rerun


class Recorder(Protocol):
    """Something that logs frames: rerun, or nothing."""

    def log(self, name: str, frame: Frame) -> None: ...


class NullRecorder:
    """Logs nothing."""

    def log(self, name: str, frame: Frame) -> None:
        pass


class RerunRecorder:
    """Logs each frame to rerun: the observed points, the model points under
    the estimated pose (as a transform), and the camera with its depth image.
    Entities are in the camera frame (OpenCV: right, down, forward)."""

    def __init__(self, spawn: bool = False, save: str | os.PathLike | None = None) -> None:
        import rerun as rr

        self._rr = rr
        rr.init("edgepose", spawn=spawn)
        if save is not None:
            rr.save(str(save))
        rr.log("camera", rr.ViewCoordinates.RDF, static=True)

    def log(self, name: str, frame: Frame) -> None:
        rr = self._rr
        T = np.asarray(frame.T_est, dtype=np.float64)
        rr.log(f"camera/{name}/observed", rr.Points3D(np.asarray(frame.cloud, np.float32), colors=[OBSERVED]))
        rr.log(f"camera/{name}/estimate", rr.Transform3D(translation=T[:3, 3], mat3x3=T[:3, :3]))
        rr.log(
            f"camera/{name}/estimate/model",
            rr.Points3D(np.asarray(frame.model_points, np.float32), colors=[MODEL], radii=0.001),
        )
        if frame.K is not None and frame.depth is not None:
            height, width = np.shape(frame.depth)
            rr.log(f"camera/{name}/image", rr.Pinhole(image_from_camera=frame.K, width=width, height=height))
            rr.log(f"camera/{name}/image/depth", rr.DepthImage(np.asarray(frame.depth)))


def recorder(spawn: bool = False, save: str | os.PathLike | None = None) -> Recorder:
    """A :class:`RerunRecorder` when asked for (``spawn`` a viewer and/or
    ``save`` a ``.rrd`` recording) and rerun is installed (``pip install
    'edgepose[viz]'``); otherwise a :class:`NullRecorder` (with a warning on
    stderr when rerun was asked for but is missing)."""
    if not (spawn or save):
        return NullRecorder()
    try:
        return RerunRecorder(spawn=spawn, save=save)
    except ImportError:
        print("warning: rerun logging needs the viz extra (pip install 'edgepose[viz]'); not logging", file=sys.stderr)
        return NullRecorder()


def save_reliability_png(path: str | os.PathLike, groups: dict[str, tuple[np.ndarray, np.ndarray]]) -> Path:
    """A reliability diagram: per group (label → (confidences, correct)), the
    share of correct poses against the mean confidence in 10 bins; a
    calibrated confidence lies on the diagonal. Needs only numpy and pillow."""
    from PIL import Image, ImageDraw, ImageFont

    from edgepose.eval.metrics import auroc, calibration

    size, left, top, right, bottom = 560, 70, 40, 20, 60
    width, height = size - left - right, size - top - bottom
    picture = Image.new("RGB", (size, size), (255, 255, 255))
    draw = ImageDraw.Draw(picture)
    font, small = _font(ImageFont, 13), _font(ImageFont, 11)

    def xy(confidence: float, share: float) -> tuple[float, float]:
        return left + confidence * width, top + (1.0 - share) * height

    for tick in np.linspace(0.0, 1.0, 6):
        draw.line([xy(tick, 0), xy(tick, 1)], fill=(230, 230, 230))
        draw.line([xy(0, tick), xy(1, tick)], fill=(230, 230, 230))
        draw.text((xy(tick, 0)[0] - 8, top + height + 6), f"{tick:.1f}", fill=(60, 60, 60), font=small)
        draw.text((left - 30, xy(0, tick)[1] - 7), f"{tick:.1f}", fill=(60, 60, 60), font=small)
    draw.rectangle([xy(0, 1), xy(1, 0)], outline=(60, 60, 60))
    for a in np.linspace(0.0, 0.96, 25):  # the calibrated diagonal, dashed
        draw.line([xy(a, a), xy(a + 0.02, a + 0.02)], fill=(140, 140, 140), width=1)
    colours = [(31, 119, 180), (255, 127, 14), (44, 160, 44), (214, 39, 40), (148, 103, 189)]
    for g, (label, (p, y)) in enumerate(groups.items()):
        colour = colours[g % len(colours)]
        c = calibration(p, y)
        points = [xy(m, a) for m, a, n in zip(c.mean_confidence, c.accuracy, c.count) if n > 0]
        if len(points) > 1:
            draw.line(points, fill=colour, width=2)
        for px, py in points:
            draw.ellipse([px - 4, py - 4, px + 4, py + 4], fill=colour)
        legend_y = top + 8 + 18 * g
        draw.rectangle([left + 8, legend_y + 3, left + 18, legend_y + 13], fill=colour)
        area = auroc(p, y)
        ranking = f"AUROC {area:.3f}" if np.isfinite(area) else "AUROC – (all right or all wrong)"
        text = f"{label}: {len(p)} poses, {ranking}, ECE {c.ece:.3f}"
        draw.text((left + 24, legend_y), text, fill=(30, 30, 30), font=small)
    draw.text((left, 12), "Reliability of Pose.confidence (diagonal: calibrated)", fill=(0, 0, 0), font=font)
    draw.text((left + width / 2 - 90, size - 28), "confidence (mean per bin)", fill=(0, 0, 0), font=font)
    axis_label = Image.new("RGB", (height, 18), (255, 255, 255))
    ImageDraw.Draw(axis_label).text((40, 2), "share correct, ADD(-S) < 0.1 d", fill=(0, 0, 0), font=font)
    picture.paste(axis_label.rotate(90, expand=True), (4, top))
    path = Path(path)
    picture.save(path)
    return path
