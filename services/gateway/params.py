"""Path and query parameter types that several routers share (one definition each)."""

from __future__ import annotations

from typing import Annotated

from fastapi import Header, Path, Query

from shared.keys import SEGMENT_PATTERN as SEGMENT  # one key segment, the pattern written once
SEQ_MAX = 2**31 - 1

MissionId = Annotated[str, Path(pattern=SEGMENT, description="mission id")]
ExplorationId = Annotated[str, Path(pattern=SEGMENT, description="exploration id")]
JobId = Annotated[str, Path(pattern=SEGMENT, description="job id")]
MapId = Annotated[str, Path(pattern=SEGMENT, description="map id")]
ImageName = Annotated[str, Path(pattern=SEGMENT)]
Seq = Annotated[int, Path(ge=0, le=SEQ_MAX)]
Version = Annotated[int | None, Query(ge=1, le=SEQ_MAX, description="a stored version (default: the latest)")]
IfNoneMatch = Annotated[str | None, Header(description="an ETag of this record already held: 304 if unchanged")]
LastEventId = Annotated[str | None, Header()]
After = Annotated[int | None, Query(ge=-1, le=SEQ_MAX, description="resume after this seq")]

RECORD_DOC = {304: {"description": "not modified since the ETag given in If-None-Match"}, 404: {}}
SSE_DOC = {200: {"content": {"text/event-stream": {}},
                 "description": "``id: seq``, ``event: kind``, ``data: event JSON``; ``event: end`` closes"},
           404: {}, 400: {}}
IMAGE_DOC = {200: {"content": {"image/jpeg": {}}}, 404: {}}
