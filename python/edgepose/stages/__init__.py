"""The five named stages of :func:`edgepose.estimate` (``docs/method.md``),
each reusable on its own (the exporter's evaluation, benchmarks):

1. :func:`prepare_query` — keep the points that are the object (outliers,
   flying pixels and background a spilled mask picked up are dropped), turn
   the cloud so its centroid ray is the optical axis, centre, scale and
   resample it to a map;
2. :func:`retrieve` — encode the map, cosine top-K over the codebook's
   codes (Rust), the in-plane angle of each candidate (IRR head);
3. :func:`candidate_poses` — each candidate view and angle as a pose
   (:func:`pair_poses`: poses voted for by point pairs, for doubtful views);
4. :func:`score_poses` — how well each pose explains the view: truncated
   keypoint distances to the model and free-space violations (Rust);
5. :func:`refine_hypotheses` — point-to-plane ICP (Rust) from the best few
   distinct candidates, scored again; the best one is polished (while
   another core searches for its turned rival for the confidence,
   :func:`polished`).

Poses are model frame → camera (the model frame is the mesh frame shifted by
the model's centre); units are metres. Every tuning value lives in
:class:`edgepose.settings.EstimateSettings`.

Import them from here; each lives in the module of its stage: ``query``
(1), ``retrieval`` (2, 3), ``scoring`` (4), ``refine`` (5 and the poses that
rival its pick: the flip margin, the turned pose, the alternatives).
"""

from __future__ import annotations

from edgepose.stages.query import (
    SCENE_MARGIN,
    Query,
    SceneDepth,
    off_support_plane,
    on_support_plane,
    prepare_query,
    query_of_cleaned,
    scene_around,
    subsample,
)
from edgepose.stages.refine import (
    FLIP_ALIGN_ITERATIONS,
    FLIP_SETTLE_ITERATIONS,
    FLIP_SETTLED_RIVALS,
    RIVAL_DISTANCE,
    RIVAL_POINTS,
    FlipMargin,
    FlipRival,
    Hypotheses,
    Pick,
    Refined,
    RivalSearch,
    alternatives,
    distinct_hypotheses,
    distinct_poses,
    flip_margin,
    flip_rival,
    pick_hypothesis,
    polish,
    polished,
    pose_distances,
    refine_hypotheses,
    turned_pose,
    usable_icp,
)
from edgepose.stages.retrieval import (
    Retrieval,
    candidate_poses,
    nearest_views,
    pair_poses,
    retrieve,
)
from edgepose.stages.scoring import (
    PoseScores,
    free_space_tolerance,
    near_the_cloud,
    rim_tolerant_violation,
    score_poses,
)

__all__ = [
    "FLIP_ALIGN_ITERATIONS",
    "FLIP_SETTLED_RIVALS",
    "FLIP_SETTLE_ITERATIONS",
    "FlipMargin",
    "FlipRival",
    "Hypotheses",
    "Pick",
    "PoseScores",
    "Query",
    "RIVAL_DISTANCE",
    "RIVAL_POINTS",
    "Refined",
    "Retrieval",
    "RivalSearch",
    "SCENE_MARGIN",
    "SceneDepth",
    "alternatives",
    "candidate_poses",
    "distinct_hypotheses",
    "distinct_poses",
    "flip_margin",
    "flip_rival",
    "free_space_tolerance",
    "near_the_cloud",
    "nearest_views",
    "off_support_plane",
    "on_support_plane",
    "pair_poses",
    "pick_hypothesis",
    "polish",
    "polished",
    "pose_distances",
    "prepare_query",
    "query_of_cleaned",
    "refine_hypotheses",
    "retrieve",
    "rim_tolerant_violation",
    "scene_around",
    "score_poses",
    "subsample",
    "turned_pose",
    "usable_icp",
]
