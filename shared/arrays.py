"""Typed numpy fields for pydantic models.

Messages carry images and clouds as numpy arrays. ``Array(dtype, ndim)`` is an annotated type that
validates dtype and rank (lists are converted, other dtypes are refused rather than silently cast:
a uint8 image that arrives as float64 is a bug upstream) and that documents itself in OpenAPI.
"""

from __future__ import annotations

from typing import Annotated, Any

import numpy as np
from pydantic import BeforeValidator, PlainSerializer, WithJsonSchema


def Array(dtype: str, ndim: int | None = None, last_dim: int | None = None) -> Any:  # noqa: N802
    want = np.dtype(dtype)

    def validate(value: Any) -> np.ndarray:
        if isinstance(value, np.ndarray):
            arr = value
            if arr.dtype != want:
                # Allow only lossless promotions (e.g. bool masks stay bool, float32 stays float32).
                if not np.can_cast(arr.dtype, want, casting="safe"):
                    raise ValueError(f"expected dtype {want}, got {arr.dtype}")
                arr = arr.astype(want)
        else:
            arr = np.asarray(value, dtype=want)
        if ndim is not None and arr.ndim != ndim:
            raise ValueError(f"expected a {ndim}-d array, got shape {arr.shape}")
        if last_dim is not None and (arr.ndim == 0 or arr.shape[-1] != last_dim):
            raise ValueError(f"expected last dimension {last_dim}, got shape {arr.shape}")
        return arr

    schema = {
        "type": "object",
        "description": f"numpy array dtype={want.name}" + (f" ndim={ndim}" if ndim else ""),
    }
    return Annotated[
        np.ndarray,
        BeforeValidator(validate),
        # JSON (HTTP) renders arrays as nested lists; the binary codec keeps the ndarray itself.
        PlainSerializer(lambda a: a.tolist(), when_used="json"),
        WithJsonSchema(schema),
    ]
