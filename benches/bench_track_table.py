"""Tracking an object that slides and turns on a table, given each frame's
depth: the ``Tracker`` with the table's points dropped
(``EstimateSettings.support_plane``, the default) and kept.

    .venv/bin/python benches/bench_track_table.py [--frames 30] [--sequences 2]

Sequences: the eight training CAD parts of ``bench_confidence_cost.py``
(never YCB), each resting on a table at stress level ``on_table`` (the
table seen from 30–70° above, the mask grown 5 px onto it and around, 1/4
of the spilled pixels mixed), sliding 4 mm a frame along the table and
turning 1.5° a frame about its normal (at 30 fps: 12 cm/s, 45°/s); seeds
from 777950. Each frame is ``Tracker.update(cloud, depth=, K=)``. Printed
per mode: frames, the share right (ADD(-S) < 0.1 d), the median error,
how many frames were tracked and re-initialised (the tracked pose failed
its check: ``estimate`` ran again), the median time of a frame and of a
tracked frame, and the mean confidence.
"""

from __future__ import annotations

import argparse

import numpy as np
from bench_confidence_cost import SEED_BASE, tuning_parts
from edgepose.encoder import default_encoder
from edgepose.eval import pose_errors
from edgepose.eval.scenes import render_scene
from edgepose.settings import DEFAULT_SETTINGS
from edgepose.track import Tracker
from edgepose.views import rotation_about

#: Motion per frame along the table (metres) and about its normal (degrees).
STEP_M, TURN_DEG = 0.004, 1.5


def sequence(mesh, seed: int, frames: int) -> list:
    """The rendered frames of ``mesh`` sliding and turning on the table of
    the ``on_table`` scene of ``seed``."""
    first = render_scene(mesh, "on_table", seed)
    normal, _ = first.support
    across = np.cross(normal, [1.0, 0.0, 0.0])
    along = 0.6 * np.array([1.0, 0.0, 0.0]) + 0.8 * across / np.linalg.norm(across)  # in the table
    T0 = first.T_cam_obj
    centre = T0[:3, :3] @ mesh.bounding_box.centroid + T0[:3, 3]
    views = []
    for f in range(frames):
        R = rotation_about(normal, np.radians(TURN_DEG * f))
        T = np.eye(4)
        T[:3, :3] = R @ T0[:3, :3]
        T[:3, 3] = R @ (T0[:3, 3] - centre) + centre + STEP_M * f * along
        views.append(render_scene(mesh, "on_table", seed, T_cam_obj=T))
    return views


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--frames", type=int, default=30, help="frames per sequence")
    parser.add_argument("--sequences", type=int, default=2, help="sequences per part")
    args = parser.parse_args()
    encoder = default_encoder()
    modes = {"table dropped": True, "table kept": False}
    rows: dict[str, list] = {mode: [] for mode in modes}
    for k, _, mesh, codebook in tuning_parts(encoder):
        points, d = codebook.model.mesh_points, codebook.model.diameter
        for s in range(args.sequences):
            views = sequence(mesh, SEED_BASE + 50 + k * 100 + s, args.frames)
            for mode, plane in modes.items():
                tracker = Tracker(codebook, settings=DEFAULT_SETTINGS.with_(support_plane=plane), encoder=encoder)
                for view in views:
                    pose = tracker.update(view.cloud, depth=view.depth, K=view.K, depth_scale=1.0)
                    error = pose_errors(points, pose.matrix, view.T_cam_obj, d, codebook.symmetry.symmetric).add_or_s
                    rows[mode].append((pose.mode, error / d, 1e3 * pose.timings["total"], pose.confidence))
    print(f"{len(rows['table dropped'])} frames a mode ({args.sequences} sequences of {args.frames} frames × 8 parts)")
    print("| mode | right | median error (d) | tracked | re-initialised | median ms | tracked ms | mean confidence |")
    print("| --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: |")
    for mode, r in rows.items():
        tracked = [x[2] for x in r if x[0] == "tracked"]
        print(
            f"| {mode} | {np.mean([x[1] < 0.1 for x in r]):.1%} | {np.median([x[1] for x in r]):.4f} "
            f"| {len(tracked)} | {sum(x[0] == 'reinitialised' for x in r)} | {np.median([x[2] for x in r]):.2f} "
            f"| {np.median(tracked) if tracked else float('nan'):.2f} | {np.mean([x[3] for x in r]):.3f} |"
        )


if __name__ == "__main__":
    main()
