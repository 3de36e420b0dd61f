"""Frames and camera model shared by every service.

One place for the conventions of ../shared/BRIEF.md, so that the simulator, the renderer, the
reconstructor and the planner agree to the last pixel:

* World frame: metres, right-handed, **z up**; heading ``theta`` measured from +x towards +y
  (counter-clockwise seen from above).
* Agent pose: ``(x, y, z)`` is the point on the floor under the agent, ``heading_rad`` its yaw.
  The camera sits ``camera_height_m`` (1.25 m by default) above that point.
* Camera frame: OpenCV (x right, y down, z forward). Pitch is positive when looking up.
* Pinhole intrinsics from a horizontal field of view: ``fx = fy = (W/2) / tan(hfov/2)``,
  principal point at the centre of the pixel grid ``((W-1)/2, (H-1)/2)``.
* Depth images hold **z-depth** (distance along the optical axis) in metres, float32; ``0`` marks
  "no measurement" (a hole, a miss, a sensor drop-out).
* Panorama: 12 views, view ``i`` looks at ``heading - i * 30 deg`` (the agent "rotates right", as in the
  paper), pitch 0.
* Habitat / R2R-CE data is y-up (x right, y up, z backwards): :func:`habitat_to_world` and
  :func:`world_to_habitat` are the only conversion, used at the data boundary.
* Scene files: :func:`scene_file_to_world` is the linear map from a file's own axes to the world.
  **Invariant**: it is ``habitat_to_world`` applied after the transform Habitat itself gives the file
  (its ``up`` to Habitat +y, its ``front`` to Habitat -z, then ``scale``), so a vertex and an R2R-CE
  position that Habitat puts at the same place land at the same world point. For a file in Habitat's
  own frame (up +y, front -z, scale 1) it *is* ``habitat_to_world``; for a z-up file with front +y
  (Matterport3D, Replica) it is the identity.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

DEFAULT_CAMERA_HEIGHT_M = 1.25
PANORAMA_VIEWS = 12
PANORAMA_STEP_RAD = 2.0 * math.pi / PANORAMA_VIEWS


@dataclass(frozen=True)
class PinholeCamera:
    """A pinhole camera defined by its image size and horizontal field of view."""

    width_px: int = 256
    height_px: int = 256
    hfov_deg: float = 90.0

    def __post_init__(self) -> None:
        if self.width_px <= 0 or self.height_px <= 0:
            raise ValueError(f"image size must be positive, got {self.width_px}x{self.height_px}")
        if not 1.0 <= self.hfov_deg <= 179.0:
            raise ValueError(f"hfov_deg must be in [1, 179], got {self.hfov_deg}")

    @property
    def fx(self) -> float:
        return (self.width_px / 2.0) / math.tan(math.radians(self.hfov_deg) / 2.0)

    @property
    def fy(self) -> float:
        # Square pixels: the vertical focal length equals the horizontal one.
        return self.fx

    @property
    def cx(self) -> float:
        return (self.width_px - 1) / 2.0

    @property
    def cy(self) -> float:
        return (self.height_px - 1) / 2.0

    @property
    def vfov_deg(self) -> float:
        return math.degrees(2.0 * math.atan((self.height_px / 2.0) / self.fy))

    def matrix(self) -> np.ndarray:
        """The 3x3 intrinsic matrix K."""
        return np.array(
            [[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]], dtype=np.float64
        )

    def pixel_rays(self) -> np.ndarray:
        """Unit-z rays through every pixel centre in the camera frame, shape (H, W, 3).

        Multiplying a ray by a z-depth gives the camera-frame point that the pixel sees.
        """
        u = np.arange(self.width_px, dtype=np.float64)
        v = np.arange(self.height_px, dtype=np.float64)
        uu, vv = np.meshgrid(u, v)
        rays = np.stack(
            [(uu - self.cx) / self.fx, (vv - self.cy) / self.fy, np.ones_like(uu)], axis=-1
        )
        return rays


def camera_rotation(heading_rad: float, pitch_rad: float = 0.0) -> np.ndarray:
    """Rotation world_from_camera (columns: camera x/right, y/down, z/forward in world axes)."""
    ch, sh = math.cos(heading_rad), math.sin(heading_rad)
    cp, sp = math.cos(pitch_rad), math.sin(pitch_rad)
    forward = np.array([cp * ch, cp * sh, sp])
    right = np.array([sh, -ch, 0.0])
    down = np.cross(forward, right)
    return np.stack([right, down, forward], axis=1)


def camera_pose(
    position_m: np.ndarray | tuple[float, float, float],
    heading_rad: float,
    pitch_rad: float = 0.0,
    camera_height_m: float = DEFAULT_CAMERA_HEIGHT_M,
) -> np.ndarray:
    """4x4 world_from_camera for an agent standing at ``position_m`` (floor point)."""
    t = np.eye(4)
    t[:3, :3] = camera_rotation(heading_rad, pitch_rad)
    t[:3, 3] = np.asarray(position_m, dtype=np.float64) + np.array([0.0, 0.0, camera_height_m])
    return t


def camera_poses(position_m, headings_rad, pitches_rad, camera_height_m: float = DEFAULT_CAMERA_HEIGHT_M) -> np.ndarray:
    """(B, 4, 4) world_from_camera of one floor position at B headings and pitches: exactly the stacked
    :func:`camera_pose` results, in one array pass (a simulator's 12-view panorama calls this per step).

    The sines and cosines come from ``math`` as in :func:`camera_rotation` (numpy's vectorised ones
    may differ in the last bit); the cross product is written out in ``np.cross``'s order.
    """
    heads = np.atleast_1d(np.asarray(headings_rad, dtype=np.float64))
    pitches = np.broadcast_to(np.asarray(pitches_rad, dtype=np.float64), heads.shape)
    ch, sh = (np.array([f(float(h)) for h in heads]) for f in (math.cos, math.sin))
    cp, sp = (np.array([f(float(p)) for p in pitches]) for f in (math.cos, math.sin))
    forward = np.stack([cp * ch, cp * sh, sp], axis=1)
    right = np.stack([sh, -ch, np.zeros_like(sh)], axis=1)
    down = np.stack([
        forward[:, 1] * right[:, 2] - forward[:, 2] * right[:, 1],
        forward[:, 2] * right[:, 0] - forward[:, 0] * right[:, 2],
        forward[:, 0] * right[:, 1] - forward[:, 1] * right[:, 0],
    ], axis=1)
    t = np.zeros((len(heads), 4, 4))
    t[:, :3, 0], t[:, :3, 1], t[:, :3, 2] = right, down, forward
    t[:, 3, 3] = 1.0
    t[:, :3, 3] = np.asarray(position_m, dtype=np.float64) + np.array([0.0, 0.0, camera_height_m])
    return t


def world_to_camera(points_world: np.ndarray, world_from_camera: np.ndarray) -> np.ndarray:
    """Transform (N, 3) world points into the camera frame of ``world_from_camera``."""
    r = world_from_camera[:3, :3]
    t = world_from_camera[:3, 3]
    return (points_world - t) @ r


def depth_to_points(depth_m: np.ndarray, camera: PinholeCamera, world_from_camera: np.ndarray):
    """Back-project a z-depth image into world points; returns (points (N,3), valid mask (H,W))."""
    valid = np.isfinite(depth_m) & (depth_m > 0)
    rays = camera.pixel_rays()[valid]
    pts_cam = rays * depth_m[valid][:, None]
    pts_world = pts_cam @ world_from_camera[:3, :3].T + world_from_camera[:3, 3]
    return pts_world, valid


def panorama_headings(heading_rad: float, views: int = PANORAMA_VIEWS) -> np.ndarray:
    """Headings of the panorama's views: the agent rotates right (clockwise) in equal steps."""
    return wrap_angle(heading_rad - np.arange(views) * (2.0 * math.pi / views))


def wrap_angle(angle_rad):
    """Wrap an angle (scalar or array) to [-pi, pi)."""
    return (np.asarray(angle_rad) + math.pi) % (2.0 * math.pi) - math.pi


def interpolate_offsets(times_s, offsets, at_s) -> np.ndarray:
    """(len(at_s), 3) planar offsets ``(dx, dy, dyaw)`` at the times ``at_s``, linear in time between
    the entries ``offsets`` (N, 3) given at ``times_s`` (N,) in time order: the first before them, the
    last after them, the yaw along the shorter way between neighbours. A drifting robot's map <- odom
    correction between two fixes (issue 33: the mapper's panoramas, the reconstructor's frames)."""
    t = np.asarray(times_s, np.float64).reshape(-1)
    o = np.asarray(offsets, np.float64).reshape(-1, 3)
    a = np.atleast_1d(np.asarray(at_s, np.float64))
    if len(t) == 0:
        return np.zeros((len(a), 3))
    if len(t) == 1:
        return np.repeat(o, len(a), axis=0)
    yaw = o[0, 2] + np.concatenate([[0.0], np.cumsum(wrap_angle(np.diff(o[:, 2])))])
    return np.stack([np.interp(a, t, o[:, 0]), np.interp(a, t, o[:, 1]), wrap_angle(np.interp(a, t, yaw))], axis=1)


def rot_z(theta_rad: float) -> np.ndarray:
    """3x3 rotation about +z by ``theta_rad`` (counter-clockwise seen from above)."""
    c, s = math.cos(theta_rad), math.sin(theta_rad)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def planar_apply(t_xyz, yaw_rad: float, xyz, heading_rad: float) -> tuple[tuple[float, float, float], float]:
    """A pose ``(xyz, heading)`` moved by the planar rigid transform ``(t_xyz, yaw)``: turned by
    ``yaw`` about +z, then shifted by ``t_xyz`` (ROS's ``parent -> child`` transform applied to a pose
    in the child frame, e.g. ``map -> odom`` to an odometry pose)."""
    p = rot_z(yaw_rad) @ np.asarray(xyz, np.float64) + np.asarray(t_xyz, np.float64)
    return (float(p[0]), float(p[1]), float(p[2])), float(wrap_angle(heading_rad + yaw_rad))


def planar_between(from_xyz, from_heading_rad: float, to_xyz, to_heading_rad: float
                   ) -> tuple[tuple[float, float, float], float]:
    """The planar rigid transform ``(t_xyz, yaw)`` that :func:`planar_apply` turns the first pose into
    the second with (a localiser's ``map -> odom`` from an odometry pose and the true one)."""
    yaw = float(wrap_angle(to_heading_rad - from_heading_rad))
    t = np.asarray(to_xyz, np.float64) - rot_z(yaw) @ np.asarray(from_xyz, np.float64)
    return (float(t[0]), float(t[1]), float(t[2])), yaw


def _null_vectors(xx, yy, zz, xy, xz, yz, lam):
    """Unit vectors that ``C - lam I`` maps to (nearly) zero, C the symmetric 3x3 matrices given by their six
    entries: the longest cross product of two of its rows (both orthogonal to the null vector)."""
    a, b, c = xx - lam, yy - lam, zz - lam
    cs = np.stack([np.stack([xy * yz - xz * b, xz * xy - a * yz, a * b - xy * xy], axis=1),
                   np.stack([xy * c - xz * yz, xz * xz - a * c, a * yz - xy * xz], axis=1),
                   np.stack([b * c - yz * yz, yz * xz - xy * c, xy * yz - b * xz], axis=1)])
    sq = np.einsum("mni,mni->mn", cs, cs)
    best = np.argmax(sq, axis=0)
    i = np.arange(len(xx))
    with np.errstate(invalid="ignore", divide="ignore"):
        return cs[best, i] / np.sqrt(sq[best, i])[:, None]


def smallest_eigenvectors(xx, yy, zz, xy, xz, yz, min_gap: float = 1e-4) -> np.ndarray:
    """Unit eigenvectors of the smallest eigenvalues of symmetric 3x3 matrices given by their six entries.

    Closed form (the eigenvalues from the characteristic cubic's trigonometric solution, the vector as the
    null vector of ``C - lambda I``): in the reconstructor's registration a frame's normals were a third of
    the stands' and the drives' cost, and ``np.linalg.eigh`` (a LAPACK call a point) with its covariance
    einsum two thirds of that. A map's load in the renderer solved one per point too: its spacing and normals
    (``point_spacing_and_normals``, the tree given) took 2.8 -> 2.1 s of CPU on a 865,107-point map and
    3.6-3.8 -> 2.6-2.9 s on a 1,097,527-point one, and rendered the same pixels (the ladder's 96 views of
    both, every view's SSIM unchanged: where a sign differs from eigh's, the renderer orients the normal by
    the view directions or takes only its slope).

    It agrees with ``eigh`` to rounding wherever the smallest eigenvalue stands apart (6e-13 at most over
    214,514 stride points of the two-floor house's first four regions); where it does not (a line, repeated
    points: the normal is undefined) ``eigh`` decides, as before."""
    q = (xx + yy + zz) / 3.0
    a, b, c = xx - q, yy - q, zz - q
    p = np.sqrt((a * a + b * b + c * c + 2.0 * (xy * xy + xz * xz + yz * yz)) / 6.0)
    det = a * (b * c - yz * yz) - xy * (xy * c - yz * xz) + xz * (xy * yz - b * xz)
    with np.errstate(invalid="ignore", divide="ignore"):
        phi = np.arccos(np.clip(det / (2.0 * p ** 3), -1.0, 1.0)) / 3.0
    top = q + 2.0 * p * np.cos(phi)
    low = q + 2.0 * p * np.cos(phi + 2.0 * math.pi / 3.0)
    mid = 3.0 * q - top - low
    v = _null_vectors(xx, yy, zz, xy, xz, yz, low)
    # One Rayleigh quotient: the cubic's smallest root loses digits where the two largest nearly coincide (a
    # round patch of a plane); the quotient of a vector that close is exact to rounding.
    x, y, z = v[:, 0], v[:, 1], v[:, 2]
    v = _null_vectors(xx, yy, zz, xy, xz, yz, xx * x * x + yy * y * y + zz * z * z
                      + 2.0 * (xy * x * y + xz * x * z + yz * y * z))
    bad = ~((mid - low) > min_gap * top) | ~np.isfinite(v).all(axis=1)
    if bad.any():
        cov = np.stack([np.stack([xx, xy, xz], -1), np.stack([xy, yy, yz], -1), np.stack([xz, yz, zz], -1)], 1)
        v[bad] = np.linalg.eigh(cov[bad])[1][:, :, 0]
    return v


def pca_normals(neighbourhoods: np.ndarray) -> np.ndarray:
    """Unit normals (float64 (n, 3), sign arbitrary) of ``neighbourhoods`` (n, k, 3), each a point's k
    nearest points: the direction of least variance (principal component analysis, Hoppe et al. 1992,
    "Surface reconstruction from unorganized points"). One solver for the reconstructor's registration
    and the renderer's slopes and sides."""
    nb = neighbourhoods - neighbourhoods.mean(axis=1, keepdims=True)
    x, y, z = nb[..., 0], nb[..., 1], nb[..., 2]
    return smallest_eigenvectors((x * x).sum(1), (y * y).sum(1), (z * z).sum(1),
                                 (x * y).sum(1), (x * z).sum(1), (y * z).sum(1))


# --- Habitat (y up) <-> world (z up) -------------------------------------------------------------
# Habitat: x right, y up, z backwards. World: x, y horizontal, z up.
# world = (x_h, -z_h, y_h); this is a proper rotation (det = +1), so handedness is preserved.
_HAB_TO_WORLD = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])


def habitat_to_world(points_h) -> np.ndarray:
    """Convert Habitat (y-up) positions, shape (3,) or (N, 3), to world (z-up)."""
    return np.asarray(points_h, dtype=np.float64) @ _HAB_TO_WORLD.T


def world_to_habitat(points_w) -> np.ndarray:
    """Inverse of :func:`habitat_to_world`."""
    return np.asarray(points_w, dtype=np.float64) @ _HAB_TO_WORLD


def habitat_alignment(up, front) -> np.ndarray:
    """The rotation Habitat applies to an asset whose own up / front axes are ``up`` / ``front``.

    It maps ``up`` onto Habitat's +y (against gravity) and ``front`` onto Habitat's -z, like
    habitat-sim's stage and object ``up`` / ``front`` attributes. ``front`` is made orthogonal to
    ``up`` first; parallel or zero vectors raise ``ValueError``.
    """
    u = np.asarray(up, dtype=np.float64).reshape(3)
    f = np.asarray(front, dtype=np.float64).reshape(3)
    if not (np.all(np.isfinite(u)) and np.all(np.isfinite(f))) or np.linalg.norm(u) < 1e-9:
        raise ValueError(f"up must be a finite non-zero vector, got {tuple(u)}")
    u = u / np.linalg.norm(u)
    f = f - np.dot(f, u) * u
    if np.linalg.norm(f) < 1e-6:
        raise ValueError(f"front {tuple(front)} must not be parallel to up {tuple(up)}")
    f = f / np.linalg.norm(f)
    right = np.cross(f, u)  # Habitat: front (-z) x up (+y) = right (+x)
    # Rows: the asset axes that become Habitat x (right), y (up) and z (back).
    return np.stack([right, u, -f])


def scene_file_to_world(up=(0.0, 1.0, 0.0), front=(0.0, 0.0, -1.0), scale=(1.0, 1.0, 1.0)) -> np.ndarray:
    """3x3 map from a scene file's coordinates to the world: ``habitat_to_world . alignment . scale``.

    See the module docstring for the invariant; ``scale`` is per file axis (Habitat's stage
    ``scale`` times ``units_to_meters``).
    """
    s = np.asarray(scale, dtype=np.float64).reshape(-1)
    s = np.broadcast_to(s, (3,)) if s.size == 1 else s.reshape(3)
    if not np.all(np.isfinite(s)) or np.any(s <= 0):
        raise ValueError(f"scale must be finite and positive, got {tuple(s)}")
    return _HAB_TO_WORLD @ habitat_alignment(up, front) @ np.diag(s)


def habitat_quaternion_to_heading(q_xyzw) -> float:
    """Heading (world, z up) of a Habitat agent rotation quaternion [x, y, z, w].

    A Habitat agent looks along its local -z axis; we rotate that forward vector by the quaternion,
    convert it to the world frame and take its yaw.
    """
    x, y, z, w = (float(v) for v in q_xyzw)
    # Rotate v = (0, 0, -1) by q: v' = q v q*, expanded for this v.
    fx = -(2.0 * (x * z + w * y))
    fy = -(2.0 * (y * z - w * x))
    fz = -(1.0 - 2.0 * (x * x + y * y))
    fw = habitat_to_world(np.array([fx, fy, fz]))
    return float(math.atan2(fw[1], fw[0]))


def heading_to_habitat_quaternion(heading_rad: float) -> list[float]:
    """Habitat quaternion [x, y, z, w] (a rotation about Habitat's +y) for a world heading.

    Heading 0 (world +x) is Habitat +x, which a Habitat agent faces after turning -90 deg about y.
    """
    yaw_h = heading_rad - math.pi / 2.0  # rotation about +y that maps -z onto the heading
    return [0.0, math.sin(yaw_h / 2.0), 0.0, math.cos(yaw_h / 2.0)]
