"""EstimateSettings nested by stage: dotted names in ``with_`` and ``flat()``,
and clear errors for a name that is no setting (or moved when the settings
were nested)."""

from __future__ import annotations

import dataclasses

import edgepose
import pytest
from edgepose.settings import DEFAULT_SETTINGS

STAGES = {
    "segmentation": edgepose.SegmentSettings,
    "retrieve": edgepose.RetrieveSettings,
    "score": edgepose.ScoreSettings,
    "refine": edgepose.RefineSettings,
    "second_search": edgepose.SecondSearchSettings,
    "turn": edgepose.TurnSettings,
    "alternatives": edgepose.AlternativeSettings,
}


def test_flat_names_every_field_of_every_stage_by_its_dotted_name():
    flat = DEFAULT_SETTINGS.flat()
    for stage, cls in STAGES.items():
        assert isinstance(getattr(DEFAULT_SETTINGS, stage), cls)
        for f in dataclasses.fields(cls):
            assert flat[f"{stage}.{f.name}"] == getattr(getattr(DEFAULT_SETTINGS, stage), f.name)
    top = [f.name for f in dataclasses.fields(edgepose.EstimateSettings) if f.name not in STAGES]
    assert set(top) == {"max_cloud_points", "segment", "support_plane", "subsample_seed"}
    assert len(flat) == len(top) + sum(len(dataclasses.fields(cls)) for cls in STAGES.values())
    assert DEFAULT_SETTINGS.with_(**flat) == DEFAULT_SETTINGS


def test_with_changes_a_stage_field_by_its_dotted_name_and_leaves_the_rest():
    changed = DEFAULT_SETTINGS.with_(
        **{"refine.icp_iterations": 20, "second_search.pair_poses": 0, "turn.check_below": -1.0}, segment=False
    )
    assert changed.refine == dataclasses.replace(DEFAULT_SETTINGS.refine, icp_iterations=20)
    assert changed.second_search.pair_poses == 0 and changed.turn.check_below == -1.0 and not changed.segment
    assert changed.retrieve is DEFAULT_SETTINGS.retrieve
    whole = DEFAULT_SETTINGS.with_(retrieve=edgepose.RetrieveSettings(k=8), **{"retrieve.keypoints": 16})
    assert (whole.retrieve.k, whole.retrieve.keypoints) == (8, 16)
    assert DEFAULT_SETTINGS.refine.icp_iterations == 12  # frozen: the default is untouched


@pytest.mark.parametrize(
    ("name", "now"),
    [
        ("k", "retrieve.k"),
        ("hypothesis_points", "refine.hypothesis_points"),
        ("pair_poses", "second_search.pair_poses"),
        ("free_space_tolerance", "score.free_space_tolerance"),
        ("turn_check_below", "turn.check_below"),
        ("alternative_within", "alternatives.within"),
        ("unseen_turn_alternatives", "alternatives.unseen_turns"),
    ],
)
def test_a_flat_name_from_before_the_nesting_is_refused_with_its_dotted_name(name, now):
    with pytest.raises(TypeError, match=f"no setting '{name}': it is '{now}'"):
        DEFAULT_SETTINGS.with_(**{name: 1})


def test_an_unknown_name_or_a_stage_given_a_number_is_refused():
    for name in ("icp", "refine.k", "retrieve.k.x"):
        with pytest.raises(TypeError, match=f"no setting '{name}'"):
            DEFAULT_SETTINGS.with_(**{name: 1})
    with pytest.raises(
        TypeError, match="alternatives must be an edgepose.AlternativeSettings.*'alternatives.max_count'"
    ):
        DEFAULT_SETTINGS.with_(alternatives=0)
    with pytest.raises(TypeError, match="refine must be an edgepose.RefineSettings"):
        edgepose.EstimateSettings(refine=edgepose.ScoreSettings())
