"""Aerial stereo cameras and ray-cast rendering of a :class:`SyntheticCity`.

Cameras follow COLMAP: ``x_cam = R @ x_world + t`` with the camera looking along
+z, image x to the right and y down, and the centre of the top-left pixel at
(0.5, 0.5) (OpenCV puts it at (0, 0)). Each pixel is rendered with one ray through
its centre, so the surface point seen at pixel (row, col) projects exactly to
``(col + 0.5, row + 0.5)``.

Shading is Lambertian under a sun with ambient light and cast shadows; the albedo is
a procedural texture (multi-octave value noise evaluated at the 3-D hit point, so
both views see the same texture), then Gaussian sensor noise and 8-bit quantisation.
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass

import numpy as np

from recon3d.synthetic.city import MATERIALS, SyntheticCity

log = logging.getLogger(__name__)

__all__ = [
    "Lighting",
    "PinholeCamera",
    "Render",
    "block_cameras",
    "check_coverage",
    "render",
    "render_pair",
    "sparse_points",
    "stereo_cameras",
    "visible",
]

#: Base RGB albedo and texture contrast per material (``MATERIALS`` order, then asphalt).
_ALBEDO = np.array(
    [
        [0.30, 0.42, 0.18],  # ground (grass)
        [0.62, 0.30, 0.22],  # tiles
        [0.56, 0.54, 0.50],  # gravel
        [0.74, 0.71, 0.65],  # wall
        [0.20, 0.36, 0.14],  # foliage
        [0.36, 0.26, 0.18],  # bark
        [0.34, 0.34, 0.36],  # asphalt (ground on a street)
    ]
)
_CONTRAST = np.array([0.45, 0.40, 0.40, 0.30, 0.60, 0.30, 0.35])
_ASPHALT = len(MATERIALS)
_TABLE = 1024  # lattice period of the value noise (cells)


# --------------------------------------------------------------------------- cameras


def _rows(p: np.ndarray, m: np.ndarray) -> np.ndarray:
    """``p @ m`` for (n, 3) rows and a small (3, k) matrix, without BLAS.

    OpenBLAS threads spin against Open3D's on few shared cores and make these thin
    products ten times slower than this einsum.
    """
    return np.einsum("nj,jk->nk", p, m)


@dataclass(frozen=True)
class PinholeCamera:
    """A frame camera, COLMAP conventions (PINHOLE or OPENCV model, cam_from_world).

    Attributes
    ----------
    K : (3, 3) float64
        Intrinsics ``[[fx, 0, cx], [0, fy, cy], [0, 0, 1]]``, pixel-centre convention
        of COLMAP (top-left pixel centre at (0.5, 0.5)).
    R : (3, 3) float64
        Rotation of cam_from_world.
    t : (3,) float64
        Translation of cam_from_world: ``x_cam = R @ x_world + t``.
    width, height : int
        Image size in pixels.
    name : str
        Image file name.
    dist : (4,) float
        Lens distortion (k1, k2, p1, p2) of COLMAP's OPENCV model; zeros for a pinhole.
    """

    K: np.ndarray
    R: np.ndarray
    t: np.ndarray
    width: int
    height: int
    name: str = ""
    dist: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 0.0)

    @property
    def center(self) -> np.ndarray:
        """(3,) projection centre in world (model) coordinates."""
        return -self.R.T @ self.t

    @property
    def model(self) -> str:
        """COLMAP camera model name: "PINHOLE", or "OPENCV" with distortion."""
        return "OPENCV" if any(self.dist) else "PINHOLE"

    @property
    def params(self) -> list[float]:
        """COLMAP parameters ``[fx, fy, cx, cy]`` (PINHOLE), then ``k1, k2, p1, p2`` (OPENCV)."""
        k = [float(self.K[0, 0]), float(self.K[1, 1]), float(self.K[0, 2]), float(self.K[1, 2])]
        return k + [float(v) for v in self.dist] if any(self.dist) else k

    def project(self, xyz: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Project (n, 3) points; returns (n, 2) pixel coordinates and (n,) depths."""
        cam = _rows(np.asarray(xyz, np.float64), self.R.T) + self.t
        if any(self.dist):
            import cv2

            with np.errstate(divide="ignore", invalid="ignore"):
                uv, _ = cv2.projectPoints(cam.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), self.K, np.array(self.dist))
            return uv.reshape(-1, 2), cam[:, 2]
        uvw = _rows(cam, self.K.T)
        return uvw[:, :2] / uvw[:, 2:3], cam[:, 2]

    def rays(self, uv: np.ndarray) -> np.ndarray:
        """(n, 3) unit world directions of the rays through (n, 2) pixel coordinates."""
        uv = np.asarray(uv, np.float64)
        if any(self.dist):
            import cv2

            xy = cv2.undistortPoints(uv.reshape(-1, 1, 2), self.K, np.array(self.dist)).reshape(-1, 2)
            d = np.column_stack([xy, np.ones(len(xy))])
        else:
            d = _rows(np.column_stack([uv, np.ones(len(uv))]), np.linalg.inv(self.K).T)
        d = _rows(d, self.R)  # R.T @ d for row vectors
        return d / np.linalg.norm(d, axis=1, keepdims=True)

    def pixel_centres(self) -> np.ndarray:
        """(height * width, 2) coordinates of every pixel centre, row-major."""
        c, r = np.meshgrid(np.arange(self.width) + 0.5, np.arange(self.height) + 0.5)
        return np.column_stack([c.ravel(), r.ravel()])


def _rotation(roll: float, pitch: float, yaw: float) -> np.ndarray:
    """(3, 3) rotation about the camera z (roll), x (pitch) and y (yaw) axes, radians."""
    cz, sz = math.cos(roll), math.sin(roll)
    cx, sx = math.cos(pitch), math.sin(pitch)
    cy, sy = math.cos(yaw), math.sin(yaw)
    rz = np.array([[cz, -sz, 0], [sz, cz, 0], [0, 0, 1]])
    rx = np.array([[1, 0, 0], [0, cx, -sx], [0, sx, cx]])
    ry = np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
    return rz @ rx @ ry


def _look_at(center: np.ndarray, target: np.ndarray) -> np.ndarray:
    """cam_from_world rotation looking from ``center`` at ``target``, image x along world +x."""
    z = target - center
    z /= np.linalg.norm(z)
    x = np.array([1.0, 0.0, 0.0]) - z[0] * z
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    return np.stack([x, y, z])


def stereo_cameras(
    target: np.ndarray,
    *,
    gsd: float = 0.25,
    width: int = 1000,
    height: int = 750,
    focal: float | None = None,
    base_to_height: float = 0.4,
    max_rotation_deg: float = 2.0,
    seed: int = 0,
    n_images: int = 2,
) -> tuple[PinholeCamera, ...]:
    """A convergent aerial stereo pair (or strip) looking at ``target``, not rectified.

    The cameras fly at ``focal * gsd`` above the target, the first and the last
    ``base_to_height`` times that apart along world x (west first), the others evenly
    between them; they aim at the target and are then turned by a random roll, pitch
    and yaw of 0.5 to ``max_rotation_deg`` degrees each (different per camera), so
    their epipolar lines are not image rows.

    Parameters
    ----------
    target : (3,) float
        Local point the pair looks at (the city centre on the ground).
    gsd : float
        Ground sample distance at nadir from the flying height, metres.
    width, height : int
        Image size in pixels.
    focal : float, optional
        Focal length in pixels, default ``width`` (53 degrees field of view).
    base_to_height : float
    max_rotation_deg : float
    seed : int
    n_images : int
        Number of cameras, at least 2.

    Returns
    -------
    tuple of PinholeCamera
        Named "left.png" and "right.png" for a pair, "view1.png", "view2.png"... for a strip.
    """
    if n_images < 2:
        raise ValueError(f"n_images {n_images}: a stereo scene needs at least 2 images")
    f = float(width if focal is None else focal)
    flying = f * gsd
    base = base_to_height * flying
    K = np.array([[f, 0.0, width / 2], [0.0, f, height / 2], [0.0, 0.0, 1.0]])
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), 10]))
    target = np.asarray(target, np.float64)
    names = ["left.png", "right.png"] if n_images == 2 else [f"view{k + 1}.png" for k in range(n_images)]
    cams = []
    for side, name in zip(np.linspace(-1.0, 1.0, n_images), names, strict=True):
        center = target + np.array([side * base / 2, 0.0, flying])
        angles = rng.uniform(0.5, max_rotation_deg, 3) * rng.choice([-1.0, 1.0], 3)
        R = _rotation(*np.radians(angles)) @ _look_at(center, target)
        cams.append(PinholeCamera(K, R, -R @ center, int(width), int(height), name))
    log.debug("%d images: flying height %.1f m, base %.1f m, focal %.0f px", n_images, flying, base, f)
    return tuple(cams)


def block_cameras(
    target: np.ndarray,
    *,
    width: int,
    height: int,
    focal: float,
    gsd: float,
    base_to_height: float,
    heading: float = 0.0,
    base_angle: float = 0.0,
    principal_offset: tuple[float, float] = (0.0, 0.0),
    attitude: float = 1.7,
    strips: int = 1,
    images_per_strip: int = 2,
    side_overlap: float = 0.3,
    seed: int = 0,
    distortion: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 0.0),
) -> tuple[PinholeCamera, ...]:
    """A nadir aerial block: strips of frame images over ``target``, as a survey flies them.

    The cameras fly ``focal * gsd`` above the target. Along a strip they are
    ``base_to_height`` times that apart, in the direction of ``heading``; strips lie
    side by side with ``side_overlap``, every other one flown the opposite way (its
    images turned 180 degrees). Each camera looks straight down, its image x axis at
    ``base_angle`` degrees from the flight direction (0: the base along the image x
    axis, 90: along y, 45: diagonal), then turned by a random roll, pitch and yaw of up
    to ``attitude`` degrees each.

    Parameters
    ----------
    target : (3,) float
        Local point under the middle of the block (the city centre on the ground).
    width, height : int
        Image size in pixels.
    focal : float
        Focal length in pixels.
    gsd : float
        Ground sample distance at the flying height above ``target``, metres.
    base_to_height : float
    heading : float
        Azimuth of the flight direction, degrees clockwise from north (local +y).
    base_angle : float
        Angle from the image x axis to the flight direction, degrees.
    principal_offset : (float, float)
        Principal point minus the image centre, pixels.
    attitude : float
        Largest attitude error about each axis, degrees.
    strips, images_per_strip : int
    side_overlap : float
        Share of an image's width across the flight that the next strip sees too.
    seed : int
    distortion : (k1, k2, p1, p2)
        Lens distortion of every camera (COLMAP's OPENCV model).

    Returns
    -------
    tuple of PinholeCamera
        Strip by strip, named "s1_1.png", "s1_2.png", ...
    """
    if strips < 1 or images_per_strip < 1 or strips * images_per_strip < 2:
        raise ValueError(f"{strips} x {images_per_strip} images: a block needs at least 2")
    flying = focal * gsd
    base = base_to_height * flying
    beta = math.radians(base_angle)
    across = (width * abs(math.sin(beta)) + height * abs(math.cos(beta))) * gsd
    spacing = (1.0 - side_overlap) * across
    K = np.array([
        [focal, 0.0, width / 2 + principal_offset[0]],
        [0.0, focal, height / 2 + principal_offset[1]],
        [0.0, 0.0, 1.0],
    ])
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), 11]))
    target = np.asarray(target, np.float64)
    cams = []
    for s in range(strips):
        h = math.radians(heading + 180.0 * (s % 2))
        along = np.array([math.sin(h), math.cos(h), 0.0])
        side = np.array([math.cos(math.radians(heading)), -math.sin(math.radians(heading)), 0.0])
        ex = np.array([math.sin(h - beta), math.cos(h - beta), 0.0])
        ez = np.array([0.0, 0.0, -1.0])
        nominal = np.stack([ex, np.cross(ez, ex), ez])
        for k in range(images_per_strip):
            step = k - (images_per_strip - 1) / 2
            if s % 2:
                step = -step  # the return flight starts where the last one ended
            center = target + along * step * base + side * (s - (strips - 1) / 2) * spacing
            center[2] += flying
            angles = rng.uniform(-attitude, attitude, 3)
            R = _rotation(*np.radians(angles)) @ nominal
            name = f"s{s + 1}_{k + 1}.png"
            cams.append(PinholeCamera(K, R, -R @ center, int(width), int(height), name, tuple(distortion)))
    log.debug("block of %d images: flying height %.1f m, base %.1f m, strip spacing %.1f m",
              len(cams), flying, base, spacing)
    return tuple(cams)


def ground_footprint(camera: PinholeCamera, z: float) -> np.ndarray:
    """(4, 2) local x, y where the rays through the image corners meet the plane at height ``z``."""
    corners = np.array([[0, 0], [camera.width, 0], [camera.width, camera.height], [0, camera.height]], float)
    d = camera.rays(corners)
    t = (z - camera.center[2]) / d[:, 2]
    return (camera.center + t[:, None] * d)[:, :2]


def check_coverage(city: SyntheticCity, cameras, margin_px: float = 2.0) -> None:
    """Raise ValueError unless every camera sees the whole city area: its corners on
    the ground and every vertex of its buildings and trees."""
    s = np.array([0.0, city.size])
    cx, cy = (a.ravel() for a in np.meshgrid(s, s))
    corners = np.column_stack([cx, cy, city.terrain.height(cx, cy)])
    objects = np.unique(city.faces[city.face_owner >= 0])
    points = np.concatenate([corners, city.vertices[objects]])
    for cam in cameras:
        uv, depth = cam.project(points)
        ok = (depth > 0) & (uv >= margin_px).all(axis=1)
        ok &= (uv[:, 0] <= cam.width - margin_px) & (uv[:, 1] <= cam.height - margin_px)
        if not ok.all():
            raise ValueError(
                f"a {city.size:.0f} m city does not fit image {cam.name} "
                f"({cam.width} x {cam.height} px); "
                "use a smaller size, a larger gsd or larger images"
            )


# --------------------------------------------------------------------------- texture


def _noise_tables(seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Permutation (_TABLE,) int64, lattice values (_TABLE,) float64, octave rotations
    (8, 3, 3) and offsets (8, 3) of the value noise, from the city seed."""
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), 20]))
    perm = rng.permutation(_TABLE).astype(np.int64)
    values = rng.random(_TABLE)
    q, _ = np.linalg.qr(rng.normal(size=(8, 3, 3)))
    offsets = rng.uniform(0, 1000, (8, 3))
    return perm, values, q, offsets


def _value_noise(p: np.ndarray, perm: np.ndarray, values: np.ndarray) -> np.ndarray:
    """Trilinear value noise in [0, 1] at (n, 3) lattice coordinates, smoothstep-blended."""
    i = np.floor(p)
    f = p - i
    f = f * f * (3 - 2 * f)
    i = i.astype(np.int64)
    g = 1 - f
    m = _TABLE - 1
    hx = [perm[(i[:, 0] + k) & m] for k in (0, 1)]
    hxy = [[perm[(hx[a] + i[:, 1] + b) & m] for b in (0, 1)] for a in (0, 1)]
    out = np.zeros(len(p), p.dtype)
    for a in (0, 1):
        wa = f[:, 0] if a else g[:, 0]
        for b in (0, 1):
            wab = wa * (f[:, 1] if b else g[:, 1])
            for c in (0, 1):
                wc = f[:, 2] if c else g[:, 2]
                out += wab * wc * values[perm[(hxy[a][b] + i[:, 2] + c) & m]]
    return out


def _cell_noise(p: np.ndarray, perm: np.ndarray, values: np.ndarray) -> np.ndarray:
    """Piecewise-constant noise in [0, 1]: one random value per lattice cell (crisp speckle)."""
    i = np.floor(p).astype(np.int64)
    m = _TABLE - 1
    return values[perm[(perm[(perm[i[:, 0] & m] + i[:, 1]) & m] + i[:, 2]) & m]]


def _texture(p: np.ndarray, seed: int, finest: float, coarsest: float = 8.0) -> np.ndarray:
    """Texture value in [0, 1] at (n, 3) points: multi-octave value noise with
    wavelengths from ``coarsest`` down to about ``finest`` metres (each octave in its own
    rotated lattice, equal weights) plus a speckle of cells ``finest`` wide, with its
    contrast stretched so that detail at the scale of a few pixels dominates."""
    perm, values, rot, offsets = _noise_tables(seed)
    values = values.astype(np.float32)  # float32 halves the time; lattice coordinates stay < 1e4

    rotated = _rows(p, np.concatenate(rot, axis=1)).astype(np.float32)

    def lattice(k: int, wavelength: float) -> np.ndarray:
        shift = offsets[k].astype(np.float32)
        return rotated[:, 3 * k : 3 * k + 3] / np.float32(wavelength) + shift

    n_oct = int(np.clip(math.ceil(math.log2(coarsest / finest)) + 1, 1, len(rot) - 1))
    total = np.zeros(len(p), np.float32)
    for k in range(n_oct):
        total += _value_noise(lattice(k, coarsest / 2**k), perm, values)
    k = len(rot) - 1
    total += 0.7 * n_oct * (_cell_noise(lattice(k, finest), perm, values) - 0.5)
    return np.clip(0.5 + 1.6 * (total / n_oct - 0.5), 0.0, 1.0)


def _albedo(city: SyntheticCity, xyz: np.ndarray, face: np.ndarray, finest: float) -> np.ndarray:
    """(n, 3) RGB albedo of hit points ``xyz`` (local) on triangles ``face``."""
    mat = city.face_material[face].astype(np.int64)
    ground = mat == MATERIALS.index("ground")
    mat[ground & city.streets.is_street(xyz[:, 0], xyz[:, 1])] = _ASPHALT
    # a shifted copy of the noise per material, so roofs and ground differ
    tex = _texture(xyz + 37.0 * mat[:, None], city.seed, finest)
    c = _CONTRAST[mat][:, None]
    return _ALBEDO[mat] * city.face_tint[face] * (1 - c + 2 * c * tex[:, None])


# --------------------------------------------------------------------------- rendering


@dataclass(frozen=True)
class Lighting:
    """Sun, ambient light and sensor model.

    Attributes
    ----------
    azimuth, elevation : float
        Sun direction in degrees (azimuth clockwise from north = local +y).
    ambient : float
        Fraction of light that reaches shadows.
    gain : float
        Digital numbers per unit radiance (255 * gain for a white sunlit surface).
    noise_sigma : float
        Standard deviation of the Gaussian sensor noise, digital numbers.
    pixel_samples : int
        Rays per pixel side: each pixel averages the light of ``pixel_samples**2`` rays
        spread evenly over its area, as a sensor's pixel integrates it. With 1 (one ray
        through the pixel centre) texture finer than a pixel's footprint aliases, and
        differently in each view where one view foreshortens the surface (steep roof
        faces, the sides of crowns): a speckle no camera records, which no matcher can
        match. 3 removes most of it, at about 4 times the render time.
    """

    azimuth: float = 135.0
    elevation: float = 50.0
    ambient: float = 0.35
    gain: float = 1.2
    noise_sigma: float = 2.0
    pixel_samples: int = 1

    def __post_init__(self) -> None:
        if int(self.pixel_samples) != self.pixel_samples or self.pixel_samples < 1:
            raise ValueError(f"pixel_samples {self.pixel_samples}: a whole number, at least 1")

    @property
    def sun(self) -> np.ndarray:
        """(3,) unit vector towards the sun."""
        az, el = math.radians(self.azimuth), math.radians(self.elevation)
        return np.array([math.sin(az) * math.cos(el), math.cos(az) * math.cos(el), math.sin(el)])


@dataclass
class Render:
    """One rendered image.

    Attributes
    ----------
    image : (height, width, 3) uint8
        RGB.
    xyz : (height, width, 3) float32
        Local surface point seen through each pixel centre (NaN where no surface).
    camera : PinholeCamera
    seconds : float
        Wall time of the render.
    """

    image: np.ndarray
    xyz: np.ndarray
    camera: PinholeCamera
    seconds: float


def _cast(
    city: SyntheticCity, origins: np.ndarray, dirs: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """First hits of (n, 3) rays: distances (n,) float64 (inf on miss) and triangles (n,) int64."""
    from recon3d.core.o3d import open3d

    o3d = open3d()
    rays = np.concatenate([origins, dirs], axis=1).astype(np.float32)
    hit = city.raycaster().cast_rays(o3d.core.Tensor(rays))
    t = hit["t_hit"].numpy().astype(np.float64)
    face = hit["primitive_ids"].numpy().astype(np.int64)
    face[~np.isfinite(t)] = -1
    return t, face


def _face_normals(city: SyntheticCity) -> np.ndarray:
    v = city.vertices[city.faces]
    n = np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])
    return n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)


def _in_shadow(
    city: SyntheticCity, xyz: np.ndarray, normal: np.ndarray, sun: np.ndarray
) -> np.ndarray:
    """(n,) True where the way from a surface point to the sun is blocked."""
    from recon3d.core.o3d import open3d

    o3d = open3d()
    origins = xyz + 0.02 * normal + 0.02 * sun
    rays = np.concatenate([origins, np.broadcast_to(sun, origins.shape)], axis=1).astype(np.float32)
    return city.raycaster().test_occlusions(o3d.core.Tensor(rays)).numpy().astype(bool)


def render(
    city: SyntheticCity,
    camera: PinholeCamera,
    *,
    lighting: Lighting = Lighting(),
    texture_scale: float = 0.4,
    seed: int = 0,
) -> Render:
    """Render one image of the city, ``lighting.pixel_samples`` squared rays per pixel.

    Parameters
    ----------
    city : SyntheticCity
    camera : PinholeCamera or PushbroomCamera
        In the city's local frame (anything with ``pixel_centres``, ``rays`` and a
        ``center`` or per-pixel ``origins``).
    lighting : Lighting
    texture_scale : float
        Finest texture detail in metres (one to two pixels suits dense matching).
    seed : int
        Seed of the sensor noise.

    Returns
    -------
    Render
    """
    start = time.perf_counter()
    centres = camera.pixel_centres()
    k = int(lighting.pixel_samples)
    offsets = (np.arange(k) + 0.5) / k - 0.5  # 0 among them when k is odd
    radiance, xyz = 0.0, None
    for dy in offsets:
        for dx in offsets:
            light, hits = _radiance(city, camera, centres + (dx, dy), lighting, texture_scale)
            radiance = radiance + light
            if dx == 0.0 and dy == 0.0:
                xyz = hits  # the render's surface points are those of the pixel centres
    radiance = radiance / (k * k)
    if xyz is None:  # even k: no ray went through the centres
        xyz = _radiance(city, camera, centres, lighting, texture_scale)[1]
    stream = int(sum(map(ord, camera.name)))  # a different noise per image
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), 30, stream]))
    dn = 255.0 * lighting.gain * radiance + rng.normal(0.0, lighting.noise_sigma, radiance.shape)
    image = np.clip(np.rint(dn), 0, 255).astype(np.uint8).reshape(camera.height, camera.width, 3)
    seconds = time.perf_counter() - start
    log.info(
        "rendered %s (%d x %d px) in %.2f s", camera.name, camera.width, camera.height, seconds
    )
    xyz = xyz.reshape(camera.height, camera.width, 3).astype(np.float32)
    return Render(image, xyz, camera, seconds)


def _radiance(city: SyntheticCity, camera, uv: np.ndarray, lighting: Lighting,
              texture_scale: float) -> tuple[np.ndarray, np.ndarray]:
    """Radiance (n, 3) seen along the rays through image points ``uv`` (n, 2), and the
    surface points (n, 3) they hit (NaN where none)."""
    dirs = camera.rays(uv)
    if hasattr(camera, "origins"):  # a pushbroom camera: one projection centre per row
        origin = camera.origins(uv)
    else:
        origin = np.broadcast_to(camera.center, dirs.shape)
    t, face = _cast(city, origin, dirs)
    hit = face >= 0
    xyz = np.full(dirs.shape, np.nan)
    xyz[hit] = origin[hit] + t[hit, None] * dirs[hit]
    normal = _face_normals(city)[face[hit]]
    normal *= -np.sign(np.einsum("ij,ij->i", normal, dirs[hit]))[:, None]  # face the camera
    sun = lighting.sun
    lit = ~_in_shadow(city, xyz[hit], normal, sun)
    direct = np.clip(_rows(normal, sun[:, None])[:, 0], 0, None) * lit
    shade = lighting.ambient + (1 - lighting.ambient) * direct
    radiance = np.zeros(dirs.shape)
    radiance[hit] = _albedo(city, xyz[hit], face[hit], texture_scale) * shade[:, None]
    return radiance, xyz


def render_pair(
    city: SyntheticCity,
    cameras: tuple[PinholeCamera, ...],
    *,
    lighting: Lighting = Lighting(),
    texture_scale: float = 0.4,
    seed: int = 0,
) -> list[Render]:
    """Render every image of a stereo pair or strip (see :func:`render`)."""
    return [
        render(city, c, lighting=lighting, texture_scale=texture_scale, seed=seed)
        for c in cameras
    ]


def visible(
    city: SyntheticCity, camera: PinholeCamera, xyz: np.ndarray, tol: float = 0.02
) -> np.ndarray:
    """(n,) True where local points (n, 3) are inside the image and not hidden."""
    uv, depth = camera.project(xyz)
    inside = (depth > 0) & (uv[:, 0] >= 1) & (uv[:, 1] >= 1)
    inside &= (uv[:, 0] <= camera.width - 1) & (uv[:, 1] <= camera.height - 1)
    start = camera.origins(uv) if hasattr(camera, "origins") else np.broadcast_to(camera.center, xyz.shape)
    vec = xyz - start
    dist = np.linalg.norm(vec, axis=1)
    t, _ = _cast(city, start, vec / dist[:, None])
    return inside & (np.abs(t - dist) <= tol + 1e-5 * dist)


def sparse_points(
    city: SyntheticCity,
    cameras: tuple[PinholeCamera, ...],
    n: int = 400,
    *,
    seed: int = 0,
    min_views: int | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Surface points seen by several cameras, like a sparse SfM model.

    Without ``min_views`` the points are hit by rays through random (sub-pixel)
    positions of the first image and kept when every other camera sees them too.
    With it, each image casts its share of the rays and a point is kept when at
    least ``min_views`` cameras see it (its track: those cameras).

    Returns
    -------
    xyz : (m, 3) float64
        Local points, ``m <= n``.
    uv : (len(cameras), m, 2) float64
        Their exact projections in each image (COLMAP pixel convention), also where
        the camera does not see them.
    seen : (len(cameras), m) bool
        Which cameras see each point.
    """
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), 40]))
    sources = cameras[:1] if min_views is None else cameras
    need = len(cameras) if min_views is None else int(min_views)
    per = 4 * n if min_views is None else int(math.ceil(4 * n / len(cameras)))
    points, views = [], []
    for source in sources:
        uv0 = rng.uniform([2, 2], [source.width - 2, source.height - 2], (per, 2))
        dirs = source.rays(uv0)
        origin = np.broadcast_to(source.center, dirs.shape)
        t, face = _cast(city, origin, dirs)
        hit = face >= 0
        xyz = origin[hit] + t[hit, None] * dirs[hit]
        seen = np.stack([np.ones(len(xyz), bool) if cam is source else visible(city, cam, xyz) for cam in cameras])
        keep = seen.sum(axis=0) >= need
        points.append(xyz[keep])
        views.append(seen[:, keep])
    xyz = np.concatenate(points)
    seen = np.concatenate(views, axis=1)
    if len(sources) > 1:  # an even share of every image, in a fixed order
        order = rng.permutation(len(xyz))
        xyz, seen = xyz[order], seen[:, order]
    xyz, seen = xyz[:n], seen[:, :n]
    uv = np.stack([cam.project(xyz)[0] for cam in cameras])
    return xyz, uv, seen
