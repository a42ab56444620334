"""A self-contained HTML report of a run: tables, histograms, hillshades and a buildings map.

Everything is inline (PNG as data URIs, histograms and the map as SVG), so the file
opens offline and can be mailed as is.
"""

from __future__ import annotations

import base64
import html
import json
from pathlib import Path

import cv2
import numpy as np

from recon3d.errors import InputError
from recon3d.io import atomic_path
from recon3d.io.geotiff import read_raster

__all__ = ["hillshade", "write_report"]

STYLE = """
body{font-family:system-ui,sans-serif;margin:2em auto;max-width:1100px;color:#222}
h1{font-size:1.6em}h2{border-bottom:1px solid #ccc;padding-bottom:.2em;margin-top:1.6em}
table{border-collapse:collapse;margin:.5em 0}td,th{border:1px solid #ddd;padding:3px 8px;text-align:right}
th{background:#f3f3f3}td.l,th.l{text-align:left}.grid{display:flex;flex-wrap:wrap;gap:12px}
figure{margin:0}figcaption{font-size:.85em;color:#555;text-align:center}img{max-width:340px;border:1px solid #ccc}
.small{font-size:.85em;color:#555}
.warn{background:#fff4e0;border-left:4px solid #e08a00;padding:.4em .8em}
"""


def write_report(out_dir: str | Path) -> Path:
    """Write ``out_dir/report.html`` from the products and JSON files of a run.

    Raises
    ------
    InputError
        When ``out_dir`` is not a recon3d output folder (no report.json / run.json).
    """
    out_dir = Path(out_dir)
    try:
        report = json.loads((out_dir / "report.json").read_text(encoding="utf-8"))
        run = json.loads((out_dir / "run.json").read_text(encoding="utf-8"))
    except FileNotFoundError as exc:
        raise InputError(f"{out_dir}: not a recon3d output folder ({Path(exc.filename).name} missing)") from None
    parts = [
        f"<h1>recon3d report</h1><p class=small>{html.escape(run['inputs'].get('input', ''))} · "
        f"{run['inputs'].get('points', '?')} points · CRS {html.escape(str(run['inputs'].get('crs')))} · "
        f"recon3d {html.escape(run.get('recon3d', ''))}</p>",
        _warnings_section(report.get("warnings") or run.get("warnings") or []),
        _accuracy_section(report.get("accuracy", [])),
        _stereo_section(run.get("chosen", {}).get("stereo")),
        _ground_section(report),
        _images_section(out_dir),
        _buildings_section(out_dir, report),
        _changes_section(report),
        _timings_section(run),
        _parameters_section(run),
    ]
    page = (
        "<!DOCTYPE html><html lang=en><head><meta charset=utf-8><title>recon3d report</title>"
        f"<style>{STYLE}</style></head><body>{''.join(parts)}</body></html>"
    )
    path = out_dir / "report.html"
    with atomic_path(path) as tmp:
        tmp.write_text(page, encoding="utf-8")
    return path


def hillshade(z: np.ndarray, cell: float, *, azimuth: float = 315.0, altitude: float = 45.0) -> np.ndarray:
    """(rows, cols) uint8 hillshade of a height grid (NaN cells black)."""
    filled = np.where(np.isfinite(z), z, np.nanmin(z) if np.isfinite(z).any() else 0.0)
    gy, gx = np.gradient(filled, cell)
    slope = np.arctan(np.hypot(gx, gy))
    aspect = np.arctan2(-gx, gy)
    az, alt = np.radians(360.0 - azimuth + 90.0), np.radians(altitude)
    shade = np.sin(alt) * np.cos(slope) + np.cos(alt) * np.sin(slope) * np.cos(az - aspect)
    out = np.clip(shade * 255, 0, 255).astype(np.uint8)
    out[~np.isfinite(z)] = 0
    return out


def _warnings_section(warnings: list[str]) -> str:
    if not warnings:
        return ""
    items = "".join(f"<li>{html.escape(w)}</li>" for w in warnings)
    return f"<h2>Warnings</h2><div class=warn><ul>{items}</ul></div>"


def _satellite_section(stereo: dict) -> str:
    """Satellite pair: each tile's searched heights and why, bias, share matched, or why it failed."""
    tiles = stereo["tiles"]
    head = ("tile", "core (px)", "heights searched (m)", "from", "bias (px)", "vertical parallax (px)",
            "matched % of overlap", "points")
    rows = []
    for t in tiles["per_tile"]:
        cells = [t["tile"], t["core"], "{:.1f} .. {:.1f}".format(*t["search_heights_m"]), t["search_from"],
                 t["bias_px"], t["vertical_parallax_px"].get("median"), t["matched_percent"], t["points"]]
        rows.append("<tr>" + "".join(f"<td class=l>{html.escape(str(c))}</td>" for c in cells) + "</tr>")
    for f in tiles["failures"]:
        rows.append(f"<tr><td class=l>{f['tile']}</td><td class=l>{f['core']}</td>"
                    f"<td class=l colspan=6>failed: {html.escape(f['reason'])}</td></tr>")
    ties = stereo.get("tie_points", {})
    note = (f"<p class=small>{ties.get('on_epipolar_curves', '?')} of {ties.get('sift_matches', '?')} SIFT tie points "
            f"within {ties.get('epipolar_tolerance_px', '?')} px of their epipolar curves, heights "
            f"{stereo.get('tie_heights_m')} m; {stereo.get('matched_percent')} % of the overlap matched "
            "(the rest filled in: no DTM and no building from it).</p>")
    check = stereo.get("self_check") or {}
    if check.get("tie_points"):
        note += (f"<p class=small>Self-check: at {check['tie_points']} tie points the dense disparities differ from "
                 f"SIFT's by {check['median_px']} px (median; {check['median_m']} m), {check['within_1px_percent']} % "
                 "within 1 px.</p>")
    return (
        "<h2>Satellite pair: tiles</h2><table><tr>" + "".join(f"<th>{h}</th>" for h in head)
        + f"</tr>{''.join(rows)}</table>{note}"
    )


def _stereo_section(stereo: dict | None) -> str:
    """Frame stereo: each matched pair and its self-check against the sparse points;
    satellite pairs: their tiles."""
    if stereo and "tiles" in stereo:
        return _satellite_section(stereo)
    if not stereo or not stereo.get("pairs") or "self_check" not in stereo["pairs"][0]:
        return ""
    head = ("pair", "matched % of overlap", "sparse points covered %", "distance to sparse points (m)",
            "in GSD", "reprojection (px, p95)", "vertical parallax (px)", "share of the cloud %")
    rows = []
    for p in stereo["pairs"]:
        c = p["self_check"]
        cells = [p.get("matched_percent"), c.get("coverage_percent"), c.get("discrepancy_m"), c.get("discrepancy_gsd"),
                 c.get("reprojection_px"), p.get("vertical_parallax_px", {}).get("median"), p.get("fused_share_percent")]
        rows.append(f"<tr><td class=l>{html.escape(p['pair'])}</td>" + "".join(f"<td>{_fmt(v, 2)}</td>" for v in cells) + "</tr>")
    area = stereo.get("common_area")
    note = ""
    if area:
        note = (f"<p class=small>Area both images of a matched pair see: {area['area_m2']:.0f} m², "
                f"{area['filled_percent']:.1f} % in the DSM, {area['observed_percent']:.1f} % of it matched "
                "(not filled in).</p>")
    return (
        "<h2>Stereo pairs and their self-check</h2><table><tr>" + "".join(f"<th>{h}</th>" for h in head)
        + f"</tr>{''.join(rows)}</table>{note}"
    )


def _accuracy_section(rows: list[dict]) -> str:
    if not rows:
        return "<h2>Accuracy</h2><p>No reference was given (check points, provider classes or a reference DSM).</p>"
    head = "".join(f"<th>{h}</th>" for h in ("n", "mean", "std", "RMS", "max", "NMAD", "≤ 1 m %", "≤ 2 m %"))
    body = []
    for r in rows:
        cells = [r["n"]] + [_fmt(r[k]) for k in ("mean", "std", "rms", "max_abs", "nmad", "within_1m", "within_2m")]
        body.append(
            f"<tr><td class=l>{html.escape(r['product'])}</td><td class=l>{html.escape(r['reference'])}</td>"
            + "".join(f"<td>{c}</td>" for c in cells)
            + f"<td>{_histogram_svg(r.get('histogram'))}</td></tr>"
        )
    return (
        "<h2>Accuracy (metres)</h2><table><tr><th class=l>product</th><th class=l>reference</th>"
        f"{head}<th>errors −3…+3 m</th></tr>{''.join(body)}</table>"
    )


def _histogram_svg(hist: dict | None, width: int = 180, height: int = 40) -> str:
    if not hist or not sum(hist["counts"]):
        return ""
    counts = np.asarray(hist["counts"], dtype=float)
    w = width / len(counts)
    bars = "".join(
        f'<rect x="{i * w:.1f}" y="{height - h:.1f}" width="{w - 1:.1f}" height="{h:.1f}" fill="#4a7ebb"/>'
        for i, h in enumerate(counts / counts.max() * height)
    )
    mid = f'<line x1="{width / 2}" y1="0" x2="{width / 2}" y2="{height}" stroke="#c00" stroke-width="1"/>'
    return f'<svg width="{width}" height="{height}" role="img" aria-label="error histogram">{bars}{mid}</svg>'


def _ground_section(report: dict) -> str:
    g = report.get("ground_filter")
    if not g or not g.get("n"):
        return ""
    return (
        "<h2>Ground filter against the provider's classes</h2><table><tr><th>points scored</th><th>Type I %</th>"
        f"<th>Type II %</th><th>total %</th><th>kappa</th></tr><tr><td>{g['n']}</td><td>{_fmt(g['type_i_percent'])}</td>"
        f"<td>{_fmt(g['type_ii_percent'])}</td><td>{_fmt(g['total_percent'])}</td><td>{_fmt(g['kappa'], 4)}</td></tr></table>"
    )


def _images_section(out_dir: Path) -> str:
    figures = []
    for name, title in (("dsm", "DSM"), ("dtm", "DTM"), ("model_dsm", "model DSM")):
        path = out_dir / f"{name}.tif"
        if path.exists():
            r = read_raster(path)
            figures.append(f"<figure><img alt='{title} hillshade' src='{_png(hillshade(r.data.astype(float), r.resolution))}'>"
                           f"<figcaption>{title} (hillshade)</figcaption></figure>")
    return f"<h2>Surfaces</h2><div class=grid>{''.join(figures)}</div>" if figures else ""


def _png(image: np.ndarray, max_width: int = 800) -> str:
    if image.shape[1] > max_width:
        scale = max_width / image.shape[1]
        image = cv2.resize(image, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA)
    ok, data = cv2.imencode(".png", image)
    return "data:image/png;base64," + base64.b64encode(data.tobytes()).decode()


def _buildings_section(out_dir: Path, report: dict) -> str:
    b = report.get("buildings", {})
    rows = "".join(f"<tr><td class=l>{html.escape(k)}</td><td>{v}</td></tr>" for k, v in b.get("statuses", {}).items())
    rows += "".join(f"<tr><td class=l>reason: {html.escape(k)}</td><td>{v}</td></tr>" for k, v in b.get("reasons", {}).items())
    lods = b.get("lods", {})
    rows += "".join(f"<tr><td class=l>LoD {html.escape(k)}</td><td>{v}</td></tr>" for k, v in lods.items())
    if b.get("blocks"):
        rows += f"<tr><td class=l>blocks of BuildingParts</td><td>{b['blocks']}</td></tr>"
    table = f"<table><tr><th class=l>buildings</th><th>{b.get('count', 0)}</th></tr>{rows}</table>"
    return f"<h2>Buildings</h2>{table}{_map_svg(out_dir / 'footprints.geojson')}"


def _map_svg(path: Path, size: int = 600) -> str:
    if not path.exists():
        return ""
    features = json.loads(path.read_text(encoding="utf-8")).get("features", [])
    rings = [(f["properties"], np.asarray(f["geometry"]["coordinates"][0], float)) for f in features if f.get("geometry")]
    if not rings:
        return ""
    allxy = np.concatenate([r for _, r in rings])
    lo, hi = allxy.min(axis=0), allxy.max(axis=0)
    scale = size / max(float(np.max(hi - lo)), 1e-9)
    shapes = []
    for props, ring in rings:
        pts = " ".join(f"{(x - lo[0]) * scale:.1f},{(hi[1] - y) * scale:.1f}" for x, y in ring)
        err = props.get("roof_rms_m")
        color = "#999" if err is None else _error_color(float(err))
        label = html.escape(f"{props.get('id')}: {props.get('status')} {props.get('reason') or ''} roof RMS {err}")
        shapes.append(f'<polygon points="{pts}" fill="{color}" stroke="#333" stroke-width="0.5"><title>{label}</title></polygon>')
    h = (hi[1] - lo[1]) * scale
    legend = "<p class=small>Buildings coloured by roof RMS of the model against the measured DSM: green 0 m, red ≥ 2 m, grey no solid.</p>"
    return f'{legend}<svg width="{size}" height="{h:.0f}" role="img" aria-label="buildings map">{"".join(shapes)}</svg>'


def _error_color(err: float) -> str:
    t = min(max(err / 2.0, 0.0), 1.0)
    return f"rgb({int(40 + 200 * t)},{int(180 - 140 * t)},60)"


def _changes_section(report: dict) -> str:
    c = report.get("changes")
    if not c:
        return ""
    rows = "".join(f"<tr><td class=l>{html.escape(k)}</td><td>{v}</td></tr>" for k, v in c["summary"].items())
    notes = "".join(f"<li>{html.escape(n)}</li>" for n in c.get("notes", []))
    return f"<h2>Changes against the older building database</h2><table>{rows}</table><ul class=small>{notes}</ul>"


def _timings_section(run: dict) -> str:
    t = run.get("timings_s", {})
    rows = "".join(f"<tr><td class=l>{html.escape(k)}</td><td>{v:.2f}</td></tr>" for k, v in t.items())
    return f"<h2>Timings (s)</h2><table>{rows}<tr><th class=l>total</th><th>{sum(t.values()):.2f}</th></tr></table>"


def _parameters_section(run: dict) -> str:
    rows = []
    for key, value in _flatten(run.get("chosen", {})):
        rows.append(f"<tr><td class=l>{html.escape(key)}</td><td class=l>{html.escape(str(value))}</td></tr>")
    return f"<h2>Parameters chosen from the data</h2><table>{''.join(rows)}</table>"


def _flatten(d: dict, prefix: str = ""):
    for k, v in d.items():
        key = f"{prefix}{k}"
        if isinstance(v, dict) and "value" in v:
            yield key, f"{v['value']} — {v.get('reason', '')}"
        elif isinstance(v, dict):
            yield from _flatten(v, key + ".")
        elif not isinstance(v, list):
            yield key, v


def _fmt(v, digits: int = 3) -> str:
    return "–" if v is None else f"{v:.{digits}f}"
