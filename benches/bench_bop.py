"""BOP benchmark on a synthetic BOP-format dataset of the shared YCB meshes:
per-image time of ``edgepose.estimate_many`` for 8 objects against
``edgepose.estimate`` called per object (the same process, the same
images), and the BOP score (AR of VSD, MSSD, MSPD; ADD(-S)) as ``edgepose
bop`` computes it.

    .venv/bin/python benches/bench_bop.py [--scenes 2] [--images 10] [--objects 8] [--out benches/BOP.md]
    .venv/bin/python benches/bench_bop.py --timing-only [--layouts crowded]   # the times alone, in seconds

Datasets (written once to ``benches/.cache/``, not committed): the five
shared YCB meshes as BOP objects (YCB-V ids; symmetries as edgepose detects
them), ``--scenes`` × ``--images`` frames of ``--objects`` instances each
(object ids cycled, so most frames hold an object twice) at 0.7–1.0 m, on a
ring around the image centre in front of a tilted plane, hiding one another
where they overlap: two layouts, ``spread`` (mild occlusion) and
``crowded`` (the ring ~⅓ as wide: heavy occlusion); LINEMOD camera, 1 mm depth noise and steps, 1 %
dropout. Targets: every instance at least 10 % visible (BOP's rule).

Stress levels reported: ``masks exact`` (the annotated visible masks) and
``masks spill 5 px`` (each mask dilated by 5 pixels onto its neighbours and
the background, as a detector's). Times: median and 90th percentile per
image, estimation only (images are read from disk before the clock starts).
"""

from __future__ import annotations

import argparse
import datetime
import os
import platform
import time
from pathlib import Path

import edgepose
import numpy as np
from edgepose.cloud import dilate
from edgepose.eval.bop import YCBV_OBJ_ID, BopDataset
from edgepose.eval.bop_run import Detection, bop_codebooks, encode_rle, run_bop
from edgepose.eval.bop_scenes import write_bop_dataset
from edgepose.eval.bop_score import score_bop
from edgepose.model import load_model, read_mesh

REPO = Path(__file__).resolve().parents[1]
YCB = REPO.parent / "shared" / "data" / "ycb"
CACHE = REPO / "benches" / ".cache"
SPILL_PX = 5


#: Scene layouts: the ring (fractions of the image size) the objects are spread on.
LAYOUTS = {"spread": (0.18, 0.3), "crowded": (0.06, 0.14)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--scenes", type=int, default=2)
    parser.add_argument("--images", type=int, default=10, help="images per scene")
    parser.add_argument("--objects", type=int, default=8, help="object instances per image")
    parser.add_argument("--repeats", type=int, default=3, help="timed runs of each image per method (median kept)")
    parser.add_argument("--out", type=Path, default=REPO / "benches" / "BOP.md")
    parser.add_argument("--layouts", nargs="+", choices=sorted(LAYOUTS), default=list(LAYOUTS))
    parser.add_argument(
        "--timing-only", action="store_true", help="time the methods and print their tables; no scores, no file"
    )
    args = parser.parse_args()
    load_before = os.getloadavg()
    started = time.perf_counter()
    names = {v: k for k, v in YCBV_OBJ_ID.items()}
    sections = []
    for layout in args.layouts:
        spread = LAYOUTS[layout]
        dataset = _dataset(args, layout, spread)
        targets = dataset.targets()
        books = bop_codebooks(dataset, {t.obj_id for t in targets}, CACHE / "ycbsyn_codebooks")
        times, cpu, counts = _time_images(dataset, targets, books, args.repeats)
        baseline = np.median(times["estimate"])
        timing_rows = [
            f"| {name} | {1000 * np.median(ts):.1f} | {1000 * np.percentile(ts, 90):.1f} | "
            f"{baseline / np.median(ts):.2f}× | {1000 * np.median(cpu[name]):.1f} |"
            for name, ts in times.items()
        ]
        timing_table = f"""| method | median ms | p90 ms | speed-up vs estimate | CPU ms |
| --- | ---: | ---: | ---: | ---: |
{chr(10).join(timing_rows)}"""
        if args.timing_only:
            print(f"{layout}: {len(counts)} images, {np.median(counts):.0f} objects each (median)\n{timing_table}\n")
            continue
        scores = {}
        for level, detections in (("masks exact", None), (f"masks spill {SPILL_PX} px", _spilled(dataset, targets))):
            rows = run_bop(dataset, targets, books, detections=detections)
            scores[level] = score_bop(dataset, rows, targets)
        score_rows = []
        for level, s in scores.items():
            for obj_id, o in sorted(s.objects.items()):
                score_rows.append(_score_row(level, f"{names.get(obj_id, obj_id)} ({obj_id})", o))
            score_rows.append(_score_row(level, "**all**", s.overall))
        visib = [g.visib_fract for t in targets for g in dataset.image(t.scene_id, t.im_id).gts if g.obj_id == t.obj_id]
        sections.append(f"""## Layout `{layout}`: objects on a ring of {spread[0]:.2f}–{spread[1]:.2f} × the image size

{len(counts)} images, {np.median(counts):.0f} objects estimated per image (median; {min(counts)}–{max(counts)}),
{sum(t.inst_count for t in targets)} targets; visible fraction of the targets: median {np.median(visib):.2f},
10th percentile {np.percentile(visib, 10):.2f}.

### Per-image time (masks exact)

`estimate`: each object's cloud and the frame (`depth=`, `K=`), one object after another.
CPU ms: the process's CPU time an image (all its threads; median).

{timing_table}

### BOP score (%)

| stress | object | targets | AR | AR_VSD | AR_MSSD | AR_MSPD | ADD(-S) |
| --- | --- | ---: | ---: | ---: | ---: | ---: | ---: |
{chr(10).join(score_rows)}
""")
    if args.timing_only:
        return
    text = f"""# BOP benchmark (synthetic YCB scenes)

Generated by `benches/bench_bop.py`; do not edit by hand.

```bash
.venv/bin/python benches/bench_bop.py --scenes {args.scenes} --images {args.images} --objects {args.objects} \\
    --repeats {args.repeats}
```

- date: {datetime.datetime.now().astimezone().strftime("%Y-%m-%d %H:%M %Z")}
- machine: {platform.machine()}, {os.cpu_count()} CPUs; edgepose {edgepose.__version__}
- load average (1 min) before: {load_before[0]:.2f}, after: {os.getloadavg()[0]:.2f}
- wall time: {(time.perf_counter() - started) / 60:.1f} min

{__doc__.split(chr(10) + chr(10), 1)[1]}
{chr(10).join(sections)}"""
    args.out.write_text(text)
    print(text)
    print(f"wrote {args.out}")


def _dataset(args: argparse.Namespace, layout: str, spread: tuple[float, float]) -> BopDataset:
    """The layout's synthetic dataset, written once into the cache."""
    root = CACHE / f"ycbsyn_{layout}_{args.scenes}x{args.images}x{args.objects}"
    if not (root / "test_targets_bop19.json").is_file():
        meshes = {YCBV_OBJ_ID[p.stem]: read_mesh(p) for p in sorted(YCB.glob("*.ply"))}
        symmetries = {i: edgepose.detect_symmetry(load_model(m, scale=1.0)) for i, m in meshes.items()}
        write_bop_dataset(
            root,
            meshes,
            scenes=args.scenes,
            images=args.images,
            objects_per_image=args.objects,
            symmetries=symmetries,
            distance=(0.7, 1.0),
            spread=spread,
            seed=2024,
        )
    return BopDataset(root)


def _time_images(dataset: BopDataset, targets: list, books: dict, repeats: int) -> tuple[dict, dict, list[int]]:
    """Per image, the median of ``repeats`` runs of each of METHODS: wall-clock
    and process CPU seconds; and the objects per image."""
    times: dict[str, list[float]] = {name: [] for name in METHODS}
    cpu: dict[str, list[float]] = {name: [] for name in METHODS}
    counts = []
    for scene_id in dataset.scene_ids():
        for im_id in dataset.image_ids(scene_id):
            image = dataset.image(scene_id, im_id)
            depth = image.depth()
            wanted = {t.obj_id for t in targets if (t.scene_id, t.im_id) == (scene_id, im_id)}
            objects = [
                (image.mask(g.gt_id), books[g.obj_id]) for g in image.gts if g.obj_id in wanted and g.visib_fract >= 0.1
            ]
            counts.append(len(objects))
            for name, run in METHODS.items():
                laps, cpu_laps = [], []
                for _ in range(repeats):
                    t0, c0 = time.perf_counter(), time.process_time()
                    run(depth, image.K, objects)
                    laps.append(time.perf_counter() - t0)
                    cpu_laps.append(time.process_time() - c0)
                times[name].append(float(np.median(laps)))
                cpu[name].append(float(np.median(cpu_laps)))
    return times, cpu, counts


def _one_by_one(depth: np.ndarray, K: np.ndarray, objects: list) -> None:
    """Each object's ``estimate`` in turn, given the frame as ``estimate_many``
    is (its scene test and support plane): the same work per object."""
    for mask, book in objects:
        edgepose.estimate(edgepose.cloud_from_depth(depth, K, mask, 1.0), book, depth=depth, K=K, depth_scale=1.0)


#: The timed ways to estimate one image's objects (depth in metres).
METHODS = {
    "estimate_many (2 threads)": lambda depth, K, objects: edgepose.estimate_many(depth, K, objects, depth_scale=1.0),
    "estimate_many (1 thread)": lambda depth, K, objects: edgepose.estimate_many(
        depth, K, objects, depth_scale=1.0, workers=1
    ),
    "estimate": _one_by_one,
}


def _spilled(dataset: BopDataset, targets: list) -> dict[tuple[int, int], list[Detection]]:
    """Each target's visible masks dilated by SPILL_PX pixels, as detections (score 1)."""
    out: dict[tuple[int, int], list[Detection]] = {}
    for t in targets:
        image = dataset.image(t.scene_id, t.im_id)
        for g in image.gts:
            if g.obj_id == t.obj_id:
                mask = dilate(image.mask(g.gt_id), SPILL_PX)
                det = Detection(t.scene_id, t.im_id, t.obj_id, g.visib_fract, encode_rle(mask), -1.0)
                out.setdefault((t.scene_id, t.im_id), []).append(det)
    return out


def _score_row(level: str, name: str, s) -> str:
    return (
        f"| {level} | {name} | {s.targets} | {100 * s.ar:.1f} | {100 * s.ar_vsd:.1f} | {100 * s.ar_mssd:.1f} "
        f"| {100 * s.ar_mspd:.1f} | {100 * s.add_s:.1f} |"
    )


if __name__ == "__main__":
    main()
