"""RefineOptions: grouped and flat construction, validation of every field, enums, dict round trip."""

import dataclasses
import json

import pytest

from o3d_mvps.solver.options import (ConvergenceCriteria, DifferenceScheme, LightModel, ModelOptions, RefineOptions,
                                     StepOptions)

FLAT = dict(tau=100.0, smoothness=5.0, slope_weights=True, cauchy_lambda=0.1, light_model="sh", led_offset=(0.03, -0.02, 0.0), initial_light=(0.1, 0, 0, -1),
            difference_scheme="forward", depth_envelope=None, occlusion_test=False, occlusion_tolerance=0.05,
            levels=3, max_iterations=4, tolerance=1e-4, pose_iterations=2, pose_tolerance=0.0, cg_tolerance=1e-3,
            cg_max_iterations=50, joint_cg_tolerance=0.1, refine_poses=False, pose_min_pixels=0,
            joint_pose_depth=False, joint_min_pixels=5, project_albedo=False, extrapolate=False,
            refine_led_offset=False, strict_registration=True, sensor_lowpass=6.0, evidence_weights=False)


def grouped_of(flat):
    return {group: cls(**{f.name: flat[f.name] for f in dataclasses.fields(cls) if f.name in flat})
            for group, cls in (("model", ModelOptions), ("convergence", ConvergenceCriteria), ("steps", StepOptions))}


def test_flat_and_grouped_construction_are_equal_and_read_alike():
    flat = RefineOptions(frames=[0, 2], progress=False, **FLAT)
    grouped = RefineOptions(frames=[0, 2], progress=False, **grouped_of(FLAT))
    assert flat == grouped
    assert flat != RefineOptions()
    for name, value in FLAT.items():
        assert getattr(flat, name) == (tuple(value) if isinstance(value, tuple) else value), name
    assert (flat.model.tau, flat.convergence.levels, flat.steps.refine_poses) == (100.0, 3, False)


def test_a_flat_keyword_overrides_its_field_of_a_given_group_and_replace_takes_flat_names():
    options = RefineOptions(model=ModelOptions(tau=50.0, cauchy_lambda=0.2), tau=7.0)
    assert (options.tau, options.cauchy_lambda) == (7.0, 0.2)
    replaced = dataclasses.replace(options, strict_registration=True, frames=3)
    assert (replaced.strict_registration, replaced.frames, replaced.tau) == (True, 3, 7.0)
    assert dataclasses.replace(replaced, frames=None) == RefineOptions(model=options.model, strict_registration=True)


def test_fields_are_read_only():
    options = RefineOptions()
    with pytest.raises(AttributeError):
        options.tau = 3.0
    with pytest.raises(dataclasses.FrozenInstanceError):
        options.model.tau = 3.0


# One bad value per field, and the allowed range the message must state.
BAD = [
    ("tau", 0.0, "(0, inf)"), ("tau", float("nan"), "(0, inf)"), ("cauchy_lambda", -0.1, "(0, inf)"),
    ("cauchy_lambda", "automatic", "a number in (0, inf), 'auto' or None"),
    ("smoothness", -1.0, "[0, inf), 'auto' or None"), ("sensor_lowpass", -1.0, "[0, inf), 'auto' or None"),
    ("evidence_weights", 1, "True or False"),
    ("depth_envelope", 1.0, "[0, 1) or None"), ("occlusion_tolerance", -0.01, "[0, 1)"),
    ("levels", 0, "an integer in [1, inf]"), ("levels", 2.5, "an integer"), ("max_iterations", 0, "[1, inf]"),
    ("tolerance", 1.0, "[0, 1)"), ("pose_iterations", 0, "[1, inf]"), ("pose_tolerance", -1e-3, "[0, 1)"),
    ("cg_tolerance", 0.0, "(0, 1)"), ("cg_max_iterations", 0, "[1, inf]"), ("joint_cg_tolerance", 1.0, "(0, 1)"),
    ("pose_min_pixels", -1, "[0, inf]"), ("joint_min_pixels", "10", "[0, inf]"),
    ("led_offset", (0.0, 0.0), "(x, y, z) in metres or None"), ("initial_light", (1.0, 0.0), "4 SH coefficients"),
    ("refine_poses", 1, "True or False"), ("slope_weights", "yes", "True or False"), ("strict_registration", "yes", "True or False"),
    ("frames", 0, "[1, inf]"), ("frames", [0, 0], "distinct indices"), ("progress", None, "True or False"),
]


@pytest.mark.parametrize("name, value, allowed", BAD, ids=[f"{n}={v!r}" for n, v, _ in BAD])
def test_each_field_rejects_a_bad_value_naming_field_value_and_range(name, value, allowed):
    with pytest.raises(ValueError) as info:
        RefineOptions(**{name: value})
    message = str(info.value)
    assert message.startswith(f"{name} must be") and allowed in message and repr(value) in message


def test_every_numeric_field_is_covered_by_the_bad_values():
    numeric = {f.name for cls in (ModelOptions, ConvergenceCriteria, StepOptions) for f in dataclasses.fields(cls)
               if f.type in ("int", "float", "float | None", "float | str | None")}
    assert len(numeric) == 16 and numeric <= {name for name, _, _ in BAD}


def test_enums_take_plain_strings_and_reject_others_with_the_choices():
    options = RefineOptions(light_model="sh", difference_scheme=DifferenceScheme.FORWARD)
    assert options.light_model is LightModel.SH and options.light_model == "sh"
    assert options.difference_scheme is DifferenceScheme.FORWARD and f"{options.difference_scheme}" == "forward"
    assert RefineOptions().light_model is None and RefineOptions().difference_scheme == "central"  # None: the capture says
    with pytest.raises(ValueError, match=r"light_model must be one of \['led', 'sh', 'room', 'point'\], got 'spot'"):
        RefineOptions(light_model="spot")
    with pytest.raises(ValueError, match=r"difference_scheme must be one of \['central', 'forward'\], got 'backward'"):
        RefineOptions(difference_scheme="backward")


def test_the_cauchy_scale_and_slope_weights_follow_the_light_model_unless_given():
    assert not RefineOptions(light_model="led").model.slope_weighted()
    assert RefineOptions(light_model="room").model.slope_weighted()
    assert not RefineOptions(light_model="room", slope_weights=False).model.slope_weighted()
    assert RefineOptions(light_model="led").model.cauchy_scale() == 0.04
    assert RefineOptions(light_model="room").model.cauchy_scale() == "auto"
    assert RefineOptions(light_model="room", cauchy_lambda=0.02).model.cauchy_scale() == 0.02
    assert RefineOptions(light_model="led", cauchy_lambda="auto").model.cauchy_scale() == "auto"
    assert RefineOptions.from_dict(RefineOptions(cauchy_lambda="auto").to_dict()).cauchy_lambda == "auto"


def test_an_unknown_keyword_is_a_type_error_listing_the_valid_ones():
    with pytest.raises(TypeError, match=r"unknown keyword\(s\) iterations; valid keywords: model, .*max_iterations"):
        RefineOptions(iterations=5)
    with pytest.raises(TypeError, match="model must be a ModelOptions, got dict"):
        RefineOptions(model={"tau": 1.0})


def test_to_dict_is_json_ready_and_round_trips():
    options = RefineOptions(frames=[0, 3, 1], progress=False, **FLAT)
    text = json.dumps(options.to_dict())
    assert RefineOptions.from_dict(json.loads(text)) == options
    assert json.loads(text)["model"]["light_model"] == "sh"
    assert RefineOptions.from_dict({"tau": 20.0, "levels": 2}) == RefineOptions(tau=20.0, levels=2)


def test_frame_indices():
    assert RefineOptions().frame_indices(3) == [0, 1, 2]
    assert RefineOptions(frames=2).frame_indices(3) == [0, 1]
    assert RefineOptions(frames=[0, 2]).frame_indices(3) == [0, 2]
    with pytest.raises(ValueError, match="frames=4 but the capture has 3 frames; use 1..3"):
        RefineOptions(frames=4).frame_indices(3)
    with pytest.raises(ValueError, match=r"frames=\[0, 3\] must be distinct indices in 0..2"):
        RefineOptions(frames=[0, 3]).frame_indices(3)
