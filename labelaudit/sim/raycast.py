"""A spinning LiDAR that ray-casts a :class:`~labelaudit.sim.scene.Scene` into a range image.
Pure NumPy; no I/O.

The range image is the sensor's native output and the layout Waymo stores: rows are beams, the top
row has the highest elevation; columns are azimuth, from +π at column 0 down to −π (Waymo's
convention: column ``j`` looks at vehicle-frame azimuth ``π·(W − 2j − 1)/W``, i.e. the sensor-frame
azimuth is that minus the extrinsic's yaw). Points are derived from the range image, so a Waymo
writer that stores the range image, the inclinations and the extrinsic reproduces exactly the
points a KITTI writer stores.

Speed: the ground is hit in closed form for all rays at once; each object is intersected (slab
test, vectorised over its parts) only with the rays inside its azimuth sector and elevation band.
A depth buffer keeps the first hit per ray, which is what makes occlusion natural.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from labelaudit import constants as C
from labelaudit.core.geometry import invert_transform
from labelaudit.sim.scene import VEGETATION, Scene, corners_of

FloatArray = NDArray[np.float64]

NO_RETURN = -1.0
"""Range value of a pixel without a return (Waymo readers drop range ≤ 0)."""
HIT_GROUND = -1
"""``RangeImage.hit`` value of a ray whose first hit is the ground."""
HIT_NOTHING = -2
"""``RangeImage.hit`` value of a ray that hits nothing within the maximum range."""
HIT_CLUTTER = -3
"""``RangeImage.hit`` value of a ray whose first hit is unlabelled clutter (``Scene.clutter``)."""


@dataclass(frozen=True)
class LidarSpec:
    """A spinning multi-beam LiDAR (KITTI's Velodyne HDL-64E by default).

    Attributes
    ----------
    beams : number of rows (lasers)
    inclination_max_deg, inclination_min_deg : elevation of the top and bottom beam; beams are
        evenly spaced between them unless ``inclinations_deg`` is given
    columns : azimuth samples per sweep (360° / columns = the azimuth step)
    min_range, max_range : returns outside [min, max] metres are dropped
    range_noise_std : std of the Gaussian noise added to every range (m)
    dropout : probability that a return goes missing, at any range
    far_dropout : additional dropout probability at ``max_range``, growing with (range / max)²
    sensor_height : height of the sensor above the ground (m) in the KITTI rendering
    inclinations_deg : optional explicit beam elevations, top row first (length ``beams``)
    """

    beams: int = C.SIM_BEAMS
    inclination_max_deg: float = C.SIM_INCLINATION_DEG[0]
    inclination_min_deg: float = C.SIM_INCLINATION_DEG[1]
    columns: int = C.SIM_COLUMNS
    min_range: float = C.SIM_RANGE_LIMITS[0]
    max_range: float = C.SIM_RANGE_LIMITS[1]
    range_noise_std: float = C.SIM_RANGE_NOISE
    dropout: float = C.SIM_DROPOUT[0]
    far_dropout: float = C.SIM_DROPOUT[1]
    sensor_height: float = C.SIM_SENSOR_HEIGHT
    inclinations_deg: tuple[float, ...] | None = None

    def __post_init__(self) -> None:
        problems = []
        if self.beams < 1:
            problems.append(f"beams must be >= 1, got {self.beams}")
        if self.columns < 8:
            problems.append(f"columns must be >= 8, got {self.columns}")
        if not -90.0 < self.inclination_min_deg <= self.inclination_max_deg < 90.0:
            problems.append(
                f"need -90 < inclination_min_deg <= inclination_max_deg < 90, got "
                f"{self.inclination_min_deg}, {self.inclination_max_deg}"
            )
        if not 0.0 <= self.min_range < self.max_range:
            problems.append(f"need 0 <= min_range < max_range, got {self.min_range}, {self.max_range}")
        if self.range_noise_std < 0:
            problems.append(f"range_noise_std must be >= 0, got {self.range_noise_std}")
        if not (0.0 <= self.dropout <= 1.0 and 0.0 <= self.far_dropout <= 1.0):
            problems.append(f"dropout and far_dropout must be in [0, 1], got {self.dropout}, {self.far_dropout}")
        if self.sensor_height <= 0:
            problems.append(f"sensor_height must be > 0, got {self.sensor_height}")
        if self.inclinations_deg is not None:
            inc = np.asarray(self.inclinations_deg, dtype=float)
            if inc.shape != (self.beams,) or np.any(np.diff(inc) >= 0):
                problems.append(f"inclinations_deg must be {self.beams} strictly decreasing values (top row first)")
        if problems:
            raise ValueError("invalid LidarSpec: " + "; ".join(problems))

    @property
    def azimuth_step_deg(self) -> float:
        return 360.0 / self.columns

    @classmethod
    def coarse(cls, **overrides: float) -> "LidarSpec":
        """A cheap sensor for tests and quick looks: 32 beams, 0.5° azimuth step."""
        params: dict = {"beams": 32, "columns": 720}
        params.update(overrides)
        return cls(**params)

    def inclinations(self) -> FloatArray:
        """(H,) beam elevations in radians, top row first (strictly decreasing)."""
        if self.inclinations_deg is not None:
            return np.deg2rad(np.asarray(self.inclinations_deg, dtype=float))
        if self.beams == 1:
            return np.deg2rad(np.array([self.inclination_max_deg]))
        return np.deg2rad(np.linspace(self.inclination_max_deg, self.inclination_min_deg, self.beams))

    def azimuths(self, extrinsic: FloatArray | None = None) -> FloatArray:
        """(W,) sensor-frame azimuth of every column in radians (Waymo convention, see module doc)."""
        w = self.columns
        az = np.pi * (w - 2.0 * np.arange(w) - 1.0) / w
        return az - _extrinsic_yaw(extrinsic)


@dataclass(frozen=True)
class SeeThrough:
    """How far vehicles let LiDAR rays through, as real ones do (default: opaque boxes).

    Attributes
    ----------
    glass : share of the rays that meet a car's or van's windows — the side, front and rear faces
        of its cabin part, not the roof — and pass through them; such a ray goes on through the
        cabin (the windows on the far side too) and ends on the interior (the body's top inside the
        car), the ground behind it or whatever lies beyond
    under : share of the rays that meet a vehicle (Car, Van, Truck) lower than its ground
        clearance above the ground and pass under its body (the rest hit wheels, axles and sills);
        the clearance of every vehicle is drawn uniformly from ``SIM_CHASSIS_CLEARANCE[class]``
    """

    glass: float = 0.0
    under: float = 0.0

    def __post_init__(self) -> None:
        for name in ("glass", "under"):
            v = getattr(self, name)
            if not 0.0 <= v <= 1.0:
                raise ValueError(f"SeeThrough.{name} must be a share in [0, 1], got {v}")

    @property
    def active(self) -> bool:
        return self.glass > 0.0 or self.under > 0.0

    def clearances(self, class_names: list[str], rng: np.random.Generator) -> FloatArray:
        """Ground clearance (m) of every object (K,): drawn for vehicles, 0 for the rest (one
        uniform draw per object, whatever its class, so the draws of a frame do not depend on it)."""
        u = rng.random(len(class_names))
        out = np.zeros(len(class_names))
        for j, c in enumerate(class_names):
            if c in C.SIM_CHASSIS_CLEARANCE:
                lo, hi = C.SIM_CHASSIS_CLEARANCE[c]
                out[j] = lo + (hi - lo) * u[j]
        return out


OpenRule = Callable[[int, FloatArray, NDArray[np.int64]], NDArray[np.int8]]
"""Which rays pass part p: (p, distance to the part (M,), entry axis (M,)) → 1 glass, 2 under the chassis, 0 stopped."""

GLASS_CLASSES = ("Car", "Van")
"""Classes whose second part (the cabin) is glass on its side, front and rear faces."""


def _extrinsic_yaw(extrinsic: FloatArray | None) -> float:
    if extrinsic is None:
        return 0.0
    return float(np.arctan2(extrinsic[1, 0], extrinsic[0, 0]))


@dataclass
class RangeImage:
    """The output of one sweep.

    Attributes
    ----------
    range : (H, W) float32 range along each ray (m); ``NO_RETURN`` (−1) where nothing came back
    intensity : (H, W) float32 return intensity in [0, 1]; 0 where nothing came back
    hit : (H, W) int32 first hit per ray before noise/dropout: object index, ``HIT_GROUND``,
        ``HIT_CLUTTER`` or ``HIT_NOTHING``
    inclinations : (H,) beam elevations (rad), top row first
    azimuths : (W,) sensor-frame azimuth of each column (rad), decreasing
    extrinsic : (4, 4) sensor pose in the scene frame (``T_scene_sensor``)
    ray_counts : (K,) rays that geometrically intersect each object within range, occluded or not
    visible_counts : (K,) rays whose first hit is the object (before noise and dropout)
    return_counts : (K,) returns kept on the object (after noise, dropout and range limits) — the
        number of LiDAR points on it
    passed : (H, W) int32 the object whose glass or chassis the ray passed (the nearest such one;
        −1 none: every ray without :class:`SeeThrough`)
    glass_counts, under_counts : (K,) rays that reached the object's windows / the gap under it
        (nothing nearer stopped them) and passed through (0 without :class:`SeeThrough`)
    clearance : (K,) the objects' ground clearance (m; 0 without :class:`SeeThrough` ``under``)
    """

    range: NDArray[np.float32]
    intensity: NDArray[np.float32]
    hit: NDArray[np.int32]
    inclinations: FloatArray
    azimuths: FloatArray
    extrinsic: FloatArray
    ray_counts: NDArray[np.int64]
    visible_counts: NDArray[np.int64]
    return_counts: NDArray[np.int64]
    object_rays: list[tuple[slice, NDArray[np.int64]]] = field(default_factory=list, repr=False)
    passed: NDArray[np.int32] | None = field(default=None, repr=False)
    glass_counts: NDArray[np.int64] | None = None
    under_counts: NDArray[np.int64] | None = None
    clearance: FloatArray | None = None

    @property
    def valid(self) -> NDArray[np.bool_]:
        """(H, W) pixels with a return."""
        return self.range > 0

    @property
    def occlusion_fraction(self) -> FloatArray:
        """(K,) share of each object's rays that hit something else first (NaN without rays)."""
        with np.errstate(invalid="ignore", divide="ignore"):
            return 1.0 - self.visible_counts / np.where(self.ray_counts > 0, self.ray_counts, np.nan)

    def points(self, frame: str = "scene") -> tuple[NDArray[np.float32], NDArray[np.int32]]:
        """Points of all returns, row-major over the range image.

        Parameters
        ----------
        frame : "scene" (the extrinsic applied) or "sensor"

        Returns
        -------
        points : (N, 4) float32 x, y, z, intensity
        hit : (N,) int32 what each point hit (object index, ``HIT_GROUND`` or ``HIT_CLUTTER``)
        """
        if frame not in ("scene", "sensor"):
            raise ValueError(f"frame must be 'scene' or 'sensor', got {frame!r}")
        valid = self.range > 0
        # float32 throughout: the output is float32, and 1e-7 relative is far below the range noise.
        r = self.range
        horiz = r * np.cos(self.inclinations).astype(np.float32)[:, None]
        out = np.empty((int(np.count_nonzero(valid)), 4), dtype=np.float32)
        out[:, 0] = (horiz * np.cos(self.azimuths).astype(np.float32))[valid]
        out[:, 1] = (horiz * np.sin(self.azimuths).astype(np.float32))[valid]
        out[:, 2] = (r * np.sin(self.inclinations).astype(np.float32)[:, None])[valid]
        out[:, 3] = self.intensity[valid]
        if frame == "scene" and not np.array_equal(self.extrinsic, np.eye(4)):
            xyz = out[:, :3].astype(np.float64) @ self.extrinsic[:3, :3].T + self.extrinsic[:3, 3]
            out[:, :3] = xyz
        return out, self.hit[valid]


def ray_directions(inclinations: FloatArray, azimuths: FloatArray) -> FloatArray:
    """(H, W, 3) unit ray directions in the sensor frame for every range-image pixel."""
    ci, si = np.cos(inclinations)[:, None], np.sin(inclinations)[:, None]
    ca, sa = np.cos(azimuths)[None, :], np.sin(azimuths)[None, :]
    return np.stack(np.broadcast_arrays(ci * ca, ci * sa, si + 0.0 * ca), axis=-1)


@functools.lru_cache(maxsize=16)
def _scene_directions(lidar: LidarSpec, extrinsic_bytes: bytes) -> NDArray[np.float32]:
    """(H, W, 3) float32 ray directions in the scene frame, cached per sensor and pose (read-only)."""
    T = np.frombuffer(extrinsic_bytes, dtype=np.float64).reshape(4, 4)
    dirs = ray_directions(lidar.inclinations(), lidar.azimuths(T))
    if not np.array_equal(T[:3, :3], np.eye(3)):
        dirs = (dirs.reshape(-1, 3) @ T[:3, :3].T).reshape(dirs.shape)
    out = dirs.astype(np.float32)
    out.flags.writeable = False
    return out


def _column_window(az_lo: float, az_hi: float, extrinsic_yaw: float, width: int) -> NDArray[np.int64]:
    """Columns whose azimuth lies in the sensor-frame sector [az_lo, az_hi] (may wrap), padded by one."""
    # Column j looks at sensor azimuth π(W − 2j − 1)/W − yaw  ⇒  j = (π − yaw − az)·W/(2π) − ½.
    scale = width / (2.0 * np.pi)
    j0 = int(np.floor((np.pi - extrinsic_yaw - az_hi) * scale - 0.5)) - 1
    j1 = int(np.ceil((np.pi - extrinsic_yaw - az_lo) * scale - 0.5)) + 1
    if j1 - j0 + 1 >= width:
        return np.arange(width)
    return np.arange(j0, j1 + 1) % width


def _object_window(
    corners_sensor: FloatArray, inclinations: FloatArray, extrinsic_yaw: float, width: int, max_range: float
) -> tuple[slice, NDArray[np.int64]] | None:
    """Rows (a slice) and columns that can see a convex object given its 8 corners in the sensor frame.

    The azimuth extremes of a convex solid seen from outside are at its corners. Elevation is
    bounded conservatively from the corners' height range and the horizontal distance range.
    """
    xy = corners_sensor[:, :2]
    centre = xy.mean(axis=0)
    horiz = np.linalg.norm(xy, axis=1)
    radius = np.max(np.linalg.norm(xy - centre, axis=1))
    d_min = max(np.linalg.norm(centre) - radius, 1e-3)
    d_max = float(horiz.max())
    if d_min > max_range:
        return None
    if np.linalg.norm(centre) <= radius:  # sensor inside the footprint: every ray may hit
        az = (-np.pi, np.pi)
        rows = slice(0, len(inclinations))
        return rows, np.arange(width)
    az_c = np.arctan2(centre[1], centre[0])
    delta = (np.arctan2(xy[:, 1], xy[:, 0]) - az_c + np.pi) % (2 * np.pi) - np.pi
    az = (az_c + delta.min(), az_c + delta.max())
    z_lo, z_hi = corners_sensor[:, 2].min(), corners_sensor[:, 2].max()
    el_hi = np.arctan2(z_hi, d_min if z_hi > 0 else d_max)
    el_lo = np.arctan2(z_lo, d_min if z_lo < 0 else d_max)
    eps = 1e-9
    # inclinations are decreasing: rows with el_lo <= inc <= el_hi form one contiguous run.
    r0 = int(np.searchsorted(-inclinations, -el_hi - eps, side="left"))
    r1 = int(np.searchsorted(-inclinations, -el_lo + eps, side="right"))
    if r1 <= r0:
        return None
    return slice(r0, r1), _column_window(az[0], az[1], extrinsic_yaw, width)


def _intersect_boxes(origin: FloatArray, dirs: FloatArray, boxes: FloatArray) -> tuple[FloatArray, NDArray[np.int64]]:
    """Slab test of rays from one origin, each against its own yaw-rotated box.

    Parameters
    ----------
    origin : (3,) ray origin (scene frame), outside the boxes
    dirs : (M, 3) unit directions (scene frame)
    boxes : (M, 7) one box per ray

    Returns
    -------
    t : (M,) distance to the entry point, ``inf`` for a miss
    axis : (M,) local axis (0 x, 1 y, 2 z) of the face entered — its normal, for the intensity
    """
    c, s = np.cos(boxes[:, 6]), np.sin(boxes[:, 6])
    rel = origin[None, :] - boxes[:, :3]
    # Box frame: rotate by −yaw about z (R^T x); one (M, 3) array for origins and directions each.
    o_loc = np.stack([c * rel[:, 0] + s * rel[:, 1], -s * rel[:, 0] + c * rel[:, 1], rel[:, 2]], -1)
    d_loc = np.stack([c * dirs[:, 0] + s * dirs[:, 1], -s * dirs[:, 0] + c * dirs[:, 1], dirs[:, 2]], -1)
    half = boxes[:, 3:6] / 2.0
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / d_loc
        t1 = (-half - o_loc) * inv
        t2 = (half - o_loc) * inv
    t_in = np.fmin(t1, t2)  # entering each slab
    t_out = np.fmax(t1, t2)
    axis = np.argmax(t_in, axis=1)  # the slab entered last holds the face hit
    rows = np.arange(len(boxes))
    t_near = t_in[rows, axis]
    hit = (t_near <= t_out.min(axis=1)) & (t_near > 0)
    return np.where(hit, t_near, np.inf), axis


def _intersect_objects(
    origin: FloatArray,
    dirs: FloatArray,
    parts: FloatArray,
    reflectivity: FloatArray,
    obj: NDArray[np.int64],
    see_through: OpenRule | None = None,
) -> tuple[FloatArray, FloatArray, FloatArray, NDArray[np.int8]]:
    """First hit of rays on their candidate object's parts.

    Parameters
    ----------
    origin : (3,) ray origin
    dirs : (M, 3) directions of the candidate (object, ray) pairs
    parts : (K, P, 7) parts of every object (padded with boxes far away)
    reflectivity : (K, P)
    obj : (M,) object of each pair
    see_through : None, or a function (part p, t_p (M,), entry axis (M,)) → (M,) int8: 1 where the
        ray passes that part as glass, 2 where it passes under the chassis, 0 where the part stops it

    Returns
    -------
    t : (M,) distance to the object, ``inf`` for a miss
    intensity : (M,) noise-free return intensity at the hit
    t_pass : (M,) distance to the nearest part the ray passed (``inf``: none)
    kind : (M,) int8 how it passed there (1 glass, 2 under the chassis, 0 none)
    """
    t = np.full(len(dirs), np.inf, dtype=dirs.dtype)
    refl = np.zeros(len(dirs), dtype=dirs.dtype)
    cos_inc = np.zeros(len(dirs), dtype=dirs.dtype)
    t_pass = np.full(len(dirs), np.inf, dtype=dirs.dtype)
    kind = np.zeros(len(dirs), dtype=np.int8)
    for p in range(parts.shape[1]):
        t_p, axis = _intersect_boxes(origin, dirs, parts[obj, p])
        if see_through is not None:
            open_p = see_through(p, t_p, axis)
            first = (open_p > 0) & (t_p < t_pass)
            t_pass = np.where(first, t_p, t_pass)
            kind = np.where(first, open_p, kind)
            t_p = np.where(open_p > 0, np.inf, t_p)
        closer = t_p < t
        if not closer.any():
            continue
        t = np.where(closer, t_p, t)
        refl = np.where(closer, reflectivity[obj, p], refl)
        # |cos incidence| = |direction · face normal| = |component of the direction along the face axis|
        yaw = parts[obj, p, 6]
        along = np.where(
            axis == 0,
            np.cos(yaw) * dirs[:, 0] + np.sin(yaw) * dirs[:, 1],
            np.where(axis == 1, -np.sin(yaw) * dirs[:, 0] + np.cos(yaw) * dirs[:, 1], dirs[:, 2]),
        )
        cos_inc = np.where(closer, np.abs(along), cos_inc)
    return t, _intensity(refl, cos_inc), t_pass, kind


def _intensity(reflectivity: FloatArray, cos_incidence: FloatArray) -> FloatArray:
    # Partly Lambertian: a diffuse term ∝ cos θ plus a floor, so grazing surfaces stay visible.
    return reflectivity * (0.3 + 0.7 * cos_incidence)


def render_range_image(
    scene: Scene,
    lidar: LidarSpec = LidarSpec(),
    extrinsic: FloatArray | None = None,
    rng: np.random.Generator | None = None,
    see_through: SeeThrough | None = None,
    see_rng: np.random.Generator | None = None,
) -> RangeImage:
    """Ray-cast one sweep of ``lidar`` into ``scene``.

    Parameters
    ----------
    scene : ground plane and objects in the scene frame
    lidar : the sensor
    extrinsic : (4, 4) sensor pose in the scene frame ``T_scene_sensor``; default: identity (the
        KITTI case — the scene frame is the LiDAR frame and the ground is at ``-sensor_height``)
    rng : generator for range noise, dropout and intensity noise; ``None`` renders noise-free
    see_through : vehicles' windows and the gap under them let this share of rays through
        (:class:`SeeThrough`); None (or all zero) renders opaque vehicles, exactly as before
    see_rng : the generator of the see-through draws (the vehicles' clearances, then one number
        per (object, ray) pair and part); required when ``see_through`` is active

    Returns
    -------
    RangeImage
        ranges, intensities and first-hit ids of shape (H, W) = (beams, columns), the per-row
        inclinations and per-column azimuths, and per-object ray counts.
    """
    T = np.eye(4) if extrinsic is None else np.asarray(extrinsic, dtype=float)
    if T.shape != (4, 4):
        raise ValueError(f"extrinsic must be a 4×4 transform, got shape {T.shape}")
    yaw = _extrinsic_yaw(T)
    inc = lidar.inclinations()
    az = lidar.azimuths(T)
    height, width = len(inc), len(az)
    origin = T[:3, 3].copy()
    dirs = _scene_directions(lidar, T.tobytes())  # (H, W, 3) float32, scene frame
    f32 = np.float32

    # Ground plane, closed form. Full-image arrays are float32 (what the range image stores).
    dz = dirs[..., 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        t_ground = f32(scene.ground_z - origin[2]) / dz
    t_best = np.where((dz < 0) & (t_ground > 0) & (t_ground <= lidar.max_range), t_ground, f32(np.inf))
    hit = np.where(np.isfinite(t_best), HIT_GROUND, HIT_NOTHING).astype(np.int32)
    intensity = _intensity(f32(scene.ground_reflectivity), np.abs(dz))

    k = len(scene.objects)
    solids = scene.objects + scene.clutter  # clutter takes indices k, k+1, … here, HIT_CLUTTER outside
    n_solid = len(solids)
    T_sensor_scene = invert_transform(T)
    solid_boxes = np.stack([o.box for o in solids]) if solids else np.zeros((0, 7))
    all_corners = corners_of(solid_boxes) @ T_sensor_scene[:3, :3].T + T_sensor_scene[:3, 3]  # (K', 8, 3)
    windows: list[tuple[slice, NDArray[np.int64]]] = []
    pair_rays: list[NDArray[np.int64]] = []
    pair_obj: list[int] = []
    for idx in range(n_solid):
        window = _object_window(all_corners[idx], inc, yaw, width, lidar.max_range)
        if window is None:
            if idx < k:
                windows.append((slice(0, 0), np.zeros(0, dtype=np.int64)))
            continue
        rows, cols = window
        if idx < k:
            windows.append(window)
        pair_rays.append((np.arange(rows.start, rows.stop)[:, None] * width + cols[None, :]).ravel())
        pair_obj.append(idx)
    ray_counts = np.zeros(k, dtype=np.int64)
    t_flat, hit_flat, int_flat = t_best.reshape(-1), hit.reshape(-1), intensity.reshape(-1)
    foliage = np.zeros(height * width, dtype=bool)  # rays whose first hit is vegetation (porous: see below)
    passed = np.full(height * width, -1, dtype=np.int32)
    glass_counts = np.zeros(k, dtype=np.int64)
    under_counts = np.zeros(k, dtype=np.int64)
    clearance = np.zeros(k)
    see = see_through is not None and see_through.active
    if see:
        if see_rng is None:
            raise ValueError("render_range_image: see_through needs its generator (see_rng)")
        clearance = see_through.clearances(scene.class_names, see_rng)
    if pair_rays:
        # All (object, ray) candidate pairs in one batch: a few ten thousand, whatever the object count.
        ray = np.concatenate(pair_rays)
        obj = np.repeat(np.asarray(pair_obj, dtype=np.int64), [len(r) for r in pair_rays])
        n_parts = max(len(o.parts) for o in solids)
        parts = np.zeros((n_solid, n_parts, 7))
        parts[:, :, :3] = 1e9  # padding boxes no ray reaches
        parts[:, :, 3:6] = 1.0
        refl = np.zeros((n_solid, n_parts))
        for i, o in enumerate(solids):
            parts[i, : len(o.parts)] = o.parts
            refl[i, : len(o.parts)] = o.reflectivity
        pair_dirs = dirs.reshape(-1, 3)[ray]
        opener = (
            _see_through_rule(see_through, see_rng, scene, obj, pair_dirs, origin, clearance, n_parts) if see else None
        )
        # float32 for the slab test: half the memory traffic; 1e-7 relative is micrometres at 120 m.
        t_obj, int_obj, t_pass, pass_kind = _intersect_objects(
            origin.astype(f32), pair_dirs, parts.astype(f32), refl.astype(f32), obj, opener
        )
        t_obj[t_obj > lidar.max_range] = np.inf
        ray_counts = np.bincount(obj[np.isfinite(t_obj)], minlength=n_solid)[:k].astype(np.int64)
        # Depth buffer: the nearest of ground and objects per ray (ties: the later object).
        np.minimum.at(t_flat, ray, t_obj)
        win = np.isfinite(t_obj) & (t_obj == t_flat[ray])
        hit_flat[ray[win]] = np.where(obj[win] < k, obj[win], HIT_CLUTTER)
        int_flat[ray[win]] = int_obj[win]
        if see:  # rays that reached a window or the gap under a vehicle (nothing stopped them before) and went on
            went = np.isfinite(t_pass) & (t_pass < t_flat[ray])
            t_went = np.full(height * width, np.inf, dtype=t_flat.dtype)
            np.minimum.at(t_went, ray[went], t_pass[went])
            nearest = went & (t_pass == t_went[ray])
            passed[ray[nearest]] = obj[nearest]
            glass_counts = np.bincount(obj[went & (pass_kind == 1)], minlength=n_solid)[:k].astype(np.int64)
            under_counts = np.bincount(obj[went & (pass_kind == 2)], minlength=n_solid)[:k].astype(np.int64)
        porous = np.array([o.class_name == VEGETATION for o in solids], dtype=bool)
        if porous.any():
            foliage[ray[win]] = porous[obj[win]]
            foliage &= hit_flat == HIT_CLUTTER  # a nearer solid that took the ray later

    visible_counts = np.bincount(hit[hit >= 0], minlength=k).astype(np.int64)

    # Measurement: range noise, then dropout and range limits; intensity noise.
    rng_range = t_best
    if rng is not None:
        # float32 draws: half the cost, and far finer than the 2 cm noise they model.
        rng_range = t_best + f32(lidar.range_noise_std) * rng.standard_normal((height, width), dtype=f32)
        p_drop = (
            f32(lidar.dropout) + f32(lidar.far_dropout) * np.minimum(rng_range / f32(lidar.max_range), f32(1.0)) ** 2
        )
        dropped = rng.random((height, width), dtype=f32) < p_drop
        intensity = intensity * (f32(1.0) + f32(0.1) * rng.standard_normal((height, width), dtype=f32))
        keep = ~dropped & (rng_range >= lidar.min_range) & (rng_range <= lidar.max_range)
    else:
        keep = (rng_range >= lidar.min_range) & (rng_range <= lidar.max_range)
    if rng is not None and foliage.any():
        # Foliage is porous: a ray enters it before it returns (an exponential depth), and some pass
        # through its gaps (no return here). Drawn after the sensor noise, only where there is
        # foliage, so a scene without vegetation renders exactly as before.
        leaf = foliage.reshape(height, width)
        n_leaf = int(leaf.sum())
        depth = rng.exponential(C.SIM_FOLIAGE_DEPTH, n_leaf).astype(f32)
        through = rng.random(n_leaf) < C.SIM_FOLIAGE_GAP
        rng_range = rng_range.copy()
        rng_range[leaf] += depth
        keep[leaf] &= ~through
    ranges = np.where(keep, rng_range, f32(NO_RETURN))
    intensity = np.where(keep, np.clip(intensity, f32(0.0), f32(1.0)), f32(0.0))
    kept_hits = hit[keep]
    return_counts = np.bincount(kept_hits[kept_hits >= 0], minlength=k).astype(np.int64)
    return RangeImage(
        range=ranges,
        intensity=intensity,
        hit=hit,
        inclinations=inc,
        azimuths=az,
        extrinsic=T,
        ray_counts=ray_counts,
        visible_counts=visible_counts,
        return_counts=return_counts,
        object_rays=windows,
        passed=passed.reshape(height, width),
        glass_counts=glass_counts,
        under_counts=under_counts,
        clearance=clearance,
    )


def _see_through_rule(
    spec: SeeThrough,
    rng: np.random.Generator,
    scene: Scene,
    obj: NDArray[np.int64],
    dirs: FloatArray,
    origin: FloatArray,
    clearance: FloatArray,
    n_parts: int,
) -> OpenRule:
    """The ``see_through`` function of :func:`_intersect_objects` for the (object, ray) pairs
    ``obj`` (M,) with directions ``dirs`` (M, 3): one uniform number per pair and part decides
    whether the ray passes a window (part 1 of a car or van, entered through a side, front or rear
    face) or the gap under a vehicle (any part, entered lower than its clearance above the ground)."""
    k = len(scene.objects)
    u = rng.random((len(obj), n_parts))
    names = scene.class_names
    glass_obj = np.array([c in GLASS_CLASSES for c in names] + [False], dtype=bool)
    vehicle = np.array([c in C.SIM_CHASSIS_CLEARANCE for c in names] + [False], dtype=bool)
    own = np.where(obj < k, obj, k)  # clutter is never see-through
    lift = np.append(clearance, 0.0)[own]

    def rule(p: int, t_p: FloatArray, axis: NDArray[np.int64]) -> NDArray[np.int8]:
        hit = np.isfinite(t_p)
        out = np.zeros(len(t_p), dtype=np.int8)
        if p == 1:
            out[hit & glass_obj[own] & (axis != 2) & (u[:, p] < spec.glass)] = 1
        with np.errstate(invalid="ignore"):
            low = origin[2] + t_p * dirs[:, 2] - scene.ground_z < lift
        out[hit & vehicle[own] & low & (u[:, p] < spec.under)] = 2
        return out

    return rule
