"""Gateway settings from the environment (``ANT_...``) and command line."""

from __future__ import annotations

from pathlib import Path

from pydantic import Field

from shared.runner import ServiceSettings
from shared.schemas import IMPORT_MAX_BYTES, MAP_CHUNK_MAX_POINTS


class GatewaySettings(ServiceSettings):
    host: str = "127.0.0.1"
    port: int = Field(8000, ge=0, le=65535)
    api_token: str | None = Field(None, description="bearer token required by mutating routes (None: open)")
    read_token: str | None = Field(None, description="bearer token required to read missions, images, maps and "
                                                     "status (None: reads open); the API token reads too")
    cors_origins: list[str] = Field(default_factory=list)
    status_timeout_s: float = Field(1.0, gt=0, le=30)

    db_path: Path = Field(Path("runs/gateway/gateway.sqlite3"),
                          description="SQLite file (WAL) holding missions, explorations, events, images")
    request_timeout_s: float = Field(5.0, gt=0, le=120, description="bus requests made for one HTTP call")
    max_body_bytes: int = Field(1 << 20, ge=1024, description="largest JSON request body")
    # The reconstructor's own budget for one import: a larger body would be streamed, then refused.
    max_upload_bytes: int = Field(IMPORT_MAX_BYTES, ge=1024, description="largest uploaded cloud (POST /maps)")
    max_instruction_chars: int = Field(4000, ge=1, le=4000)
    validate_map: bool = Field(True, description="ask the reconstructor that a mission's map exists")
    pose_tolerance_m: float = Field(1.0, gt=0, le=100,
                                    description="start_pose / goal_m farther than this from walkable ground: 422")
    map_chunk_points: int = Field(500_000, ge=1000, le=MAP_CHUNK_MAX_POINTS, description="points per MAP_CHUNK request")
    sse_keepalive_s: float = Field(15.0, gt=0, le=300, description="comment line sent on idle SSE streams")
    sse_batch: int = Field(200, ge=1, le=10_000, description="events read from the DB per SSE round")
    threadpool_workers: int = Field(128, ge=4, le=1024, description="threads for sync routes (bus calls)")
    record_cache_jobs: int = Field(512, ge=1, le=100_000, description="encoded job records kept for polling")
    scene_timeout_s: float = Field(120.0, gt=0, le=600, description="loading a scene on robot-io (POST /robot/scene)")
    reconcile_interval_s: float = Field(5.0, gt=0, le=3600,
                                        description="how often open jobs are checked against the live workers")
    shutdown_grace_s: float = Field(3.0, ge=0, le=60, description="open streams get this long at shutdown")
    record_jobs: bool = Field(False, description="record missions and explorations to .rrd unless a job says otherwise")
    recordings_dir: Path | None = Field(None, description="where the .rrd recordings go (None: beside db_path)")
    recording_max_points: int = Field(500_000, ge=0, le=10_000_000,
                                      description="map points kept in a recording (0: no map cloud)")
