"""The simulated depth sensor and detector of the stressed scenes
(:func:`edgepose.eval.scenes.render_scene`): lateral jitter and axial noise,
mixed pixels where the mask spills, quantisation, dropout, grazing-angle
loss and holes; the detector's spilled, eroded or cut mask. Depths in metres
(inf: nothing there), images (H, W), every random draw from the scene's
generator, in the scene's order.
"""

from __future__ import annotations

import numpy as np

from edgepose.cloud import dilate, erode
from edgepose.eval.render import Camera
from edgepose.eval.stress import HOLE_PATCHES, Stress, noise_sigma


def sensed(
    z_scene: np.ndarray, stress: Stress, camera: Camera, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray]:
    """The sensor's depth of the scene (metres, inf: none) after lateral
    jitter of its samples and axial noise, and where it measured."""
    depth = z_scene.copy()
    if stress.lateral_px > 0:
        jitter = np.clip(np.rint(rng.normal(0.0, stress.lateral_px, size=(2, *depth.shape))), -2, 2).astype(int)
        r = np.clip(np.arange(camera.height)[:, None] + jitter[0], 0, camera.height - 1)
        c = np.clip(np.arange(camera.width)[None, :] + jitter[1], 0, camera.width - 1)
        depth = depth[r, c]
    measured = np.isfinite(depth)
    depth[measured] += rng.normal(size=int(measured.sum())) * noise_sigma(stress, depth[measured])
    return depth, measured


def detector_mask(visible: np.ndarray, stress: Stress, camera: Camera, rng: np.random.Generator) -> np.ndarray:
    """The detector's mask: the ``visible`` pixels spilled, eroded and/or cut
    along a random direction, as ``stress`` says."""
    mask = visible.copy()
    if stress.spill_px > 0:
        mask = dilate(mask, stress.spill_px)
    if stress.erode_px > 0:
        mask = erode(mask, stress.erode_px)
    if stress.cut > 0 and visible.any():
        angle = rng.uniform(0, 2 * np.pi)
        rows, cols = np.nonzero(visible)
        along = lambda r, c: c * np.cos(angle) + r * np.sin(angle)  # noqa: E731
        threshold = np.quantile(along(rows, cols), 1.0 - stress.cut)
        rr, cc = np.mgrid[0 : camera.height, 0 : camera.width]
        mask &= along(rr, cc) <= threshold
    return mask


def mix_spill_ring(
    depth: np.ndarray,
    mask: np.ndarray,
    visible: np.ndarray,
    measured: np.ndarray,
    z_obj: np.ndarray,
    stress: Stress,
    rng: np.random.Generator,
) -> np.ndarray:
    """Mixed ("flying") pixels: ``stress.flying`` of the measured pixels the
    mask spilled onto get a depth between the object's and theirs (``depth``
    changed in place); returns where they are."""
    ring = mask & ~visible & measured
    flying = np.zeros_like(mask)
    if stress.flying > 0 and ring.any():
        near_obj = spread(np.where(visible, z_obj, np.inf), max(stress.spill_px, 1))
        candidates = np.flatnonzero(ring & np.isfinite(near_obj))
        picked = rng.choice(candidates, int(round(stress.flying * len(candidates))), replace=False)
        flying.flat[picked] = True
        alpha = rng.uniform(0.1, 0.9, size=len(picked))
        fg = near_obj.flat[picked]
        depth.flat[picked] = fg + alpha * (depth.flat[picked] - fg)
    return flying


def recorded(
    depth: np.ndarray,
    measured: np.ndarray,
    ideal: np.ndarray,
    rays: np.ndarray,
    visible: np.ndarray,
    stress: Stress,
    rng: np.random.Generator,
) -> tuple[np.ndarray, np.ndarray]:
    """What the sensor records of ``depth``: quantised, with dropout, the
    pixels seen at a grazing angle (from the noise-free ``ideal`` depth and
    the pixels' ``rays``) and round holes in the ``visible`` object lost;
    (float32 depth, 0 where not measured; where measured)."""
    if stress.quantization > 0:
        depth[measured] = np.round(depth[measured] / stress.quantization) * stress.quantization
    if stress.dropout > 0:
        measured &= rng.random(depth.shape) >= stress.dropout
    if stress.grazing_deg < 90.0:
        measured &= viewing_angle(ideal, rays) <= stress.grazing_deg
    if stress.holes > 0 and visible.sum() >= HOLE_PATCHES:
        measured &= ~holes(visible, stress.holes, rng)
    measured &= (depth > 0) & (depth < 65.535)
    return np.where(measured, depth, 0.0).astype(np.float32), measured


def viewing_angle(z: np.ndarray, rays: np.ndarray) -> np.ndarray:
    """(H, W) degrees between each pixel's viewing ray (``rays``, (H, W, 3)
    at z = 1) and the surface's normal there, from the noise-free depth
    ``z`` (metres, inf where empty) by central differences of the
    back-projected points: near 90 at a depth edge, where the difference
    spans two surfaces; 90 where a neighbour is empty."""
    with np.errstate(invalid="ignore"):
        points = rays * z.astype(np.float64)[..., None]
        along_v, along_u = np.gradient(points, axis=(0, 1))
        normal = np.cross(along_u, along_v)
        cos = np.abs((normal * rays).sum(-1)) / (np.linalg.norm(normal, axis=-1) * np.linalg.norm(rays, axis=-1))
    return np.degrees(np.arccos(np.clip(np.nan_to_num(cos, nan=0.0), 0.0, 1.0)))


def holes(visible: np.ndarray, fraction: float, rng: np.random.Generator) -> np.ndarray:
    """(H, W) bool: ``fraction`` of the ``visible`` pixels, those nearest to
    ``HOLE_PATCHES`` of them drawn at random: round patches."""
    rows, cols = np.nonzero(visible)
    picked = rng.choice(len(rows), HOLE_PATCHES, replace=False)
    distance = np.min(np.hypot(rows[:, None] - rows[picked], cols[:, None] - cols[picked]), axis=1)
    hole = np.zeros_like(visible)
    lost = distance <= np.quantile(distance, fraction)
    hole[rows[lost], cols[lost]] = True
    return hole


def spread(z: np.ndarray, steps: int) -> np.ndarray:
    """``z`` (inf where empty) with empty pixels filled, ``steps`` times, by
    the nearest-to-camera value of their 8 neighbours."""
    out, (h, w) = z.copy(), z.shape
    for _ in range(steps):
        padded = np.pad(out, 1, constant_values=np.inf)
        best = np.min(
            [padded[1 + dy : 1 + dy + h, 1 + dx : 1 + dx + w] for dy in (-1, 0, 1) for dx in (-1, 0, 1)], axis=0
        )
        out = np.where(np.isfinite(out), out, best)
    return out
