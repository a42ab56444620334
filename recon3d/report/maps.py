"""Map figures for report.html: shaded, tinted rasters as PNG under an SVG overlay
with coordinate ticks, a scale bar, a grid-north arrow, a colour bar and a legend.

A figure is fixed-size HTML: an ``<img>`` (the raster, a PNG data URI) placed inside
the frame of an ``<svg>`` that draws everything else, so text stays crisp at any zoom.
No-data cells are transparent in the PNG and the frame behind them is hatched; the
legend says so.
"""

from __future__ import annotations

import base64
import html
from dataclasses import dataclass

import cv2
import numpy as np

from recon3d.terrain.dtm import fill_nearest

__all__ = ["COLORMAPS", "DEFS", "MapFrame", "colorize", "colour_bar", "figure_html", "hillshade", "nice_step", "png_uri",
           "shaded_relief"]

#: Colour ramps as (position 0..1, RGB) stops, interpolated linearly.
COLORMAPS = {
    # hypsometric tint: low green, yellow, brown, pale high ground
    "terrain": [(0.0, (38, 115, 77)), (0.25, (134, 179, 96)), (0.5, (235, 222, 140)),
                (0.75, (176, 122, 72)), (1.0, (245, 240, 235))],
    # height above ground: pale ground, yellow, orange, red, dark purple (light to dark: readable in grey too)
    "height": [(0.0, (246, 244, 236)), (0.12, (254, 224, 139)), (0.35, (253, 141, 60)),
               (0.65, (215, 48, 39)), (1.0, (84, 22, 94))],
}

NODATA_NOTE = "no data (NaN): transparent, shown as grey hatching"
MARGIN = {"left": 78, "right": 118, "top": 14, "bottom": 48}


#: Largest width and height of a map on the page (display pixels).
MAP_SIZE = 860


@dataclass(frozen=True)
class MapFrame:
    """Where a raster's extent lands on the page.

    ``x0, y1`` are the world coordinates of the image's top-left corner, ``scale`` the
    display pixels per world unit; ``width, height`` the image's display size (px).
    """

    x0: float
    y1: float
    scale: float
    width: int
    height: int

    @classmethod
    def fit(cls, bounds: tuple[float, float, float, float], max_width: int = MAP_SIZE,
            max_height: int = MAP_SIZE) -> MapFrame:
        """The frame showing ``bounds`` (xmin, ymin, xmax, ymax) as large as fits."""
        xmin, ymin, xmax, ymax = bounds
        scale = min(max_width / max(xmax - xmin, 1e-9), max_height / max(ymax - ymin, 1e-9))
        return cls(xmin, ymax, scale, round((xmax - xmin) * scale), round((ymax - ymin) * scale))

    def px(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Display pixel coordinates (inside the image) of world points."""
        return (np.asarray(x) - self.x0) * self.scale, (self.y1 - np.asarray(y)) * self.scale


def hillshade(z: np.ndarray, cell: float, *, azimuth: float = 315.0, altitude: float = 45.0) -> np.ndarray:
    """(rows, cols) float32 hillshade 0..1 of a height grid (NaN where ``z`` is NaN).

    ``cell`` is the grid spacing in the heights' units.
    """
    valid = np.isfinite(z)
    filled = np.where(valid, z, np.nanmedian(z) if valid.any() else 0.0)
    if valid.any() and not valid.all():  # no cliff at the edge of the data
        filled = fill_nearest(z)
    gy, gx = np.gradient(filled, cell)
    slope = np.arctan(np.hypot(gx, gy))
    aspect = np.arctan2(-gx, gy)
    az, alt = np.radians(360.0 - azimuth + 90.0), np.radians(altitude)
    shade = np.sin(alt) * np.cos(slope) + np.cos(alt) * np.sin(slope) * np.cos(az - aspect)
    return np.where(valid, np.clip(shade, 0.0, 1.0), np.nan).astype(np.float32)


def colorize(values: np.ndarray, lo: float, hi: float, cmap: str) -> np.ndarray:
    """(..., 3) uint8 RGB of ``values`` on the colour ramp ``cmap`` between ``lo`` and ``hi``."""
    stops = COLORMAPS[cmap]
    pos = np.array([p for p, _ in stops])
    rgb = np.array([c for _, c in stops], float)
    t = np.clip((np.nan_to_num(values, nan=lo) - lo) / max(hi - lo, 1e-9), 0.0, 1.0)
    return np.stack([np.interp(t, pos, rgb[:, k]) for k in range(3)], axis=-1).round().astype(np.uint8)


def shaded_relief(z: np.ndarray, cell: float, lo: float, hi: float, cmap: str | None, factor: float) -> np.ndarray:
    """(round(rows*factor), round(cols*factor), 4) uint8 RGBA: the tinted hillshade, NaN transparent.

    The heights are resampled first (bilinear up, area average down), so a coarse grid
    shown large stays smooth and a large one is not embedded at full size; ``cmap``
    None gives a grey hillshade.
    """
    valid = np.isfinite(z)
    if factor != 1.0:
        size = (max(round(z.shape[1] * factor), 1), max(round(z.shape[0] * factor), 1))
        filled = fill_nearest(z) if valid.any() and not valid.all() else np.nan_to_num(z)
        method = cv2.INTER_LINEAR if factor > 1 else cv2.INTER_AREA
        z_new = cv2.resize(filled.astype(np.float32), size, interpolation=method)
        valid = cv2.resize(valid.astype(np.uint8), size, interpolation=cv2.INTER_NEAREST).astype(bool)
        z = np.where(valid, z_new, np.nan)
        cell = cell / factor
    shade = np.nan_to_num(hillshade(z, cell), nan=0.0)
    if cmap is None:
        rgb = np.repeat((105 + 150 * shade)[..., None], 3, axis=-1)
    else:
        # multiply blend, lifted so flat ground keeps its tint
        light = np.clip(0.5 + 0.5 * shade / np.sin(np.radians(45.0)), 0.0, 1.2)  # flat ground: 1
        rgb = colorize(z, lo, hi, cmap).astype(float) * light[..., None]
    alpha = np.where(valid, 255, 0)
    return np.dstack([np.clip(rgb, 0, 255), alpha]).astype(np.uint8)


def resample_factor(shape: tuple[int, int], frame: MapFrame) -> float:
    """The factor bringing a raster near its display size: 2 for a small one (the
    browser scales the rest smoothly; more only makes the file larger), down to twice
    the display width (sharp on high-DPI screens) for a large one."""
    cols = max(shape[1], 1)
    if cols <= frame.width:
        return float(np.clip(np.floor(frame.width / cols), 1, 2))
    return min(1.0, 2.0 * frame.width / cols)


def png_uri(rgba: np.ndarray) -> str:
    """PNG data URI of an RGB(A) uint8 image (deterministic bytes)."""
    channels = cv2.COLOR_RGBA2BGRA if rgba.shape[-1] == 4 else cv2.COLOR_RGB2BGR
    # level 6: level 9 takes 8 times longer for 5 % less
    ok, data = cv2.imencode(".png", cv2.cvtColor(rgba, channels), [cv2.IMWRITE_PNG_COMPRESSION, 6])
    if not ok:
        raise ValueError("PNG encoding failed")
    return "data:image/png;base64," + base64.b64encode(data.tobytes()).decode()


def nice_step(span: float, target: int = 5) -> float:
    """A 1, 2 or 5 x 10^k step dividing ``span`` into about ``target`` parts."""
    raw = max(span, 1e-9) / target
    power = 10.0 ** np.floor(np.log10(raw))
    return float(min((m * power for m in (1, 2, 5, 10)), key=lambda s: abs(s - raw)))


def _num(v: float, step: float) -> str:
    decimals = max(0, -int(np.floor(np.log10(step)))) if step < 1 else 0
    return f"{v:,.{decimals}f}".replace(",", "\u2009")


def _ticks(frame: MapFrame, bounds, crs_label: str) -> str:
    xmin, ymin, xmax, ymax = bounds
    step = nice_step(max(xmax - xmin, ymax - ymin), 5)
    out = []
    for x in np.arange(np.ceil(xmin / step) * step, xmax + 1e-9, step):
        px = (x - frame.x0) * frame.scale
        out.append(f'<line class=grid x1="{px:.1f}" y1="0" x2="{px:.1f}" y2="{frame.height}"/>'
                   f'<line class=tick x1="{px:.1f}" y1="{frame.height}" x2="{px:.1f}" y2="{frame.height + 5}"/>'
                   f'<text class=tl x="{px:.1f}" y="{frame.height + 18}" text-anchor=middle>{_num(x, step)}</text>')
    for y in np.arange(np.ceil(ymin / step) * step, ymax + 1e-9, step):
        py = (frame.y1 - y) * frame.scale
        out.append(f'<line class=grid x1="0" y1="{py:.1f}" x2="{frame.width}" y2="{py:.1f}"/>'
                   f'<line class=tick x1="-5" y1="{py:.1f}" x2="0" y2="{py:.1f}"/>'
                   f'<text class=tl x="-8" y="{py + 4:.1f}" text-anchor=end>{_num(y, step)}</text>')
    label = html.escape(crs_label)
    out.append(f'<text class=axis x="{frame.width / 2:.0f}" y="{frame.height + 38}" text-anchor=middle>'
               f"easting ({label})</text>"
               f'<text class=axis transform="translate({-MARGIN["left"] + 14},{frame.height / 2:.0f}) rotate(-90)" '
               f"text-anchor=middle>northing ({label})</text>")
    return "".join(out)


def _scale_bar(frame: MapFrame, metres_per_unit: float) -> str:
    """Four alternating segments, lower left, in metres whatever the CRS unit."""
    metres_per_px = metres_per_unit / frame.scale
    length_m = nice_step(frame.width * metres_per_px / 4, 1)
    seg = length_m / metres_per_px / 4
    x, y = 14, frame.height - 22
    boxes = "".join(f'<rect x="{x + i * seg:.1f}" y="{y}" width="{seg:.1f}" height="6" '
                    f'fill="{"#222" if i % 2 == 0 else "#fff"}" stroke="#222" stroke-width=".8"/>' for i in range(4))
    label = f"{length_m:g} m" if length_m < 1000 else f"{length_m / 1000:g} km"
    return (f'<g class=scalebar><rect x="{x - 8}" y="{y - 20}" width="{4 * seg + 16:.1f}" height="34" rx="3" '
            f'fill="#fff" fill-opacity=".85"/>{boxes}<text x="{x}" y="{y - 5}" font-size="11">0</text>'
            f'<text x="{x + 4 * seg:.1f}" y="{y - 5}" font-size="11" text-anchor=end>{label}</text></g>')


def _north_arrow(frame: MapFrame) -> str:
    x, y = frame.width - 26, 14
    return (f'<g class=north transform="translate({x},{y})"><rect x="-14" y="-4" width="28" height="46" rx="3" '
            'fill="#fff" fill-opacity=".85"/><path d="M0 0 L9 26 L0 20 Z" fill="#222"/>'
            '<path d="M0 0 L-9 26 L0 20 Z" fill="#fff" stroke="#222" stroke-width=".8"/>'
            '<text x="0" y="39" text-anchor=middle font-size="12" font-weight="bold">N</text>'
            "<title>grid north (the CRS's y axis)</title></g>")


def colour_bar(frame: MapFrame, lo: float, hi: float, cmap: str, title: str, *, key: str, nodata: bool = True) -> str:
    """A vertical colour bar right of the frame, ticks in the data's values, and the
    no-data swatch; ``key`` makes its gradient's id unique in the page."""
    x, h, w = frame.width + 18, min(frame.height - 70, 260), 16
    stops = "".join(f'<stop offset="{1 - p:.2f}" stop-color="rgb{c}"/>' for p, c in reversed(COLORMAPS[cmap]))
    gid = f"cb-{key}"
    step = nice_step(hi - lo, 4)
    ticks = []
    for v in np.arange(np.ceil(lo / step) * step, hi + 1e-9, step):
        py = 20 + (hi - v) / max(hi - lo, 1e-9) * h
        ticks.append(f'<line class=tick x1="{x + w}" y1="{py:.1f}" x2="{x + w + 4}" y2="{py:.1f}"/>'
                     f'<text class=tl x="{x + w + 7}" y="{py + 4:.1f}">{_num(v, step)}</text>')
    return (f'<defs><linearGradient id="{gid}" x1="0" y1="0" x2="0" y2="1">{stops}</linearGradient></defs>'
            f'<text class=axis x="{x}" y="10">{html.escape(title)}</text>'
            f'<rect x="{x}" y="20" width="{w}" height="{h}" fill="url(#{gid})" stroke="#555" stroke-width=".6"/>'
            f'{"".join(ticks)}{_nodata_swatch(x, 20 + h + 16) if nodata else ""}')


def _nodata_swatch(x: float, y: float) -> str:
    return (f'<rect x="{x}" y="{y}" width="16" height="12" fill="url(#hatch)" stroke="#555" stroke-width=".6"/>'
            f'<text class=tl x="{x + 22}" y="{y + 10}">no data</text>')


#: Defined once per page (a hidden SVG): the hatching of no-data and of buildings without a solid.
DEFS = ('<svg width="0" height="0" style="position:absolute" aria-hidden="true"><defs><pattern id="hatch" width="8" height="8" patternUnits="userSpaceOnUse" patternTransform="rotate(45)">'
         '<rect width="8" height="8" fill="#f4f4f4"/><line x1="0" y1="0" x2="0" y2="8" stroke="#c8c8c8" stroke-width="3"/>'
         "</pattern></defs></svg>")


def figure_html(image_uri: str, alt: str, frame: MapFrame, bounds, *, key: str, crs_label: str,
                metres_per_unit: float, legend: str, overlay: str = "", caption: str = "") -> str:
    """One map figure: the raster, its overlay (SVG drawn in image pixels, clipped to
    the frame), ticks, scale bar, north arrow and ``legend`` (SVG, right of the frame).
    ``key`` makes the figure's SVG ids unique in the page."""
    m = MARGIN
    w, h = frame.width + m["left"] + m["right"], frame.height + m["top"] + m["bottom"]
    img = (f'<img class=raster src="{image_uri}" alt="{html.escape(alt)}" width="{frame.width}" '
           f'height="{frame.height}" style="left:{m["left"]}px;top:{m["top"]}px">')
    svg = (
        f'<svg class=overlay width="{w}" height="{h}" viewBox="0 0 {w} {h}" aria-hidden="true">'
        f'<g transform="translate({m["left"]},{m["top"]})">'
        f'<defs><clipPath id="clip-{key}"><rect width="{frame.width}" height="{frame.height}"/></clipPath></defs>'
        f'<g clip-path="url(#clip-{key})">{overlay}</g>{_ticks(frame, bounds, crs_label)}'
        f'<rect x="0" y="0" width="{frame.width}" height="{frame.height}" fill="none" stroke="#333" stroke-width="1"/>'
        f"{_scale_bar(frame, metres_per_unit)}{_north_arrow(frame)}{legend}</g></svg>"
    )
    cap = f"<figcaption>{caption}</figcaption>" if caption else ""
    return f'<figure class=map><div class=canvas style="width:{w}px;height:{h}px">{img}{svg}</div>{cap}</figure>'
