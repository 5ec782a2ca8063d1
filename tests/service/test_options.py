"""The options model (service.options): strict types, one schema, and the dataclasses built from it."""

from __future__ import annotations

import json

import pytest

from rasterizer.compaction import CompactionOptions
from service.errors import BadInput
from service.inputs import parse_options
from service.options import SceneOptions, options_json_schema, options_markdown
from service.pipeline import PipelineOptions
from service.scene_adaptive import AdaptiveRangeOptions


def refusal(options: str) -> str:
    """The message of the 422 ``invalid_options`` that the options JSON ``options`` gets."""
    with pytest.raises(BadInput) as info:
        parse_options(options, None)
    assert info.value.status == 422 and info.value.code == "invalid_options"
    return info.value.message


@pytest.mark.parametrize("options, field", [
    ('{"compaction": {"merge_smooth": "no"}}', "compaction.merge_smooth"),
    ('{"adaptive_range": {"enabled": "no"}}', "adaptive_range.enabled"),
    ('{"compaction": {"max_count": true}}', "compaction.max_count"),
    ('{"compaction": {"max_count": 2.5}}', "compaction.max_count"),
    ('{"compaction": {"min_opacity": 1e400}}', "compaction.min_opacity"),
    ('{"adaptive_range": {"margin": 1e400}}', "adaptive_range.margin"),
    ('{"near": 1e400}', "near"),
    ('{"compaction": {"merge_smooth": 1}}', "compaction.merge_smooth"),
    ('{"compaction": {"min_confidence": true}}', "compaction.min_confidence"),
    ('{"compaction": {"smooth_levels": 2}}', "compaction.smooth_levels"),
    ('{"refine_poses": "yes"}', "refine_poses"),
    ('{"sh_degree": true}', "sh_degree"),
    ('{"compaction": true}', "compaction"),
    ('{"adaptive_range": "on"}', "adaptive_range"),
])
def test_wrong_types_are_422_naming_the_field(options, field):
    message = refusal(options)
    assert f"options.{field}" in message, message


# Compaction steps that the service does not have (measured, not kept: docs/design.md, Compaction): unknown keys.
@pytest.mark.parametrize("key, value", [("resolve_overlap", "split"), ("merge_duplicates", True),
                                        ("duplicate_range_tol", 0.05), ("duplicate_footprint_ratio", 4.0)])
def test_compaction_keys_of_steps_the_service_lacks_are_unknown_options(key, value):
    message = refusal(json.dumps({"compaction": {key: value}}))
    assert f"options.compaction.{key}: unknown option" in message, message
    assert f"`compaction.{key}`" not in options_markdown()


@pytest.mark.parametrize("options, words", [
    ('{"compaction": {"max_count": 0}}', "options.compaction.max_count"),
    ('{"compaction": {"max_bytes": 100}}', "compaction.max_bytes=100 cannot hold the PLY of one Gaussian"),
    ('{"sh_degree": 0, "compaction": {"max_bytes": 0}}', "at sh_degree 0"),
])
def test_caps_that_leave_no_gaussian_are_refused_before_the_work(options, words):
    message = refusal(options)
    assert words in message, message


@pytest.mark.parametrize("options, words", [
    ('{"compaction": false, "min_opacity": 0.5}', "compaction false keeps"),
    ('{"min_opacity": 0.5, "compaction": {"min_opacity": 0.01}}', "disagree"),
])
def test_an_option_that_another_overrides_is_refused(options, words):
    message = refusal(options)
    assert words in message, message


@pytest.mark.parametrize("options, named", [
    ('{"adaptive_range": {"margin": 0.3}}', ["adaptive_range.margin"]),  # "enabled" left out: off, margin unused
    ('{"adaptive_range": {"enabled": false, "low_pct": 5, "min_ratio": 2}}',
     ["adaptive_range.low_pct", "adaptive_range.min_ratio"]),
    ('{"compaction": {"merge_smooth": false, "smooth_colour_tol": 0.06}}', ["compaction.smooth_colour_tol"]),
    ('{"compaction": {"merge_smooth": false, "smooth_plane_tol": 0.01, "smooth_max_incidence_deg": 45}}',
     ["compaction.smooth_max_incidence_deg", "compaction.smooth_plane_tol"]),
])
def test_settings_of_a_step_that_is_off_are_refused(options, named):
    """They would change nothing: an adaptive_range object without "enabled": true runs no coarse pass."""
    message = refusal(options)
    assert all(name in message for name in named), message
    assert ('"enabled": true' if "adaptive" in options else "merge_smooth is false") in message, message


@pytest.mark.parametrize("options", ['{"min_opacity": 0.5, "compaction": {"min_opacity": 0.5}}',
                                     '{"adaptive_range": false, "near": 0.5}', '{"min_opacity": 0.1}',
                                     '{"adaptive_range": {"enabled": true, "margin": 0.3}}',
                                     '{"adaptive_range": {"enabled": false}}',
                                     '{"compaction": {"merge_smooth": false, "max_count": 1000}}',
                                     '{"compaction": {"merge_smooth": true, "smooth_colour_tol": 0.06}}'])
def test_options_that_agree_are_accepted(options):
    parse_options(options, None)


def test_a_long_unknown_key_is_named_shortened():
    """A 100,000-character key is named by its start and length, not whole."""
    message = refusal(json.dumps({"x" * 100_000: 1}))
    assert "unknown option" in message and "(100000 characters)" in message and len(message) < 300, message[:300]


def test_smallest_byte_cap_keeps_one_gaussian():
    from rasterizer.compaction.options import ply_count_for_bytes

    for degree in (0, 1):
        message = refusal(json.dumps({"sh_degree": degree, "compaction": {"max_bytes": 1}}))
        smallest = int(message.split("at least ")[1].split(" bytes")[0])
        assert ply_count_for_bytes(smallest, (degree + 1) ** 2) == 1 > ply_count_for_bytes(smallest - 1, (degree + 1) ** 2)
        parse_options(json.dumps({"sh_degree": degree, "compaction": {"max_bytes": smallest}}), None)


def test_typed_values_build_the_rasterizer_dataclasses_by_keyword():
    raw, pipeline, poses = parse_options(json.dumps({
        "near": 1, "far": 20.5, "min_opacity": 0.02, "sh_degree": 0, "baseline": 0.5,
        "compaction": {"merge_smooth": False, "max_count": 1000, "min_confidence": 0.2},
        "adaptive_range": {"enabled": True, "margin": 0.3}}), None)
    assert raw["near"] == 1  # the object as sent: scene ids hash it
    assert (pipeline.near, pipeline.far, pipeline.sh_degree) == (1.0, 20.5, 0)
    assert pipeline.compaction == CompactionOptions(min_opacity=0.02, merge_smooth=False, max_count=1000,
                                                    min_confidence=0.2)
    assert pipeline.adaptive_range == AdaptiveRangeOptions(enabled=True, margin=0.3)
    assert poses.baseline == 0.5 and poses.camera_height is None
    assert parse_options('{"compaction": false}', None)[1].compaction == CompactionOptions.off()
    assert parse_options('{"adaptive_range": true}', None)[1].adaptive_range.enabled is True
    assert PipelineOptions.from_dict({}) == parse_options(None, None)[1]
    assert PipelineOptions.from_dict({}).compaction == CompactionOptions()


def test_defaults_are_the_dataclasses_and_the_schema_lists_every_field():
    assert SceneOptions().compaction_options() == CompactionOptions()
    assert SceneOptions().adaptive_options() == AdaptiveRangeOptions()
    schema = options_json_schema()
    assert "$ref" not in json.dumps(schema)
    comp = next(s for s in schema["properties"]["compaction"]["anyOf"] if s.get("type") == "object")
    assert comp["properties"]["merge_smooth"]["default"] is True
    assert comp["properties"]["max_count"]["anyOf"][0]["type"] == "integer"
    text = options_markdown()
    for name in ("near", "far", "sh_degree", "rig_cap_deg", "compaction.max_bytes", "adaptive_range.margin"):
        assert f"`{name}`" in text
    assert "smooth_levels" not in text


def test_scene_post_form_field_documents_the_schema(tmp_path):
    from service.app import create_app
    from service.config import Settings

    spec = create_app(Settings(model_path=tmp_path / "m.onnx", store_dir=tmp_path / "s")).openapi()
    body = next(v for k, v in spec["components"]["schemas"].items() if k.startswith("Body_create_scene"))
    field = body["properties"]["options"]
    assert field["contentSchema"]["properties"]["compaction"]
    assert "`compaction.merge_smooth` (bool, default `True`)" in field["description"]


@pytest.mark.parametrize("body", [{"optimise_opacity": True}, {"opacity_lr": 0.1}, {"loss": "l2"}, {"loss": "huber"},
                                  {"cross_check": "no"}, {"iterations": True}, {"colour_reg": float("inf")}])
def test_refine_request_has_no_experiment_switches_and_strict_types(body):
    from pydantic import ValidationError

    from service.routes.jobs import RefineRequest

    with pytest.raises(ValidationError):
        RefineRequest.model_validate(body)
    assert set(RefineRequest.model_fields) == {"iterations", "height", "sh_degree", "colour_reg", "holdout",
                                               "patience", "cross_check"}


def test_refine_solver_default_loss_is_the_documented_one():
    from rasterizer.refine import solver

    assert solver.RefineOptions().loss == "l1"
    assert "L2 stays the default" not in solver.__doc__ and 'default "l1"' in solver.__doc__
