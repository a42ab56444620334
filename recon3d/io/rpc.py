"""RPC (rational polynomial coefficient) camera models for satellite images.

An RPC model maps a ground point (longitude, latitude in degrees on WGS84, height in
metres above the WGS84 ellipsoid) to an image pixel (row, col) with a ratio of two
cubic polynomials per image axis, evaluated on normalised coordinates::

    L = (lon - long_off) / long_scale,  P = (lat - lat_off) / lat_scale,
    H = (h - height_off) / height_scale
    row = line_off + line_scale * Num_line(P, L, H) / Den_line(P, L, H)
    col = samp_off + samp_scale * Num_samp(P, L, H) / Den_samp(P, L, H)

Each polynomial has 20 coefficients in the RPC00B term order (NITF STDI-0002, the
GeoTIFF RPC tag and the OSSIM ``polynomial_format: B`` keyword list)::

    1, L, P, H, LP, LH, PH, L^2, P^2, H^2, PLH, L^3, LP^2, LH^2, L^2P, P^3, PH^2,
    L^2H, P^2H, H^3

Pixel convention
----------------
Rows and columns are those of the RPC itself: **(0, 0) is the centre of the
top-left pixel** of the full scene (as in GDAL's RPC tags and OSSIM keyword lists,
and the same as OpenCV and :class:`recon3d.core.camera.Camera`). The pixel with
numpy index ``image[i, j]`` covers rows ``i - 0.5 .. i + 0.5``. CNES shareloc's
default ``topleftconvention`` adds 0.5 to these offsets; recon3d does not.

:class:`RPCCamera` adds the offset of a crop within the full scene, so that its
pixel coordinates index the crop's array directly.
"""

from __future__ import annotations

import logging
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from recon3d.errors import InputError

__all__ = ["RPCCamera", "RPCModel", "read_rpc_camera"]

log = logging.getLogger(__name__)

_CHUNK = 65536  # points evaluated at once: bounds the (20, n) term arrays to ~10 MB

_NORMALISATION_KEYS = (
    "line_off",
    "samp_off",
    "lat_off",
    "long_off",
    "height_off",
    "line_scale",
    "samp_scale",
    "lat_scale",
    "long_scale",
    "height_scale",
)
_COEFF_NAMES = ("line_num", "line_den", "samp_num", "samp_den")


def _terms(L: np.ndarray, P: np.ndarray, H: np.ndarray) -> np.ndarray:
    """(20, n) RPC00B monomials of normalised lon L, lat P, height H (each (n,))."""
    one = np.ones_like(L)
    return np.stack(
        [
            one, L, P, H,
            L * P, L * H, P * H, L * L, P * P, H * H,
            P * L * H, L * L * L, L * P * P, L * H * H, L * L * P,
            P * P * P, P * H * H, L * L * H, P * P * H, H * H * H,
        ]
    )  # fmt: skip


def _terms_dL(L: np.ndarray, P: np.ndarray, H: np.ndarray) -> np.ndarray:
    """(20, n) derivatives of the monomials with respect to L."""
    zero = np.zeros_like(L)
    one = np.ones_like(L)
    return np.stack(
        [
            zero, one, zero, zero,
            P, H, zero, 2 * L, zero, zero,
            P * H, 3 * L * L, P * P, H * H, 2 * L * P,
            zero, zero, 2 * L * H, zero, zero,
        ]
    )  # fmt: skip


def _terms_dP(L: np.ndarray, P: np.ndarray, H: np.ndarray) -> np.ndarray:
    """(20, n) derivatives of the monomials with respect to P."""
    zero = np.zeros_like(L)
    one = np.ones_like(L)
    return np.stack(
        [
            zero, zero, one, zero,
            L, zero, H, zero, 2 * P, zero,
            L * H, zero, 2 * L * P, zero, L * L,
            3 * P * P, H * H, zero, 2 * P * H, zero,
        ]
    )  # fmt: skip


@dataclass(frozen=True, eq=False)
class RPCModel:
    """A ground-to-image RPC model (RPC00B) of a full satellite scene.

    Parameters
    ----------
    line_num, line_den, samp_num, samp_den : (20,) float
        Numerator and denominator coefficients of the row (line) and column (sample)
        functions, in RPC00B term order.
    line_off, line_scale, samp_off, samp_scale : float
        Row and column normalisation, in pixels ((0, 0) = centre of the top-left pixel).
    lat_off, lat_scale, lon_off, lon_scale : float
        Latitude and longitude normalisation, in degrees (WGS84).
    height_off, height_scale : float
        Height normalisation, in metres above the WGS84 ellipsoid.

    Notes
    -----
    The validity domain is ``offset +- scale`` on each ground axis (see
    :meth:`in_domain`). Compare models with :meth:`same_as`, not ``==``.
    """

    line_num: np.ndarray
    line_den: np.ndarray
    samp_num: np.ndarray
    samp_den: np.ndarray
    line_off: float
    line_scale: float
    samp_off: float
    samp_scale: float
    lat_off: float
    lat_scale: float
    lon_off: float
    lon_scale: float
    height_off: float
    height_scale: float

    def __post_init__(self) -> None:
        for name in _COEFF_NAMES:
            coeffs = np.asarray(getattr(self, name), dtype=np.float64).reshape(-1)
            if coeffs.shape != (20,) or not np.all(np.isfinite(coeffs)):
                raise InputError(
                    f"RPC {name} coefficients: need 20 finite numbers, got {coeffs.size}"
                )
            coeffs.setflags(write=False)
            object.__setattr__(self, name, coeffs)
        for name in ("line", "samp", "lat", "lon", "height"):
            off, scale = float(getattr(self, f"{name}_off")), float(getattr(self, f"{name}_scale"))
            if not (np.isfinite(off) and np.isfinite(scale) and scale != 0.0):
                raise InputError(f"RPC {name} offset/scale unusable: {off} / {scale}")
            object.__setattr__(self, f"{name}_off", off)
            object.__setattr__(self, f"{name}_scale", scale)
        stacked = np.stack([self.line_num, self.line_den, self.samp_num, self.samp_den])
        stacked.setflags(write=False)
        object.__setattr__(self, "_coeffs", stacked)

    # ------------------------------------------------------------------ readers
    @classmethod
    def from_geom(cls, path: str | Path) -> RPCModel:
        """Read an OSSIM keyword list (``.geom``, ``type: ossimRpcModel``).

        Keys used: ``line_off samp_off lat_off long_off height_off``, the five
        ``*_scale`` and ``{line,samp}_{num,den}_coeff_00 .. _19``. ``polynomial_format``,
        when present, must be ``B``.

        Raises
        ------
        InputError
            When the file cannot be read, a key is missing or a value is not a number.
        """
        path = Path(path)
        try:
            text = path.read_text(encoding="utf-8", errors="replace")
        except OSError as exc:
            raise InputError(f"{path}: cannot read RPC keyword file ({exc.strerror})") from None
        kw: dict[str, str] = {}
        for line in text.splitlines():
            key, sep, value = line.partition(":")
            if sep:
                kw[key.strip()] = value.strip()
        fmt = kw.get("polynomial_format", "B")
        if fmt.upper() != "B":
            raise InputError(f"{path}: unsupported RPC polynomial_format {fmt!r} (only B)")
        coeff_keys = {
            name: [f"{name}_coeff_{i:02d}" for i in range(20)] for name in _COEFF_NAMES
        }
        needed = list(_NORMALISATION_KEYS) + [k for keys in coeff_keys.values() for k in keys]
        missing = [k for k in needed if k not in kw]
        if missing:
            more = f" and {len(missing) - 5} more" if len(missing) > 5 else ""
            shown = ", ".join(missing[:5]) + more
            raise InputError(f"{path}: not an OSSIM RPC keyword file, missing keys {shown}")

        def number(key: str) -> float:
            try:
                return float(kw[key])
            except ValueError:
                raise InputError(f"{path}: RPC key {key} is not a number: {kw[key]!r}") from None

        try:
            return cls(
                **{name: [number(k) for k in keys] for name, keys in coeff_keys.items()},
                line_off=number("line_off"),
                line_scale=number("line_scale"),
                samp_off=number("samp_off"),
                samp_scale=number("samp_scale"),
                lat_off=number("lat_off"),
                lat_scale=number("lat_scale"),
                lon_off=number("long_off"),
                lon_scale=number("long_scale"),
                height_off=number("height_off"),
                height_scale=number("height_scale"),
            )
        except InputError as exc:
            raise InputError(f"{path}: {exc}") from None

    @classmethod
    def from_rasterio(cls, rpcs) -> RPCModel:
        """Build from a :class:`rasterio.rpc.RPC` (``dataset.rpcs``, GDAL RPC metadata).

        GDAL's RPC metadata uses the same (0, 0) = centre of the top-left pixel
        convention, so the offsets are taken as they are.
        """
        return cls(
            line_num=rpcs.line_num_coeff,
            line_den=rpcs.line_den_coeff,
            samp_num=rpcs.samp_num_coeff,
            samp_den=rpcs.samp_den_coeff,
            line_off=rpcs.line_off,
            line_scale=rpcs.line_scale,
            samp_off=rpcs.samp_off,
            samp_scale=rpcs.samp_scale,
            lat_off=rpcs.lat_off,
            lat_scale=rpcs.lat_scale,
            lon_off=rpcs.long_off,
            lon_scale=rpcs.long_scale,
            height_off=rpcs.height_off,
            height_scale=rpcs.height_scale,
        )

    def to_rasterio(self):
        """The same model as a :class:`rasterio.rpc.RPC` (to write into a GeoTIFF)."""
        from rasterio.rpc import RPC

        return RPC(
            height_off=self.height_off,
            height_scale=self.height_scale,
            lat_off=self.lat_off,
            lat_scale=self.lat_scale,
            line_den_coeff=self.line_den.tolist(),
            line_num_coeff=self.line_num.tolist(),
            line_off=self.line_off,
            line_scale=self.line_scale,
            long_off=self.lon_off,
            long_scale=self.lon_scale,
            samp_den_coeff=self.samp_den.tolist(),
            samp_num_coeff=self.samp_num.tolist(),
            samp_off=self.samp_off,
            samp_scale=self.samp_scale,
        )

    def same_as(self, other: RPCModel) -> bool:
        """True when both models have identical coefficients and normalisation."""
        return np.array_equal(self._coeffs, other._coeffs) and all(
            getattr(self, f"{n}_{s}") == getattr(other, f"{n}_{s}")
            for n in ("line", "samp", "lat", "lon", "height")
            for s in ("off", "scale")
        )

    # ------------------------------------------------------------------ geometry
    @property
    def height_range(self) -> tuple[float, float]:
        """(min, max) ellipsoidal height of the validity domain, metres."""
        return self.height_off - abs(self.height_scale), self.height_off + abs(self.height_scale)

    def _normalise_ground(self, lon, lat, h):
        return (
            (lon - self.lon_off) / self.lon_scale,
            (lat - self.lat_off) / self.lat_scale,
            (h - self.height_off) / self.height_scale,
        )

    def project(self, lon, lat, h) -> tuple[np.ndarray, np.ndarray]:
        """Ground to image: full-scene pixel coordinates of ground points.

        Parameters
        ----------
        lon, lat : array_like (...)
            WGS84 longitude and latitude in degrees (broadcast together with ``h``).
        h : array_like (...)
            Height above the WGS84 ellipsoid in metres.

        Returns
        -------
        row, col : (...) float64
            Full-scene pixel coordinates, (0, 0) = centre of the top-left pixel.
            Points outside the validity domain are extrapolated (see :meth:`in_domain`).
        """
        lon, lat, h = np.broadcast_arrays(*(np.asarray(a, dtype=np.float64) for a in (lon, lat, h)))
        shape = lon.shape
        L, P, H = self._normalise_ground(lon.ravel(), lat.ravel(), h.ravel())
        rn = np.empty(L.size)
        cn = np.empty(L.size)
        for s in range(0, L.size, _CHUNK):
            sl = slice(s, s + _CHUNK)
            v = self._coeffs @ _terms(L[sl], P[sl], H[sl])
            rn[sl] = v[0] / v[1]
            cn[sl] = v[2] / v[3]
        row = rn * self.line_scale + self.line_off
        col = cn * self.samp_scale + self.samp_off
        return row.reshape(shape), col.reshape(shape)

    def localize(
        self, row, col, h, *, tol: float = 1e-8, max_iter: int = 20
    ) -> tuple[np.ndarray, np.ndarray]:
        """Image to ground: the (lon, lat) seen at full-scene pixels at given heights.

        Inverts :meth:`project` by Newton's method on the normalised longitude and
        latitude with the analytic 2 x 2 Jacobian, all points at once, starting from
        the centre of the domain.

        Parameters
        ----------
        row, col : array_like (...)
            Full-scene pixel coordinates, (0, 0) = centre of the top-left pixel.
        h : array_like (...)
            Height above the WGS84 ellipsoid in metres (broadcast with row, col).
        tol : float
            Convergence threshold on the Newton step, in degrees (1e-8 deg is ~1 mm).
        max_iter : int
            Iteration limit; points that have not converged by then get NaN (logged
            as a warning).

        Returns
        -------
        lon, lat : (...) float64
            WGS84 degrees.
        """
        row, col, h = np.broadcast_arrays(*(np.asarray(a, dtype=np.float64) for a in (row, col, h)))
        shape = row.shape
        rt = (row.ravel() - self.line_off) / self.line_scale
        ct = (col.ravel() - self.samp_off) / self.samp_scale
        H = (h.ravel() - self.height_off) / self.height_scale
        L = np.zeros(rt.size)
        P = np.zeros(rt.size)
        tol_L = tol / abs(self.lon_scale)
        tol_P = tol / abs(self.lat_scale)
        failed = 0
        for s in range(0, rt.size, _CHUNK):
            idx = np.arange(s, min(s + _CHUNK, rt.size))
            idx = idx[np.isfinite(rt[idx]) & np.isfinite(ct[idx]) & np.isfinite(H[idx])]
            for _ in range(max_iter):
                if idx.size == 0:
                    break
                Li, Pi, Hi = L[idx], P[idx], H[idx]
                v = self._coeffs @ _terms(Li, Pi, Hi)
                dvL = self._coeffs @ _terms_dL(Li, Pi, Hi)
                dvP = self._coeffs @ _terms_dP(Li, Pi, Hi)
                r = v[0] / v[1]
                c = v[2] / v[3]
                r_L = (dvL[0] - r * dvL[1]) / v[1]
                r_P = (dvP[0] - r * dvP[1]) / v[1]
                c_L = (dvL[2] - c * dvL[3]) / v[3]
                c_P = (dvP[2] - c * dvP[3]) / v[3]
                er = rt[idx] - r
                ec = ct[idx] - c
                det = r_L * c_P - r_P * c_L
                with np.errstate(divide="ignore", invalid="ignore"):
                    dL = (c_P * er - r_P * ec) / det
                    dP = (r_L * ec - c_L * er) / det
                L[idx] = Li + dL
                P[idx] = Pi + dP
                done = (np.abs(dL) < tol_L) & (np.abs(dP) < tol_P)
                idx = idx[~done]
            if idx.size:
                failed += idx.size
                L[idx] = np.nan
                P[idx] = np.nan
        invalid = ~(np.isfinite(rt) & np.isfinite(ct) & np.isfinite(H))
        L[invalid] = np.nan
        P[invalid] = np.nan
        if failed:
            log.warning(
                "RPC localisation did not converge for %d of %d points (set to NaN)",
                failed,
                rt.size,
            )
        lon = L * self.lon_scale + self.lon_off
        lat = P * self.lat_scale + self.lat_off
        return lon.reshape(shape), lat.reshape(shape)

    def in_domain(self, lon, lat, h, *, margin: float = 0.01) -> np.ndarray:
        """Whether ground points lie in the RPC validity domain.

        Parameters
        ----------
        lon, lat, h : array_like (...)
            WGS84 degrees and ellipsoidal metres (broadcast together).
        margin : float
            Tolerance as a fraction of each scale: the domain is
            ``|value - offset| <= (1 + margin) * scale`` on every axis.

        Returns
        -------
        (...) bool
        """
        lon, lat, h = np.broadcast_arrays(*(np.asarray(a, dtype=np.float64) for a in (lon, lat, h)))
        L, P, H = self._normalise_ground(lon, lat, h)
        limit = 1.0 + margin
        return (np.abs(L) <= limit) & (np.abs(P) <= limit) & (np.abs(H) <= limit)


@dataclass(frozen=True, eq=False)
class RPCCamera:
    """An image with an RPC model: a full scene or a crop of one.

    Parameters
    ----------
    model : RPCModel
        The full scene's model.
    width, height : int
        Size of this image (the crop) in pixels.
    col0, row0 : float
        Full-scene pixel coordinates of this image's pixel (0, 0): crop pixel
        (row, col) is full-scene pixel (row + row0, col + col0). 0 for a full scene.
    name : str
    image_path : Path or None

    Notes
    -----
    Pixel coordinates follow :class:`RPCModel`: (0, 0) is the centre of the crop's
    top-left pixel, so ``image[i, j]`` is at (row, col) = (i, j).
    """

    model: RPCModel
    width: int
    height: int
    col0: float = 0.0
    row0: float = 0.0
    name: str = ""
    image_path: Path | None = None

    def project(self, lon, lat, h) -> tuple[np.ndarray, np.ndarray]:
        """Ground to crop pixels: (row, col), each shaped like the broadcast inputs.

        See :meth:`RPCModel.project`; the result is shifted by (row0, col0).
        """
        row, col = self.model.project(lon, lat, h)
        return row - self.row0, col - self.col0

    def localize(
        self, row, col, h, *, tol: float = 1e-8, max_iter: int = 20
    ) -> tuple[np.ndarray, np.ndarray]:
        """Crop pixels (row, col) at heights h to (lon, lat); see :meth:`RPCModel.localize`."""
        row, col = np.asarray(row, dtype=np.float64), np.asarray(col, dtype=np.float64)
        return self.model.localize(row + self.row0, col + self.col0, h, tol=tol, max_iter=max_iter)

    def in_domain(self, lon, lat, h, *, margin: float = 0.01) -> np.ndarray:
        """See :meth:`RPCModel.in_domain`."""
        return self.model.in_domain(lon, lat, h, margin=margin)

    def contains(self, row, col) -> np.ndarray:
        """(...) bool: whether crop pixel coordinates fall on the image (pixel edges included)."""
        row, col = np.asarray(row, dtype=np.float64), np.asarray(col, dtype=np.float64)
        in_rows = (row >= -0.5) & (row <= self.height - 0.5)
        return in_rows & (col >= -0.5) & (col <= self.width - 0.5)


def read_rpc_camera(image_path: str | Path) -> RPCCamera:
    """The RPC camera of an image file.

    The model comes from the GeoTIFF RPC metadata (GDAL ``RPC`` domain) when present,
    else from an OSSIM keyword file beside the image with the same stem
    (``img1.tif`` -> ``img1.geom``), which describes the full scene. The crop offset
    (col0, row0) is the geotransform's translation when the geotransform is a pure
    pixel offset (scale 1, no rotation, rows downwards, as a crop of a
    non-georeferenced scene carries); otherwise it is 0. The size is the image's.

    Raises
    ------
    InputError
        When the image cannot be read, or no RPC is found (naming the image).
    """
    import rasterio
    from rasterio.errors import NotGeoreferencedWarning

    from recon3d.io import require_file
    from recon3d.io.geotiff import DAMAGED_RASTER

    path = require_file(image_path, "image")
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", NotGeoreferencedWarning)
            with rasterio.open(path) as src:
                rpcs = src.rpcs
                transform = src.transform
                width, height = src.width, src.height
    except DAMAGED_RASTER as exc:
        raise InputError(f"{path}: cannot read image ({exc})") from None

    geom = path.with_suffix(".geom")
    if rpcs is not None:
        model = RPCModel.from_rasterio(rpcs)
        source = "GeoTIFF RPC tags"
    elif geom.is_file():
        model = RPCModel.from_geom(geom)
        source = str(geom)
    else:
        raise InputError(
            f"{path}: no RPC model found "
            f"(no RPC metadata in the image and no {geom.name} beside it)"
        )

    t = transform
    if (t.a, t.b, t.d, t.e) == (1.0, 0.0, 0.0, 1.0):
        col0, row0 = float(t.c), float(t.f)
    else:
        col0 = row0 = 0.0
    log.debug(
        "%s: RPC from %s, crop offset col %g row %g, %d x %d",
        path, source, col0, row0, width, height,
    )
    return RPCCamera(model, int(width), int(height), col0, row0, name=path.stem, image_path=path)
