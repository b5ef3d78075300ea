"""Stress levels of the pose benchmark: what the scene, the sensor and the
detector mask do to an object's cloud (rendered by
:func:`edgepose.eval.scenes.render_scene`).

Units are metres and pixels, as each field says.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Stress:
    """One stress level of the pose benchmark: what the scene, the sensor and
    the detector mask do to the object's cloud."""

    name: str
    """Short identifier (``STRESS_LEVELS`` key)."""
    description: str = ""
    """One line for reports."""
    visible: float = 1.0
    """Target fraction (0–1) of the object's own pixels left visible by the occluder; 1: no occluder."""
    spill_px: int = 0
    """Pixels (Euclidean disk radius) by which the detector mask grows over the background."""
    erode_px: int = 0
    """Pixels (Euclidean disk radius) by which the detector mask shrinks into the object."""
    cut: float = 0.0
    """Fraction (0–1) of the object's visible pixels the detector misses, cut off by a
    half-plane of random direction."""
    flying: float = 0.0
    """Fraction (0–1) of the spilled pixels that are mixed ("flying") pixels, with a depth between the
    object's and the background's."""
    noise: str = "constant"
    """Depth-noise model: ``"constant"`` (std ``depth_noise``) or ``"kinect"`` (std
    0.0012 + 0.0019·(z − 0.4)² m, Nguyen et al. 2012)."""
    depth_noise: float = 0.001
    """Metres: std of the ``"constant"`` model's Gaussian depth noise."""
    lateral_px: float = 0.0
    """Pixels: std of the lateral jitter of every pixel's depth sample (moves depth edges)."""
    distance: tuple[float, float] = (0.45, 0.9)
    """Metres: range of the object's centre depth."""
    quantization: float = 0.001
    """Metres: depth is rounded to multiples of this."""
    dropout: float = 0.02
    """Probability (0–1) that a pixel has no measurement."""
    holes: float = 0.0
    """Fraction (0–1) of the object's visible pixels with no measurement, in ``HOLE_PATCHES`` round
    patches about random points of it: a dark or shiny part of the surface."""
    grazing_deg: float = 90.0
    """Degrees: pixels whose surface (any surface of the scene) is seen farther than this from face-on
    have no measurement, as a real sensor loses depth on steep faces and at depth edges; 90: none lost."""
    resting: bool = False
    """Whether the object rests on the support plane, a table seen from ``TABLE_ELEVATION_DEG`` above,
    in one of its stable poses (given a pose: touching the plane at its lowest point), instead of
    standing 2–6 cm in front of a wall: a spilled mask then takes table points that meet the object."""
    background: bool = True
    """Whether a support plane and 1–3 neighbouring objects are rendered; ``False`` (only with no other
    stress) renders exactly :func:`edgepose.eval.render_view`'s view."""

    def __post_init__(self) -> None:
        if self.noise not in ("constant", "kinect"):
            raise ValueError(f"unknown noise model {self.noise!r}; use 'constant' or 'kinect'")
        plain = (
            self.visible >= 1.0
            and not (
                self.spill_px
                or self.erode_px
                or self.cut
                or self.flying
                or self.lateral_px
                or self.holes
                or self.resting
            )
            and self.grazing_deg >= 90.0
            and self.noise == "constant"
        )
        if not (self.background or plain):
            raise ValueError("background=False renders render_view's plain view: no other stress allowed")


#: Patches of a level's ``holes``.
HOLE_PATCHES = 3
#: Degrees: range of the angle between the camera's line of sight to a ``resting`` object and the table.
TABLE_ELEVATION_DEG = (30.0, 70.0)

#: The benchmark's stress levels, in report order.
STRESS_LEVELS: dict[str, Stress] = {
    s.name: s
    for s in [
        Stress(
            "clean", "fully visible, perfect mask, 1 mm noise, no background (render_view's view)", background=False
        ),
        Stress("visible70", "solid occluder in front, 70 % of the object visible", visible=0.7),
        Stress("visible40", "solid occluder in front, 40 % of the object visible", visible=0.4),
        Stress("visible20", "solid occluder in front, 20 % of the object visible", visible=0.2),
        Stress("spill2", "mask grown 2 px over the background; 1/4 of spilled pixels mixed", spill_px=2, flying=0.25),
        Stress("spill5", "mask grown 5 px over the background; 1/4 of spilled pixels mixed", spill_px=5, flying=0.25),
        Stress("spill8", "mask grown 8 px over the background; 1/4 of spilled pixels mixed", spill_px=8, flying=0.25),
        Stress("eroded3", "mask eroded by 3 px", erode_px=3),
        Stress("partial", "detector misses a half-plane cut of 25 % of the object's pixels", cut=0.25),
        Stress(
            "noise_far",
            "object 1.0-1.5 m away, Kinect noise 0.0012 + 0.0019 (z-0.4)^2 m, 0.8 px lateral jitter",
            noise="kinect",
            lateral_px=0.8,
            distance=(1.0, 1.5),
        ),
        Stress(
            "occluded30_spill5", "70 % visible and mask grown 5 px (1/4 mixed)", visible=0.7, spill_px=5, flying=0.25
        ),
        Stress(
            "sensor_holes",
            "15 % of the object without depth in 3 patches (dark or shiny); no depth beyond 75° from face-on",
            holes=0.15,
            grazing_deg=75.0,
        ),
        Stress(
            "on_table",
            "resting on a table seen from 30-70° above; mask grown 5 px onto the table and around (1/4 mixed)",
            resting=True,
            spill_px=5,
            flying=0.25,
        ),
    ]
}


def noise_sigma(stress: Stress, z: np.ndarray) -> np.ndarray:
    """Std (metres) of the depth noise of ``stress``'s model at depths ``z`` (metres)."""
    z = np.asarray(z, dtype=np.float64)
    return 0.0012 + 0.0019 * (z - 0.4) ** 2 if stress.noise == "kinect" else np.full(z.shape, stress.depth_noise)
