"""Every number of every request schema is finite and inside a stated range, checked when a payload is
decoded - the class of defect behind ``turn(angle_rad=inf)`` poisoning the robot's pose."""

from __future__ import annotations

import math

import pytest
from pydantic import BaseModel

from shared import schemas
from shared.bus.typed import error_for
from shared.codec import CodecError, decode, encode
from shared.schemas import ErrorCode
from tests.reliability.limits import bad_value_payloads, numeric_leaves, request_schemas, samples


def _models(model: type[BaseModel], seen: set | None = None):
    seen = set() if seen is None else seen
    if model in seen:
        return seen
    seen.add(model)
    for f in model.model_fields.values():
        for t in _types(f.annotation):
            if isinstance(t, type) and issubclass(t, BaseModel):
                _models(t, seen)
    return seen


def _types(tp):
    import typing

    yield tp
    for a in typing.get_args(tp):
        yield from _types(a)


@pytest.mark.parametrize("model", request_schemas(), ids=lambda m: m.__name__)
def test_every_number_of_every_request_schema_has_a_stated_range(model):
    unbounded = [(leaf.path, leaf.lower, leaf.upper) for leaf in numeric_leaves(model)
                 if leaf.lower is None or leaf.upper is None]
    assert not unbounded, f"{model.__name__}: numbers without a lower and an upper bound: {unbounded}"
    lax = [m.__name__ for m in _models(model) if m.model_config.get("allow_inf_nan", True)]
    assert not lax, f"{model.__name__}: models that accept NaN/inf: {lax}"


def test_every_request_schema_that_carries_numbers_has_a_fuzz_sample():
    have = samples()
    missing = [m.__name__ for m in request_schemas() if numeric_leaves(m) and m.SCHEMA not in have]
    assert not missing


@pytest.mark.parametrize("schema", sorted(samples()), ids=str)
def test_non_finite_huge_and_out_of_range_values_are_refused_at_decode(schema):
    sample = samples()[schema]
    assert decode(encode(sample), type(sample)) is not None  # the sample itself is valid
    n = 0
    for path, value, payload in bad_value_payloads(sample):
        with pytest.raises(CodecError) as err:
            decode(payload, type(sample))
        assert err.value.reason == "invalid", (path, value, err.value)
        # An inf is reported as inf, never as "nan" (issue 15 item 6).
        if isinstance(value, float) and math.isinf(value):
            assert "nan" not in str(err.value).lower(), err.value
        n += 1
    assert n >= 4  # every sample carries numbers


@pytest.mark.parametrize("text", ["\u0000", "   ", "?!", "12 34", "go\u0000 left"])
def test_an_empty_or_meaningless_instruction_is_refused(text):
    with pytest.raises(ValueError):
        schemas.MissionRequest(mission_id="m", instruction=text, map_id="m")


def test_free_form_fields_refuse_non_finite_numbers():
    with pytest.raises(ValueError):
        schemas.ExplorationRequest(exploration_id="x", map_id="m", options={"a": [1.0, float("nan")]})
    with pytest.raises(ValueError):
        schemas.MissionOptions(policy_config={"t": float("inf")})


def test_budgets_are_typed_errors():
    cam = schemas.CameraIntrinsics(width_px=512, height_px=512)
    req = schemas.RenderRequest(map_id="m", views=[schemas.ViewPose(position_m=(0, 0, 0))] * 64, camera=cam)
    with pytest.raises(schemas.BudgetExceeded) as err:
        req.check_budget()
    assert error_for(err.value)[0] == ErrorCode.BUDGET_EXCEEDED
    assert "16,777,216 px asked" in str(err.value)
    schemas.RenderRequest(map_id="m", views=[schemas.ViewPose(position_m=(0, 0, 0))] * 64).check_budget()
    with pytest.raises(schemas.BudgetExceeded):
        schemas.ObserveRequest(camera=schemas.CameraIntrinsics(width_px=4096, height_px=4096)).check_budget()
    with pytest.raises(schemas.BudgetExceeded):
        schemas.MapChunkRequest(map_id="m", max_points=10_000_000).check_budget()
