"""The base of every message: limits, per-request budgets, the ``Message`` model and the finite checks."""

from __future__ import annotations

import math
from typing import Annotated, Any, ClassVar

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, model_validator

from shared.keys import SEGMENT_PATTERN


# --- limits -----------------------------------------------------------------------------------------
# Every number a request carries is finite (``allow_inf_nan=False`` on every model) and inside a stated
# range, checked when the message is decoded: a value outside it can only be a mistake or an attack,
# and once inside a robot's pose or a map it would poison every later request.

WORLD_LIMIT_M = 2.0e7  # |coordinate|: UTM northings reach 1e7 m; 1e300 is a mistake (nearness to the
# scene is checked where the scene is known: a start pose 1e6 m away gets a 422 with its distance)
ANGLE_LIMIT_RAD = 4.0 * math.pi  # |heading| or |turn|: two full turns either way
PITCH_LIMIT_RAD = math.pi / 2.0
TIME_LIMIT_S = 1.0e11  # timestamps: epoch seconds (~1.7e9) or simulated seconds (>= 0)
SEQ_LIMIT = 2**31 - 1  # ids, versions, sequence numbers, counts
LABEL_LIMIT = 2**31 - 1

Metres = Annotated[float, Field(ge=-WORLD_LIMIT_M, le=WORLD_LIMIT_M)]
Distance_m = Annotated[float, Field(ge=0.0, le=WORLD_LIMIT_M)]
Radians = Annotated[float, Field(ge=-ANGLE_LIMIT_RAD, le=ANGLE_LIMIT_RAD)]
Pitch_rad = Annotated[float, Field(ge=-PITCH_LIMIT_RAD, le=PITCH_LIMIT_RAD)]
Seconds = Annotated[float, Field(ge=0.0, le=TIME_LIMIT_S)]
Xyz_m = tuple[Metres, Metres, Metres]
LabelId = Annotated[int, Field(ge=-1, le=LABEL_LIMIT)]
Count = Annotated[int, Field(ge=0, le=SEQ_LIMIT)]
Cost_usd = Annotated[float, Field(ge=0.0, le=1e6)]
# A depth sensor's declared noise, sigma = rel * depth^2 (0: exact or not known): the same quantity on a
# frame, a panorama, a ROS 2 profile and the exploration's outcome. 0.5 gives 2 m of sigma at 2 m: no
# camera that noisy is worth mapping with.
DepthNoiseRel = Annotated[float, Field(ge=0.0, le=0.5)]
_ID_PATTERN = SEGMENT_PATTERN  # kept for older imports: use SegmentId
# An id that names a key segment (map, mission, exploration, build, upload, job): refused on decode
# unless it is one valid segment, so no handler validates ids by hand.
SegmentId = Annotated[str, Field(pattern=SEGMENT_PATTERN)]
Duration_s = Annotated[float, Field(ge=0.0, le=TIME_LIMIT_S)]


class BudgetExceeded(ValueError):
    """A well-formed request asks for more work or data than one request may (pixels, views, points,
    frames, bytes); the bus answers ``budget_exceeded`` and the gateway 413."""

    def __init__(self, what: str, asked: float, limit: float, unit: str = ""):
        u = f" {unit}" if unit else ""
        super().__init__(f"{what}: {asked:,.0f}{u} asked, at most {limit:,.0f}{u} per request")
        self.what, self.asked, self.limit = what, asked, limit


# Per-request budgets (data, not code): what one request may cost the service that answers it.
RENDER_MAX_PIXELS = 64 * 256 * 256  # views x width x height of one RenderRequest (~50 MB of reply)
PANORAMA_MAX_PIXELS = 12 * 512 * 512  # views x width x height of one panorama sent for prediction (~25 MB)
VIEW_MAX_PIXELS = 512 * 512  # one view of an observed panorama (the robot's own config sets the views)
MAP_CHUNK_MAX_POINTS = 2_000_000  # points of one MapChunk (~30 MB)
BUILD_MAX_RECORDINGS = 256
BUILD_MAX_FRAMES = 500_000  # frames of every recording of one BuildMapRequest together
IMPORT_MAX_BYTES = 1 << 30  # an imported cloud file (streamed: neither side holds it, so the disk is the limit)
IMPORT_PART_BYTES = 4 << 20  # what a sender puts in one part of an upload (MapImportRequest.upload_id)
IMPORT_PART_MAX_BYTES = 32 << 20  # the most one part may carry
PATH_MAX_POINTS = 10_000  # trajectories and reference paths
FREE_FORM_MAX_ITEMS = 10_000  # values in a free-form dict (options, policy configs, event data)
FREE_FORM_MAX_ABS = 1e15  # |number| in a free-form dict; the typed config that reads it narrows it


def check_free_form(value: Any, what: str) -> Any:
    """``value`` (a free-form dict from HTTP or the bus) if every number in it is finite and in range
    and it is not absurdly large; else ValueError. What request models use on their ``dict[str, Any]``."""
    _free_form_check(value, what, [FREE_FORM_MAX_ITEMS])
    return value


def _free_form_check(value: Any, what: str, budget: list[int]) -> None:
    """Free-form (``dict[str, Any]``) fields escape the typed checks: refuse non-finite and huge
    numbers and absurd sizes in them too (the typed config that reads them narrows the ranges)."""
    budget[0] -= 1
    if budget[0] < 0:
        raise ValueError(f"{what}: more than {FREE_FORM_MAX_ITEMS} values")
    if isinstance(value, (int, float)) and not isinstance(value, bool):
        if not math.isfinite(value):
            raise ValueError(f"{what} must be finite, got {value}")
        if abs(value) > FREE_FORM_MAX_ABS:
            raise ValueError(f"{what} must be within +-{FREE_FORM_MAX_ABS:g}, got {value:g}")
    elif isinstance(value, dict):
        for k, v in value.items():
            _free_form_check(v, f"{what}.{k}", budget)
    elif isinstance(value, (list, tuple)):
        for i, v in enumerate(value):
            _free_form_check(v, f"{what}[{i}]", budget)


class Message(BaseModel):
    """Base of every bus message."""

    model_config = ConfigDict(arbitrary_types_allowed=True, extra="forbid", frozen=False, allow_inf_nan=False)
    SCHEMA: ClassVar[str] = "message"
    VERSION: ClassVar[int] = 1
    FREE_FORM: ClassVar[tuple[str, ...]] = ()  # dict[str, Any] fields, checked by _free_form_check

    def __init_subclass__(cls, **kwargs: Any) -> None:
        super().__init_subclass__(**kwargs)
        # Schema names default to the class name so that no two messages share one by accident.
        if "SCHEMA" not in cls.__dict__:
            cls.SCHEMA = cls.__name__

    @model_validator(mode="after")
    def _free_form_finite(self):
        for name in self.FREE_FORM:
            _free_form_check(getattr(self, name), name, [FREE_FORM_MAX_ITEMS])
        return self

    def check_budget(self) -> None:
        """Raise :class:`BudgetExceeded` when this request asks for more than one request may
        (the serving side calls it after decoding, before any work)."""


def _finite(values: tuple[float, ...] | float, what: str):
    vals = values if isinstance(values, tuple) else (values,)
    if not all(math.isfinite(v) for v in vals):
        raise ValueError(f"{what} must be finite, got {values}")
    return values


def _finite_array(arr: np.ndarray | None, what: str, non_negative: bool = False) -> None:
    """Refuse NaN/inf (and, for depths, negative values) in a float array payload: one bad value
    would silently poison a map, a splat or a distance downstream."""
    if arr is None or arr.dtype.kind != "f" or arr.size == 0:
        return
    bad = ~np.isfinite(arr)
    if non_negative:
        bad |= arr < 0
    if bad.any():
        rule = "finite and >= 0" if non_negative else "finite"
        raise ValueError(f"{what} must be {rule}; {int(bad.sum())} of {arr.size} values are not")
