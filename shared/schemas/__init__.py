"""Every message that crosses the bus, as pydantic v2 models.

One package, split by domain (``base``: limits and the ``Message`` model; ``geometry``; ``robot``;
``navigation``; ``maps``; ``render``; ``missions``; ``events``; ``service``), re-exported here so a reader and
every import find every payload of the system in one place (the key expressions that carry them live
in :mod:`shared.keys`). Conventions (frames, units, camera) are those of
:mod:`shared.geometry`. Images and clouds are numpy arrays (see :mod:`shared.arrays`); the binary
codec (:mod:`shared.codec`) moves them without copies.

Each model has a ``SCHEMA`` name and a ``VERSION``; the codec writes both into the envelope and
refuses a payload whose name or version does not match what the receiver expects.
"""

from .base import (  # noqa: F401
    WORLD_LIMIT_M,
    ANGLE_LIMIT_RAD,
    PITCH_LIMIT_RAD,
    TIME_LIMIT_S,
    SEQ_LIMIT,
    LABEL_LIMIT,
    Metres,
    Distance_m,
    Radians,
    Pitch_rad,
    Seconds,
    Xyz_m,
    LabelId,
    Count,
    Cost_usd,
    DepthNoiseRel,
    _ID_PATTERN,
    SegmentId,
    Duration_s,
    BudgetExceeded,
    RENDER_MAX_PIXELS,
    PANORAMA_MAX_PIXELS,
    VIEW_MAX_PIXELS,
    MAP_CHUNK_MAX_POINTS,
    BUILD_MAX_RECORDINGS,
    BUILD_MAX_FRAMES,
    IMPORT_MAX_BYTES,
    IMPORT_PART_BYTES,
    IMPORT_PART_MAX_BYTES,
    PATH_MAX_POINTS,
    FREE_FORM_MAX_ITEMS,
    FREE_FORM_MAX_ABS,
    check_free_form,
    _free_form_check,
    Message,
    _finite,
    _finite_array,
)
from .geometry import (  # noqa: F401
    Pose,
    CameraIntrinsics,
    ViewPose,
)
from .robot import (  # noqa: F401
    Panorama,
    Frame,
    MoveStatus,
    SceneViewsRequest,
    ObserveRequest,
    MoveRequest,
    MoveResult,
    TurnRequest,
    ResetRequest,
    PoseReply,
    RecordRequest,
    RecordReply,
    RoomInfo,
    ObjectInfo,
    SceneSummary,
    LoadSceneRequest,
    GeodesicRequest,
    GeodesicReply,
)
from .navigation import (  # noqa: F401
    CandidateKind,
    Candidate,
    CandidateSet,
    NavNode,
    NavEdge,
    NavGraph,
    Tour,
    TourRecording,
    OdomCorrection,
)
from .maps import (  # noqa: F401
    DriftCorrection,
    PoseGraphSummary,
    RegionDriftCorrection,
    MapInfo,
    MapLabelling,
    MapListReply,
    MapRequest,
    MapChunkRequest,
    MapChunk,
    BuildCancelRequest,
    BuildMapRequest,
    MapImportRequest,
    MapImportProgress,
)
from .render import (  # noqa: F401
    SplatMode,
    RenderRequest,
    RenderResult,
    MapRoomLabel,
    SpatialMapRequest,
    SpatialMapResult,
)
from .missions import (  # noqa: F401
    Decision,
    JobState,
    _meaningful_instruction,
    Instruction,
    MissionOptions,
    MissionRequest,
    JobAccepted,
    CancelRequest,
    JobEventKind,
    ExplorationRequest,
    ExplorationCancelRequest,
)
from .events import (  # noqa: F401
    UsageData,
    EpisodeMetricsData,
    EventPayload,
    _finite_xyz,
    MissionStarted,
    MissionStep,
    MissionEnd,
    _FINISHED_ENDS,
    MissionFinished,
    ExplorationStarted,
    ExplorationOutcome,
    StageProgress,
    ExplorationProgress,
    ExplorationFinished,
    MapBuildProgress,
    MapBuildFinished,
    JobCancelled,
    JobFailed,
    EventData,
    JobEvent,
)
from .service import (  # noqa: F401
    Ping,
    ServiceInfo,
    EndpointStats,
    ServiceMetrics,
    ErrorCode,
    ErrorReply,
)
from .scene_graph import (  # noqa: F401
    SCENE_GRAPH_MAX_ROOMS,
    SCENE_GRAPH_MAX_OBJECTS,
    SceneOpening,
    SceneRoom,
    SceneObject,
    SceneStairs,
    FloorGrid,
    SceneGraph,
    SceneGraphRequest,
)
