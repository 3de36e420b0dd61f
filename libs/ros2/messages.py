"""The ROS 2 messages robot-io speaks, CDR-encoded through the ``rosbags`` typestore (never rclpy).

One typestore (ROS 2 Jazzy definitions) holds every message type; the two service types we use
(``std_srvs/srv/Trigger`` and ``turtlesim/srv/TeleportAbsolute``, the common teleport service of
simulators) are registered here, because rosbags ships messages only. Their RIHS01 type hashes follow
REP-2016 as rosidl computes them for a service: a ``<srv>`` description with ``request_message``,
``response_message`` and ``event_message`` fields (checked against rmw_zenoh's documented
``example_interfaces/srv/AddTwoInts`` hash in the tests).
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from rosbags.typesys import Stores, get_typestore, get_types_from_msg
from rosbags.typesys.store import Nodetype, Typestore

from .errors import Ros2ProtocolError

MESSAGES = {
    "image": "sensor_msgs/msg/Image",
    "compressed_image": "sensor_msgs/msg/CompressedImage",
    "camera_info": "sensor_msgs/msg/CameraInfo",
    "imu": "sensor_msgs/msg/Imu",
    "scan": "sensor_msgs/msg/LaserScan",
    "odometry": "nav_msgs/msg/Odometry",
    "occupancy_grid": "nav_msgs/msg/OccupancyGrid",
    "twist": "geometry_msgs/msg/Twist",
    "tf": "tf2_msgs/msg/TFMessage",
    "bool": "std_msgs/msg/Bool",
    "clock": "rosgraph_msgs/msg/Clock",
}

# name -> (request fields, response fields), in .srv syntax.
SERVICES = {
    "std_srvs/srv/Trigger": ("", "bool success\nstring message\n"),
    "turtlesim/srv/TeleportAbsolute": ("float32 x\nfloat32 y\nfloat32 theta\n", ""),
    # An action's cancel service (rcl_action). Constants are not part of the type hash (REP-2016);
    # the return codes are in ``libs.ros2.action.CancelReturn``.
    "action_msgs/srv/CancelGoal": ("action_msgs/GoalInfo goal_info\n",
                                   "int8 return_code\naction_msgs/GoalInfo[] goals_canceling\n"),
}

# name -> (goal, result, feedback fields), in .action syntax: the Jazzy definitions of
# ros-navigation/navigation2 nav2_msgs/action (Jazzy's bt_navigator fills NavigateToPose's
# error_code with the failing planner's or controller's code, see ``libs.ros2.action``). Error-code
# constants are left out: they do not enter the type hash, and the codes are data in ``action.py``.
# Other distros differ in fields, hence in hash and layout: Kilted's Spin goal adds ``bool
# disable_collision_checks``, Rolling's NavigateToPose feedback adds two tracking errors; a robot on
# them needs their definitions here (rmw_zenoh keys would not match, bridge payloads would not decode).
ACTIONS = {
    "nav2_msgs/action/NavigateToPose": (
        "geometry_msgs/PoseStamped pose\nstring behavior_tree\n",
        "uint16 error_code\nstring error_msg\n",
        "geometry_msgs/PoseStamped current_pose\nbuiltin_interfaces/Duration navigation_time\n"
        "builtin_interfaces/Duration estimated_time_remaining\nint16 number_of_recoveries\nfloat32 distance_remaining\n"),
    "nav2_msgs/action/Spin": (
        "float32 target_yaw\nbuiltin_interfaces/Duration time_allowance\n",
        "builtin_interfaces/Duration total_elapsed_time\nuint16 error_code\nstring error_msg\n",
        "float32 angular_distance_traveled\n"),
}


class CdrError(Ros2ProtocolError, ValueError):
    """A payload is not valid CDR for the type it arrived on (or a message cannot be encoded)."""


def _as_srv_names(o: Any) -> Any:
    # get_types_from_msg files every type under "<pkg>/msg/"; a service's parts live under "<pkg>/srv/"
    # (an action's under "<pkg>/action/").
    if isinstance(o, str):
        return o.replace("/srv/msg/", "/srv/").replace("/action/msg/", "/action/")
    if isinstance(o, (list, tuple)):
        return type(o)(_as_srv_names(x) for x in o)
    return o


def service_types(name: str, request: str, response: str) -> dict:
    """The typestore definitions of service ``name``: its Request, Response, Event and description."""
    short = name.rsplit("/", 1)[1]
    types: dict = {}
    types.update(get_types_from_msg(request, f"{name}_Request"))
    types.update(get_types_from_msg(response, f"{name}_Response"))
    types.update(get_types_from_msg(
        f"service_msgs/msg/ServiceEventInfo info\n{short}_Request[<=1] request\n{short}_Response[<=1] response\n",
        f"{name}_Event"))
    types.update(get_types_from_msg(
        f"{short}_Request request_message\n{short}_Response response_message\n{short}_Event event_message\n", name))
    return {_as_srv_names(k): _as_srv_names(v) for k, v in types.items()}


def action_types(name: str, goal: str, result: str, feedback: str) -> dict:
    """The typestore definitions of action ``name`` as rosidl generates them: its Goal, Result and
    Feedback messages, the ``_SendGoal`` and ``_GetResult`` services (each hashed like any service,
    which is the hash rmw_zenoh puts in their keys) and the ``_FeedbackMessage`` topic type."""
    short = name.rsplit("/", 1)[1]
    types: dict = {}
    types.update(get_types_from_msg(goal, f"{name}_Goal"))
    types.update(get_types_from_msg(result, f"{name}_Result"))
    types.update(get_types_from_msg(feedback, f"{name}_Feedback"))
    types.update(service_types(f"{name}_SendGoal", f"unique_identifier_msgs/UUID goal_id\n{short}_Goal goal\n",
                               "bool accepted\nbuiltin_interfaces/Time stamp\n"))
    types.update(service_types(f"{name}_GetResult", "unique_identifier_msgs/UUID goal_id\n",
                               f"int8 status\n{short}_Result result\n"))
    types.update(get_types_from_msg(f"unique_identifier_msgs/UUID goal_id\n{short}_Feedback feedback\n",
                                    f"{name}_FeedbackMessage"))
    return {_as_srv_names(k): _as_srv_names(v) for k, v in types.items()}


def _fix_char_arrays(store: Typestore) -> None:
    # In ROS 2 .msg files ``char`` is an alias of uint8 (rosidl maps it so, and the type hash sees
    # uint8); rosbags keeps ``char``, which changes nothing in CDR (one byte) but changes the hash of
    # service_msgs/ServiceEventInfo (char[16] client_gid) and so of every service description.
    for name, (consts, fields) in list(store.fielddefs.items()):
        new = []
        changed = False
        for fname, desc in fields:
            if desc[0] == Nodetype.ARRAY and desc[1][0] == (Nodetype.BASE, ("char", 0)):
                desc = (Nodetype.ARRAY, ((Nodetype.BASE, ("uint8", 0)), desc[1][1]))
                changed = True
            new.append((fname, desc))
        if changed:
            store.fielddefs[name] = (consts, new)


@functools.cache
def typestore() -> Typestore:
    """The process-wide typestore (Jazzy messages + our services); built once."""
    store = get_typestore(Stores.ROS2_JAZZY)
    for name, (req, resp) in SERVICES.items():
        store.register(service_types(name, req, resp))
    for name, (goal, result, feedback) in ACTIONS.items():
        store.register(action_types(name, goal, result, feedback))
    _fix_char_arrays(store)
    return store


@dataclass(frozen=True)
class RosType:
    """A ROS 2 interface type: ``pkg/msg/Name`` or ``pkg/srv/Name``."""

    name: str

    @property
    def dds_name(self) -> str:
        """The DDS type name rmw_zenoh puts in keys, e.g. ``std_msgs::msg::dds_::String_``."""
        pkg, kind, short = self.name.split("/")
        return f"{pkg}::{kind}::dds_::{short}_"

    @property
    def type_hash(self) -> str:
        return type_hash(self.name)

    @property
    def is_service(self) -> bool:
        """A service, an action's generated ``_SendGoal``/``_GetResult`` services included."""
        kind = self.name.split("/")[1]
        return kind == "srv" or (kind == "action" and self.name.endswith(("_SendGoal", "_GetResult")))


@functools.cache
def type_hash(name: str) -> str:
    """The RIHS01 type hash of a message or service (REP-2016), from the typestore."""
    store = typestore()
    if name not in store.fielddefs:
        raise CdrError(f"unknown ROS type {name!r}")
    return store.hash_rihs01(name)


def msg_class(name: str):
    return typestore().types[name]


def encode(name: str, msg: Any) -> bytes:
    """CDR (little endian, with the 4-byte encapsulation header) of ``msg`` of type ``name``."""
    try:
        return bytes(typestore().serialize_cdr(msg, name))
    except Exception as exc:  # rosbags raises assorted errors on a malformed message
        raise CdrError(f"cannot encode {name}: {exc}") from exc


def decode(name: str, data: bytes | memoryview) -> Any:
    try:
        return typestore().deserialize_cdr(bytes(data), name)
    except Exception as exc:
        raise CdrError(f"not a valid {name}: {type(exc).__name__}: {exc}") from exc


def new(name: str, **fields) -> Any:
    return msg_class(name)(**fields)


# --- builders and readers of the messages robot-io uses -----------------------------------------------------


def stamp(t_s: float):
    sec = math.floor(t_s)
    return new("builtin_interfaces/msg/Time", sec=int(sec), nanosec=int(round((t_s - sec) * 1e9)) % 1_000_000_000)


def stamp_s(t) -> float:
    return float(t.sec) + float(t.nanosec) * 1e-9


def header(t_s: float, frame_id: str):
    return new("std_msgs/msg/Header", stamp=stamp(t_s), frame_id=frame_id)


def vector3(x=0.0, y=0.0, z=0.0):
    return new("geometry_msgs/msg/Vector3", x=float(x), y=float(y), z=float(z))


def quaternion_from_yaw(yaw_rad: float):
    return new("geometry_msgs/msg/Quaternion", x=0.0, y=0.0, z=math.sin(yaw_rad / 2), w=math.cos(yaw_rad / 2))


def yaw_from_quaternion(q) -> float:
    return math.atan2(2.0 * (q.w * q.z + q.x * q.y), 1.0 - 2.0 * (q.y * q.y + q.z * q.z))


def twist(linear_mps: float = 0.0, angular_rps: float = 0.0):
    return new(MESSAGES["twist"], linear=vector3(linear_mps), angular=vector3(0.0, 0.0, angular_rps))


def odometry(t_s: float, xyz, yaw_rad: float, v_mps: float, w_rps: float, frame="odom", child="base_link"):
    cov = np.zeros(36, np.float64)
    pose = new("geometry_msgs/msg/PoseWithCovariance", pose=new(
        "geometry_msgs/msg/Pose", position=new("geometry_msgs/msg/Point", x=float(xyz[0]), y=float(xyz[1]), z=float(xyz[2])),
        orientation=quaternion_from_yaw(yaw_rad)), covariance=cov)
    tw = new("geometry_msgs/msg/TwistWithCovariance", twist=twist(v_mps, w_rps), covariance=cov.copy())
    return new(MESSAGES["odometry"], header=header(t_s, frame), child_frame_id=child, pose=pose, twist=tw)


# Image encodings: name -> (numpy dtype, channels).
ENCODINGS = {"rgb8": (np.uint8, 3), "bgr8": (np.uint8, 3), "mono8": (np.uint8, 1), "16UC1": (np.uint16, 1),
             "mono16": (np.uint16, 1), "32FC1": (np.float32, 1), "32SC1": (np.int32, 1)}


def image(t_s: float, frame_id: str, array: np.ndarray, encoding: str):
    if encoding not in ENCODINGS:
        raise CdrError(f"unsupported image encoding {encoding!r}; known: {sorted(ENCODINGS)}")
    dtype, ch = ENCODINGS[encoding]
    a = np.ascontiguousarray(array, dtype=dtype)
    h, w = a.shape[:2]
    if (a.ndim == 3 and a.shape[2] != ch) or (a.ndim == 2 and ch != 1):
        raise CdrError(f"{encoding} needs {ch} channel(s), got shape {a.shape}")
    return new(MESSAGES["image"], header=header(t_s, frame_id), height=h, width=w, encoding=encoding,
               is_bigendian=0, step=w * ch * a.itemsize, data=a.view(np.uint8).reshape(-1))


def image_array(msg) -> np.ndarray:
    """The pixels of a sensor_msgs/Image as (H, W[, C]) numpy, in its own encoding (validated)."""
    enc = msg.encoding
    if enc not in ENCODINGS:
        raise CdrError(f"unsupported image encoding {enc!r}; known: {sorted(ENCODINGS)}")
    dtype, ch = ENCODINGS[enc]
    item = np.dtype(dtype).itemsize
    h, w, step = int(msg.height), int(msg.width), int(msg.step)
    if h <= 0 or w <= 0 or step < w * ch * item or len(msg.data) < h * step:
        raise CdrError(f"image {w}x{h} step {step} does not fit its {len(msg.data)} bytes")
    rows = np.asarray(msg.data[: h * step]).reshape(h, step)[:, : w * ch * item]
    a = np.ascontiguousarray(rows).view(np.dtype(dtype).newbyteorder(">" if msg.is_bigendian else "<"))
    a = a.astype(dtype, copy=False).reshape((h, w, ch) if ch > 1 else (h, w))
    return a


def compressed_image(t_s: float, frame_id: str, rgb: np.ndarray, quality: int = 90, fmt: str = "jpeg"):
    """A colour frame as image_transport's ``compressed`` plugin publishes it: ``fmt`` jpeg or png,
    the format field ``"rgb8; <fmt> compressed bgr8"`` (the codec stores BGR, as OpenCV does)."""
    import cv2

    if fmt not in ("jpeg", "png"):
        raise CdrError(f"unsupported compressed format {fmt!r}: jpeg or png")
    params = [cv2.IMWRITE_JPEG_QUALITY, quality] if fmt == "jpeg" else [cv2.IMWRITE_PNG_COMPRESSION, 1]
    ok, buf = cv2.imencode(".jpg" if fmt == "jpeg" else ".png", np.ascontiguousarray(rgb[..., ::-1]), params)
    if not ok:
        raise CdrError(f"{fmt} encoding failed")
    return new(MESSAGES["compressed_image"], header=header(t_s, frame_id), format=f"rgb8; {fmt} compressed bgr8",
               data=buf.reshape(-1))


# compressed_depth_image_transport's ConfigHeader: int32 compressionFormat (INV_DEPTH = 0), then
# float32 depthParam[2] (the inverse-depth quantisation of 32FC1; unused for 16UC1), little endian.
_DEPTH_HEADER = np.dtype([("format", "<i4"), ("quant_a", "<f4"), ("quant_b", "<f4")])
DEPTH_HEADER_BYTES = _DEPTH_HEADER.itemsize  # 12


def compressed_depth(t_s: float, frame_id: str, depth_mm: np.ndarray, png_level: int = 1):
    """16UC1 depth (millimetres, 0 = none) as compressed_depth_image_transport publishes it:
    format ``"16UC1; compressedDepth png"``, data = ConfigHeader + a 16-bit PNG."""
    import cv2

    a = np.ascontiguousarray(depth_mm, dtype=np.uint16)
    ok, buf = cv2.imencode(".png", a, [cv2.IMWRITE_PNG_COMPRESSION, png_level])
    if not ok:
        raise CdrError("compressedDepth PNG encoding failed")
    head = np.zeros(1, _DEPTH_HEADER)
    return new(MESSAGES["compressed_image"], header=header(t_s, frame_id), format="16UC1; compressedDepth png",
               data=np.concatenate([head.view(np.uint8), buf.reshape(-1)]))


def compressed_depth_m(msg) -> np.ndarray:
    """Depth in metres (float32, 0 = none) from a ``compressedDepth`` CompressedImage: 16UC1
    millimetres, or 32FC1 as quantised inverse depth (depth = a / (q - b), q = 0 none)."""
    import cv2

    fmt = str(msg.format)
    data = np.asarray(msg.data, np.uint8)
    if "compressedDepth" not in fmt or len(data) <= DEPTH_HEADER_BYTES:
        raise CdrError(f"not a compressedDepth image ({fmt!r}, {len(data)} bytes)")
    if "rvl" in fmt.lower():
        raise CdrError("compressedDepth rvl is not supported: publish png (the plugin's default)")
    head = data[:DEPTH_HEADER_BYTES].view(_DEPTH_HEADER)[0]
    img = cv2.imdecode(data[DEPTH_HEADER_BYTES:], cv2.IMREAD_UNCHANGED)
    if img is None or img.dtype != np.uint16 or img.ndim != 2:
        raise CdrError(f"compressedDepth payload is not a 16-bit single-channel PNG ({fmt!r})")
    if fmt.startswith("16UC1"):
        return img.astype(np.float32) / 1000.0
    if fmt.startswith("32FC1"):
        a, b = float(head["quant_a"]), float(head["quant_b"])
        if not (math.isfinite(a) and math.isfinite(b)) or a <= 0:
            raise CdrError(f"compressedDepth 32FC1 with bad quantisation ({a}, {b})")
        q = img.astype(np.float32)
        with np.errstate(divide="ignore"):
            d = np.where(q > 0, a / (q - b), 0.0)
        return np.where(np.isfinite(d) & (d > 0), d, 0.0).astype(np.float32)
    raise CdrError(f"compressedDepth of {fmt.split(';')[0]!r}: 16UC1 or 32FC1")


def compressed_rgb(msg) -> np.ndarray:
    import cv2

    img = cv2.imdecode(np.asarray(msg.data, np.uint8), cv2.IMREAD_COLOR)
    if img is None:
        raise CdrError(f"cannot decode CompressedImage ({msg.format!r})")
    return np.ascontiguousarray(img[..., ::-1])


def camera_info(t_s: float, frame_id: str, width: int, height: int, fx: float, fy: float, cx: float, cy: float):
    k = np.array([fx, 0, cx, 0, fy, cy, 0, 0, 1], np.float64)
    p = np.array([fx, 0, cx, 0, 0, fy, cy, 0, 0, 0, 1, 0], np.float64)
    roi = new("sensor_msgs/msg/RegionOfInterest", x_offset=0, y_offset=0, height=0, width=0, do_rectify=False)
    return new(MESSAGES["camera_info"], header=header(t_s, frame_id), height=height, width=width,
               distortion_model="plumb_bob", d=np.zeros(5, np.float64), k=k, r=np.eye(3).reshape(-1), p=p,
               binning_x=0, binning_y=0, roi=roi)


def imu(t_s: float, frame_id: str, yaw_rad: float, w_rps: float):
    cov = np.zeros(9, np.float64)
    return new(MESSAGES["imu"], header=header(t_s, frame_id), orientation=quaternion_from_yaw(yaw_rad),
               orientation_covariance=cov, angular_velocity=vector3(0, 0, w_rps), angular_velocity_covariance=cov.copy(),
               linear_acceleration=vector3(0, 0, 9.81), linear_acceleration_covariance=cov.copy())


def laser_scan(t_s: float, frame_id: str, ranges: np.ndarray, angle_min: float, angle_increment: float,
               range_min: float, range_max: float, scan_time_s: float = 0.1):
    r = np.asarray(ranges, np.float32)
    return new(MESSAGES["scan"], header=header(t_s, frame_id), angle_min=float(angle_min),
               angle_max=float(angle_min + angle_increment * (len(r) - 1)), angle_increment=float(angle_increment),
               time_increment=0.0, scan_time=float(scan_time_s), range_min=float(range_min), range_max=float(range_max),
               ranges=r, intensities=np.zeros(0, np.float32))


def transform_stamped(t_s: float, parent: str, child: str, xyz, yaw_rad: float):
    tr = new("geometry_msgs/msg/Transform", translation=vector3(*xyz), rotation=quaternion_from_yaw(yaw_rad))
    return new("geometry_msgs/msg/TransformStamped", header=header(t_s, parent), child_frame_id=child, transform=tr)


def tf_message(transforms: list):
    return new(MESSAGES["tf"], transforms=transforms)


def occupancy_grid(t_s: float, frame_id: str, grid: np.ndarray, resolution_m: float, origin_xy_m):
    """``grid`` (H, W) int8: -1 unknown, 0 free, 100 occupied; row 0 at origin y (ROS convention)."""
    h, w = grid.shape
    origin = new("geometry_msgs/msg/Pose", position=new("geometry_msgs/msg/Point", x=float(origin_xy_m[0]),
                 y=float(origin_xy_m[1]), z=0.0), orientation=quaternion_from_yaw(0.0))
    info = new("nav_msgs/msg/MapMetaData", map_load_time=stamp(t_s), resolution=float(resolution_m), width=w, height=h,
               origin=origin)
    return new(MESSAGES["occupancy_grid"], header=header(t_s, frame_id), info=info,
               data=np.ascontiguousarray(grid, np.int8).reshape(-1))


def clock(t_s: float):
    return new(MESSAGES["clock"], clock=stamp(t_s))


def boolean(v: bool):
    return new(MESSAGES["bool"], data=bool(v))


def trigger_response(success: bool, message: str):
    return new("std_srvs/srv/Trigger_Response", success=bool(success), message=str(message))
