"""A self-contained HTML report of a run, from its run.json, report.json and products.

Everything is inline (rasters as PNG data URIs, overlays and histograms as SVG, a few
lines of JS to sort the tables), so the file opens offline and can be mailed as is.
Numbers are rounded for people: metres to the centimetre, percentages to 0.1, and a
measure that does not apply reads "n/a" (never a zero that looks like a failure).
"""

from __future__ import annotations

import html
import json
import math
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np

from recon3d.errors import InputError
from recon3d.io import atomic_path
from recon3d.io.geotiff import read_raster
from recon3d.report import maps
from recon3d.report.maps import hillshade

__all__ = ["fmt_m", "fmt_pct", "hillshade", "write_report"]

NA = "n/a"

STYLE = """
:root{--ink:#1d2733;--muted:#5b6672;--line:#d9dee4;--head:#eef1f4;--accent:#1f5f99}
body{font-family:system-ui,-apple-system,"Segoe UI",Roboto,sans-serif;margin:0;color:var(--ink);background:#f6f7f9}
main{max-width:1120px;margin:0 auto;padding:1.2em 2em 3em;background:#fff;box-shadow:0 0 8px rgba(0,0,0,.06)}
h1{font-size:1.7em;margin:.3em 0 .1em}h2{font-size:1.25em;border-bottom:2px solid var(--accent);padding-bottom:.2em;margin-top:1.8em}
h3{font-size:1.02em;margin:1.2em 0 .3em}
table{border-collapse:collapse;margin:.4em 0 .8em;font-size:.9em;font-variant-numeric:tabular-nums}
td,th{border:1px solid var(--line);padding:3px 8px;text-align:right;vertical-align:middle}
th{background:var(--head);font-weight:600}td.l,th.l{text-align:left}
table.kv th{text-align:left;font-weight:500;background:#f7f8fa}
.meta{color:var(--muted);font-size:.92em;margin:.2em 0 1em}
.cards{display:flex;flex-wrap:wrap;gap:10px;margin:1em 0}
.card{border:1px solid var(--line);border-radius:6px;padding:.5em .9em;min-width:120px;background:#fbfcfd}
.card.alert{border-color:#e08a00;background:#fff6e5}.card b{display:block;font-size:1.35em}.card span{color:var(--muted);font-size:.82em}
nav{font-size:.88em;margin:.6em 0}nav a{margin-right:1em;color:var(--accent);text-decoration:none}
.small,figcaption{font-size:.85em;color:var(--muted)}
.warn{background:#fff6e5;border-left:4px solid #e08a00;padding:.3em .8em;margin:.4em 0}
.ok{background:#eef7ee;border-left:4px solid #3c8d40;padding:.5em .8em}
.warn li.note{color:var(--muted)}.warn li{margin:.25em 0}
.tag{display:inline-block;font-size:.75em;border-radius:3px;padding:0 5px;margin-right:6px;color:#fff;background:#e08a00}
.tag.note{background:#7a8794}
figure.map{margin:.6em 0 1.4em}.canvas{position:relative}
img.raster{position:absolute;display:block;background:repeating-linear-gradient(45deg,#f4f4f4 0 5px,#cdcdcd 5px 7px)}
svg.overlay{position:absolute;left:0;top:0;overflow:visible}
svg text{font-family:system-ui,sans-serif;fill:#222}.tl{font-size:11px}.axis{font-size:12px;fill:#444}
line.grid{stroke:#fff;stroke-opacity:.45;stroke-width:.7}line.tick{stroke:#333;stroke-width:1}
.bldg path{stroke:#1b1b1b;stroke-width:1;fill-rule:evenodd;cursor:pointer}.bldg path:hover,.bldg path.hi{stroke:#e3007a;stroke-width:2.5}
.bldg text{font-size:10px;fill:#111;paint-order:stroke;stroke:#fff;stroke-width:3px;pointer-events:none}
table.sortable th{cursor:pointer;user-select:none}table.sortable th:after{content:" \\2195";color:#aab}
table.sortable th.asc:after{content:" \\2191";color:#333}table.sortable th.desc:after{content:" \\2193";color:#333}
table.buildings{width:100%}table.buildings td{white-space:nowrap}tr.hi td{background:#ffe8f4}td.bad{color:#b00020}td.fallback{color:#b35900}.na{color:#9aa3ad}
footer{margin-top:2.5em;font-size:.8em;color:var(--muted)}
"""

SCRIPT = """
document.querySelectorAll('table.sortable').forEach(function(t){
  t.querySelectorAll('th').forEach(function(th,i){th.addEventListener('click',function(){
    var asc=!th.classList.contains('asc');t.querySelectorAll('th').forEach(function(h){h.classList.remove('asc','desc')});
    th.classList.add(asc?'asc':'desc');var body=t.tBodies[0],rows=Array.from(body.rows);
    rows.sort(function(a,b){var x=a.cells[i].dataset.v,y=b.cells[i].dataset.v;
      var nx=parseFloat(x),ny=parseFloat(y),c;
      if(x===''||x===undefined){return 1}if(y===''||y===undefined){return -1}
      c=(!isNaN(nx)&&!isNaN(ny))?nx-ny:x.localeCompare(y);return asc?c:-c});
    rows.forEach(function(r){body.appendChild(r)})})})});
function hi(id,on){document.querySelectorAll('[data-b="'+id+'"]').forEach(function(e){e.classList.toggle('hi',on)})}
document.querySelectorAll('[data-b]').forEach(function(e){var id=e.dataset.b;
  e.addEventListener('mouseenter',function(){hi(id,true)});e.addEventListener('mouseleave',function(){hi(id,false)});
  if(e.tagName==='path'){e.addEventListener('click',function(){var r=document.getElementById('row-'+id);
    if(r){r.scrollIntoView({block:'center'})}})}});
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
    buildings = _building_rows(out_dir)
    # the maps (hillshades and PNG encoding, in numpy and OpenCV, which let go of the
    # GIL) are drawn side by side: most of the report's time on a large area
    with ThreadPoolExecutor(FIGURE_THREADS) as pool:
        surfaces = [pool.submit(_surface_figure, out_dir, run, *spec) for spec in SURFACES]
        ortho = pool.submit(_ortho_section, out_dir, run, report.get("ortho"), report.get("textures"))
        buildings_map = pool.submit(_buildings_section, out_dir, run, report, buildings)
    sections = [
        ("warnings", "Warnings and notes", _warnings_section(run, report)),
        ("accuracy", "Accuracy", _accuracy_section(report.get("accuracy", []))),
        ("ground", "Ground filter", _ground_section(report.get("ground_filter"))),
        ("detection", "Building detection", _detection_section(report)),
        ("stereo", "Stereo", _stereo_section(run.get("chosen", {}).get("stereo"))),
        ("surfaces", "Surfaces", "".join(f.result() for f in surfaces)),
        ("ortho", "Orthophoto and image check", ortho.result()),
        ("buildings", "Buildings", buildings_map.result()),
        ("changes", "Changes", _changes_section(report.get("changes"))),
        ("timings", "Timings", _timings_section(run)),
        ("parameters", "Parameters", _parameters_section(run)),
    ]
    sections = [(key, title, body) for key, title, body in sections if body]
    nav = "".join(f'<a href="#{key}">{title}</a>' for key, title, _ in sections)
    body = "".join(f'<section id="{key}"><h2>{title}</h2>{content}</section>' for key, title, content in sections)
    page = (
        "<!DOCTYPE html><html lang=en><head><meta charset=utf-8>"
        f"<title>recon3d report: {html.escape(Path(run['inputs'].get('input', '')).name)}</title>"
        f"<style>{STYLE}</style></head><body>{maps.DEFS}<main>{_header(run, report, buildings)}<nav>{nav}</nav>{body}"
        f"{_footer(run)}</main><script>{SCRIPT}</script></body></html>"
    )
    path = out_dir / "report.html"
    with atomic_path(path) as tmp:
        tmp.write_text(page, encoding="utf-8")
    return path


# --------------------------------------------------------------------------- numbers


def _finite(v) -> bool:
    return isinstance(v, int | float) and not isinstance(v, bool) and math.isfinite(v)


def fmt_m(v, unit: str = "") -> str:
    """A length in metres to the centimetre ("n/a" for None or NaN)."""
    return f"{v:.2f}{unit}" if _finite(v) else NA


def fmt_pct(v) -> str:
    """A percentage to 0.1 ("n/a" for None or NaN)."""
    return f"{v:.1f}" if _finite(v) else NA


def _fmt_int(v) -> str:
    return f"{int(v):,}" if _finite(v) else NA


def _fmt_num(v) -> str:
    """A parameter as people write it: 4 significant digits, integers as integers."""
    if isinstance(v, bool) or not _finite(v):
        return html.escape(str(v))
    if float(v).is_integer() and abs(v) < 1e15:
        return f"{int(v):,}"
    return f"{v:.4g}"


def _td(text: str, value=None, cls: str = "") -> str:
    """A table cell; ``value`` (number or text) is what the table sorts on."""
    v = "" if value is None or (isinstance(value, float) and not math.isfinite(value)) else html.escape(str(value))
    if text == NA:
        cls = (cls + " na").strip()
    c = f' class="{cls}"' if cls else ""
    return f'<td{c} data-v="{v}">{text}</td>'


def _table(head: list[str], rows: list[str], *, cls: str = "", left: int | set[int] = 1) -> str:
    """A table; ``left`` is the number of leading left-aligned columns, or their indices."""
    left = set(range(left)) if isinstance(left, int) else left
    ths = "".join(f'<th{" class=l" if i in left else ""}>{h}</th>' for i, h in enumerate(head))
    c = f' class="{cls}"' if cls else ""
    return f"<table{c}><thead><tr>{ths}</tr></thead><tbody>{''.join(rows)}</tbody></table>"


def _kv(rows: list[tuple[str, str]]) -> str:
    return "<table class=kv><tbody>" + "".join(f"<tr><th>{k}</th><td>{v}</td></tr>" for k, v in rows) + "</tbody></table>"


# --------------------------------------------------------------------------- header, warnings


#: The accuracy rows (product, reference) the report's header shows as cards, and their labels.
CARDS = {
    ("model DSM", "measured DSM on roofs"): "model RMS on roofs",
    ("model DSM", "matched DSM on roofs"): "model vs matched DSM on roofs",
    ("DTM", "provider ground points"): "DTM RMS, provider ground",
}


def _header(run: dict, report: dict, buildings: list[dict]) -> str:
    inputs = run.get("inputs", {})
    chosen = run.get("chosen", {})
    cell = chosen.get("dsm.resolution", {}).get("value")
    crs = inputs.get("crs") or "?"
    units = inputs.get("units", {}).get("horizontal", "")
    facts = [inputs.get("kind", ""), f"{_fmt_int(inputs.get('points'))} points", f"CRS {crs}" + (f" ({units})" if units else "")]
    if chosen.get("reference_date", {}).get("value"):
        facts.append(f"reference date {chosen['reference_date']['value']}")
    meta = " · ".join(html.escape(str(x)) for x in facts)
    source = " + ".join(html.escape(str(p)) for p in (inputs.get("input", ""), inputs.get("second_image")) if p)
    count = _building_count(report.get("buildings", {}), buildings)
    cards = [(count["buildings"], "buildings"), (count["with_solid"], "with a solid"),
             (fmt_m(cell, " m") if cell else NA, "DSM cell"),
             (len(run.get("warnings", [])), "warnings")]
    for row in report.get("accuracy", []):
        label = CARDS.get((row.get("product"), row.get("reference")))
        if label:
            cards.append((fmt_m(row.get("rms"), " m"), label))
    card_html = "".join(f"<div class=\"card{' alert' if label == 'warnings' and v else ''}\"><b>{v}</b><span>{label}</span></div>"
                        for v, label in cards)
    return (f"<h1>recon3d report</h1><div class=meta><b>{source}</b><br>{meta}</div>"
            f"<div class=cards>{card_html}</div>")


def _warnings_section(run: dict, report: dict) -> str:
    """Every warning and note of run.json (and of report.json, once), at the top."""
    warnings = list(dict.fromkeys(list(run.get("warnings") or []) + list(report.get("warnings") or [])))
    notes = list(dict.fromkeys(run.get("notes") or []))
    if not warnings and not notes:
        return "<p class=ok id=no-warnings>No warnings and no notes: every check of the run passed.</p>"
    items = [f'<li class=warning><span class=tag>warning</span>{html.escape(w)}</li>' for w in warnings]
    items += [f'<li class=note><span class="tag note">note</span>{html.escape(n)}</li>' for n in notes]
    return f"<div class=warn><ul id=warning-list>{''.join(items)}</ul></div>"


# --------------------------------------------------------------------------- accuracy


def _accuracy_section(rows: list[dict]) -> str:
    if not rows:
        return "<p>No reference was given (check points, provider classes or a reference DSM).</p>"
    head = ["product", "reference", "n", "mean", "std", "RMS", "max |error|", "NMAD", "≤ 1 m %", "≤ 2 m %",
            "errors −3 … +3 m"]
    body = []
    for r in rows:
        cells = [_td(html.escape(r["product"]), r["product"], "l"), _td(html.escape(r["reference"]), r["reference"], "l"),
                 _td(_fmt_int(r.get("n")), r.get("n"))]
        cells += [_td(fmt_m(r.get(k)), r.get(k)) for k in ("mean", "std", "rms", "max_abs", "nmad")]
        cells += [_td(fmt_pct(r.get(k)), r.get(k)) for k in ("within_1m", "within_2m")]
        cells.append(f"<td>{_histogram_svg(r.get('histogram'))}</td>")
        body.append("<tr class=acc>" + "".join(cells) + "</tr>")
    matched = any(r["reference"].startswith("matched DSM") for r in rows)
    caveat = (" The matched DSM is itself reconstructed from the images, with errors of its own (outlines wider than the "
              "buildings put roofs over its ground; occlusions fill it low): its rows say how well the model fits it, "
              "not how close either is to the ground; the check points are that measure.") if matched else ""
    return (_table(head, body, cls="accuracy", left=2)
            + "<p class=small>Errors in metres (product minus reference). NMAD: the median absolute deviation scaled to a standard deviation "
            f"(robust to outliers). The histogram's red line is zero.{html.escape(caveat)}</p>")


def _histogram_svg(hist: dict | None, width: int = 160, height: int = 34) -> str:
    if not hist or not sum(hist["counts"]):
        return ""
    counts = np.asarray(hist["counts"], dtype=float)
    w = width / len(counts)
    bars = "".join(
        f'<rect x="{i * w:.1f}" y="{height - h:.1f}" width="{max(w - 1, .5):.1f}" height="{h:.1f}" fill="#4a7ebb"/>'
        for i, h in enumerate(counts / counts.max() * height)
    )
    mid = f'<line x1="{width / 2}" y1="0" x2="{width / 2}" y2="{height}" stroke="#c00" stroke-width="1"/>'
    return f'<svg width="{width}" height="{height}" role="img" aria-label="error histogram">{bars}{mid}</svg>'


def _ground_section(g: dict | None) -> str:
    if not g or not g.get("n"):
        return ""
    # kappa and Type II need objects (classes 3-6) in the provider's classes
    no_objects = g.get("reference_objects") == 0 or (
        "reference_objects" not in g and g.get("type_ii_percent") == 0 and g.get("kappa") == 0)
    type_ii = NA if no_objects else fmt_pct(g.get("type_ii_percent"))
    kappa = NA if no_objects else (f"{g['kappa']:.3f}" if _finite(g.get("kappa")) else NA)
    rows = [("points scored", _fmt_int(g["n"])), ("share of the cloud scored %", fmt_pct(g.get("scored_share_percent"))),
            ("Type I % (ground rejected)", fmt_pct(g.get("type_i_percent"))),
            ("Type II % (objects accepted as ground)", type_ii),
            ("total error %", fmt_pct(g.get("total_percent"))), ("Cohen's kappa", kappa)]
    note = ("<p class=small>Against the provider's classes: ground (2) versus vegetation and buildings (3–6); "
            "unclassified points are left out.")
    if no_objects:
        note += " The provider's classes hold no vegetation or building, so Type II and kappa do not apply."
    return _kv(rows) + note + "</p>"


def _detection_section(report: dict) -> str:
    """The building detection scores against the provider's building class, when it had one."""
    a, p = report.get("buildings_vs_provider_area"), report.get("buildings_vs_provider")
    if not a and not p:
        return ""
    out = []
    if a:
        out.append("<h3>Against the provider's building points, by area and by building</h3>")
        head = ["measure", "completeness %", "correctness %", "quality %"]
        rows = [
            "<tr><td class=l>area (cells of " + fmt_m(a.get("cell"), " m") + ")</td>"
            + "".join(_td(fmt_pct(a.get(k)), a.get(k)) for k in ("completeness", "correctness", "quality")) + "</tr>",
            "<tr><td class=l>buildings (objects)</td>"
            + "".join(_td(fmt_pct(a.get(k)), a.get(k))
                      for k in ("object_completeness", "object_correctness", "object_quality")) + "</tr>",
        ]
        out.append(_table(head, rows, cls="detection"))
        out.append(_kv([
            ("reference buildings / detected", f"{_fmt_int(a.get('n_reference'))} / {_fmt_int(a.get('n_detected'))}"),
            ("reference found / detected correct", f"{_fmt_int(a.get('n_found'))} / {_fmt_int(a.get('n_correct'))}"),
            ("reference area / detected / overlap (m²)",
             " / ".join(_fmt_area(a.get(k)) for k in ("reference_area", "detected_area", "overlap_area"))),
            ("outline distance RMS / mean / max (m)",
             " / ".join(fmt_m(a.get(k)) for k in ("outline_rms", "outline_mean", "outline_max"))),
            ("outline samples far off %", fmt_pct(a.get("outline_far_percent"))),
            ("vegetation points labelled building %", fmt_pct(a.get("vegetation_as_building_percent"))),
        ]))
    if p:
        out.append("<h3>Against the provider's building points, point by point</h3>")
        out.append(_kv([("provider building points", _fmt_int(p.get("reference_building_points"))),
                        ("completeness %", fmt_pct(p.get("completeness_percent"))),
                        ("correctness %", fmt_pct(p.get("correctness_percent")))]))
    out.append("<p class=small>Completeness: share of the reference found; correctness: share of the detection that "
               "is right; quality: overlap over union.</p>")
    return "".join(out)


def _fmt_area(v) -> str:
    return f"{v:,.1f}" if _finite(v) else NA


# --------------------------------------------------------------------------- stereo


def _stereo_section(stereo: dict | None) -> str:
    """Frame stereo: the candidate and matched pairs and their self-check; satellite: its tiles."""
    if not stereo:
        return ""
    if "tiles" in stereo:
        return _satellite_section(stereo)
    out = []
    candidates = stereo.get("candidates") or []
    if candidates:
        rows = [f"<tr>{_td(html.escape(c['pair']), c['pair'], 'l')}{_td(fmt_m(c.get('base_to_height')), c.get('base_to_height'))}"
                f"{_td(fmt_pct(100 * c['overlap']) if _finite(c.get('overlap')) else NA, c.get('overlap'))}"
                f"{_td(_fmt_int(c.get('common_points')), c.get('common_points'))}"
                f"{_td('yes' if c.get('used') else 'no', int(bool(c.get('used'))))}</tr>" for c in candidates]
        out.append("<h3>Image pairs considered</h3>"
                   + _table(["pair", "base / height", "overlap %", "common sparse points", "matched"], rows))
    pairs = stereo.get("pairs") or []
    if pairs:
        rows = []
        for p in pairs:
            c, vp = p.get("self_check") or {}, p.get("vertical_parallax_px") or {}
            span = (p.get("matching") or {}).get("disparity_range_searched", p.get("disparity_range", {})).get("value")
            rows.append(
                "<tr class=pair>" + _td(html.escape(p["pair"]), p["pair"], "l")
                + _td(html.escape(str((p.get("matching") or {}).get("engine", NA))), None, "l")
                + _td(f"{span[0]} … {span[1]}" if span else NA)
                + _td(fmt_m(vp.get("median")), vp.get("median")) + _td(fmt_m(vp.get("p90")), vp.get("p90"))
                + _td(fmt_pct(p.get("matched_percent")), p.get("matched_percent"))
                + _td(fmt_pct(c.get("coverage_percent")), c.get("coverage_percent"))
                + _td(fmt_m(c.get("discrepancy_m")), c.get("discrepancy_m"))
                + _td(fmt_m(c.get("discrepancy_p90_m")), c.get("discrepancy_p90_m"))
                + _td(fmt_m(c.get("discrepancy_gsd")), c.get("discrepancy_gsd"))
                + _td(fmt_m(c.get("reprojection_px")), c.get("reprojection_px"))
                + _td(fmt_pct(p.get("fused_share_percent")), p.get("fused_share_percent")) + "</tr>")
        head = ["pair", "matcher", "disparities searched (px)", "vertical parallax median (px)", "p90 (px)",
                "matched % of overlap", "sparse points covered %", "distance to sparse points median (m)",
                "p90 (m)", "median in GSD", "reprojection p95 (px)", "share of the cloud %"]
        out.append("<h3>Matched pairs and their self-check</h3>" + _table(head, rows))
    gsd = stereo.get("ground_sample_distance")
    facts = [("pairs matched", _fmt_int(stereo.get("pair_count", len(pairs)))),
             ("ground sample distance (m)", fmt_m(gsd)), ("points in the fused cloud", _fmt_int(stereo.get("points")))]
    area = stereo.get("common_area")
    if area:
        facts += [("area both images of a pair see (m²)", _fmt_area(area.get("area_m2"))),
                  ("of it filled in the DSM %", fmt_pct(area.get("filled_percent"))),
                  ("of it matched (not filled in) %", fmt_pct(area.get("observed_percent"))),
                  ("of it hidden from one image (estimated on the DSM) %", fmt_pct(area.get("hidden_percent"))),
                  ("matched of what both images see %", fmt_pct(area.get("matched_of_visible_percent")))]
    out.append(_kv(facts))
    out.append("<p class=small>Self-check: the dense result against the pair's own sparse points (those both images "
               "observe): covered share, height distance, and reprojection into both original images.</p>")
    return "".join(out)


def _satellite_section(stereo: dict) -> str:
    """Satellite pair: the tie points, each tile's searched heights and why, bias, share matched, or why it failed."""
    tiles = stereo["tiles"]
    head = ["tile", "core (px)", "heights searched (m)", "from", "bias (px)", "vertical parallax median (px)",
            "matched % of overlap", "points", "status"]
    rows = []
    for t in tiles.get("per_tile", []):
        lo, hi = t["search_heights_m"]
        vp = (t.get("vertical_parallax_px") or {}).get("median")
        rows.append("<tr class=tile>" + _td(html.escape(str(t["tile"])), str(t["tile"]), "l")
                    + _td(html.escape(_short(t.get("core"))), None, "l") + _td(f"{lo:.1f} … {hi:.1f}", lo)
                    + _td(html.escape(str(t.get("search_from", NA))), None, "l")
                    + _td(html.escape(", ".join(fmt_m(v) for v in t.get("bias_px") or []) or NA), None)
                    + _td(fmt_m(vp), vp) + _td(fmt_pct(t.get("matched_percent")), t.get("matched_percent"))
                    + _td(_fmt_int(t.get("points")), t.get("points")) + _td("matched", "matched", "l") + "</tr>")
    for f in tiles.get("failures", []):
        rows.append(f"<tr class=failed>{_td(html.escape(str(f['tile'])), str(f['tile']), 'l')}"
                    f"{_td(html.escape(_short(f.get('core'))), None, 'l')}"
                    f"<td class='l bad' colspan=7>failed: {html.escape(str(f.get('reason', '')))}</td></tr>")
    ties = stereo.get("tie_points") or {}
    check = stereo.get("self_check") or {}
    vp = stereo.get("vertical_parallax_px") or {}
    heights = stereo.get("tie_heights_m")
    facts = [
        ("SIFT tie points / on their epipolar curves",
         f"{_fmt_int(ties.get('sift_matches'))} / {_fmt_int(ties.get('on_epipolar_curves'))} "
         f"(within {_fmt_num(ties.get('epipolar_tolerance_px', NA))} px)"),
        ("tie point heights (m)", f"{heights[0]:.1f} … {heights[1]:.1f}" if heights else NA),
        ("vertical parallax median / p90 (px)", f"{fmt_m(vp.get('median'))} / {fmt_m(vp.get('p90'))}"),
        ("affine camera residual (px)", fmt_m(stereo.get("affine_residual_px"))),
        ("overlap matched %", fmt_pct(stereo.get("matched_percent"))),
        ("tiles matched / failed", f"{len(tiles.get('per_tile', []))} / {len(tiles.get('failures', []))}"),
    ]
    if check.get("tie_points"):
        facts += [("self-check: tie points", _fmt_int(check["tie_points"])),
                  ("self-check: dense minus SIFT disparity, median (px / m)",
                   f"{fmt_m(check.get('median_px'))} / {fmt_m(check.get('median_m'))}"),
                  ("self-check: within 1 px %", fmt_pct(check.get("within_1px_percent")))]
    return (f"<h3>Satellite pair</h3>{_kv(facts)}<h3>Tiles</h3>{_table(head, rows, cls='tiles')}"
            "<p class=small>The unmatched rest of the overlap is filled in for the DSM only: no DTM and no building "
            "comes from it.</p>")


def _short(v) -> str:
    if isinstance(v, list | tuple):
        return ", ".join(_short(x) for x in v)
    return _fmt_num(v) if _finite(v) else str(v if v is not None else NA)


# --------------------------------------------------------------------------- maps


def _crs_label(run: dict) -> str:
    inputs = run.get("inputs", {})
    unit = inputs.get("units", {}).get("horizontal", "metre")
    return f"{inputs.get('crs') or '?'}, {'m' if unit == 'metre' else unit}"


def _metres_per_unit(run: dict) -> tuple[float, float]:
    u = run.get("inputs", {}).get("units", {})
    return float(u.get("metres_per_unit") or 1.0), float(u.get("vertical_metres_per_unit") or 1.0)


def _raster_figure(path: Path, run: dict, title: str, cmap: str, caption: str, *, from_zero: bool = False) -> str:
    """A map of a height raster, tinted over its 1-99 % range, or from 0 to its 99.5 %
    height (at least 1 m) with ``from_zero``."""
    r = read_raster(path, max_side=2 * maps.MAP_SIZE)  # twice the display size: sharp on high-DPI screens
    h_unit, v_unit = _metres_per_unit(run)
    z = r.data.astype(float) * v_unit  # heights shown in metres
    if not np.isfinite(z).any():
        return f"<p class=small>{title}: no data.</p>"
    if from_zero:
        lo, hi = 0.0, max(float(np.nanpercentile(z, 99.5)), 1.0)
    else:
        lo, hi = tuple(np.nanpercentile(z, [1, 99]))
    bounds = _bounds(r)
    frame = maps.MapFrame.fit(bounds)
    rgba = maps.shaded_relief(z, r.resolution * h_unit, lo, hi, cmap, maps.resample_factor(z.shape, frame))
    legend = maps.colour_bar(frame, lo, hi, cmap, title, key=path.stem)
    return maps.figure_html(maps.png_uri(rgba), f"{title} map", frame, bounds, key=path.stem, crs_label=_crs_label(run),
                            metres_per_unit=h_unit, legend=legend, caption=caption)


def _bounds(r) -> tuple[float, float, float, float]:
    t = r.transform
    rows, cols = r.data.shape
    xs, ys = (t.c, t.c + t.a * cols), (t.f, t.f + t.e * rows)
    return min(xs), min(ys), max(xs), max(ys)


#: The surface maps: product, colour bar title, colour ramp, caption.
SURFACES = (
    ("dsm", "DSM height (m)", "terrain", "DSM: the highest surface (roofs, trees, ground). "),
    ("dtm", "DTM height (m)", "terrain", "DTM: the bare ground. "),
    ("ndsm", "height above ground (m)", "height", "nDSM: DSM minus DTM. "),
)

#: Maps drawn at once. Each holds about ten float64 copies of its raster while drawn,
#: read at most twice the display size (2 MAP_SIZE cells a side, up to 240 MB).
FIGURE_THREADS = 2


def _surface_figure(out_dir: Path, run: dict, name: str, title: str, cmap: str, caption: str) -> str:
    """One surface map: DSM and DTM tinted over their own 1-99 % height range, nDSM from 0."""
    note = f"Hillshade from the north-west, tinted by height; {maps.NODATA_NOTE}."
    path = out_dir / f"{name}.tif"
    if not path.exists():
        return ""
    return (f"<h3>{name.upper() if name != 'ndsm' else 'nDSM'}</h3>"
            + _raster_figure(path, run, title, cmap, caption + note, from_zero=cmap == "height"))


def _ortho_section(out_dir: Path, run: dict, o: dict | None, textures: dict | None = None) -> str:
    """Stereo runs: the true orthophoto, the image-difference map and its doubtful areas,
    and what buildings_textured.glb took from the images."""
    import cv2
    import rasterio

    path = out_dir / "ortho.tif"
    if o is None or not path.exists():
        return ""
    with rasterio.open(path) as src:
        image = src.read()
        bounds = tuple(src.bounds)
    frame = maps.MapFrame.fit(bounds)
    size = (max(frame.width * 2, 1), max(frame.height * 2, 1))  # twice the display size: sharp on high-DPI screens
    if image.dtype == np.uint8:
        rgba = np.moveaxis(image, 0, -1)
    else:  # panchromatic float: stretched over its 1-99 % range for display
        grey = image[0]
        lo, hi = np.nanpercentile(grey, [1, 99]) if np.isfinite(grey).any() else (0.0, 1.0)
        g = np.clip((np.nan_to_num(grey, nan=lo) - lo) / max(hi - lo, 1e-9) * 255, 0, 255).astype(np.uint8)
        rgba = np.dstack([g, g, g, np.where(np.isfinite(grey), 255, 0).astype(np.uint8)])
    rgba = cv2.resize(np.ascontiguousarray(rgba), size, interpolation=cv2.INTER_AREA)
    h_unit, _ = _metres_per_unit(run)
    figures = [maps.figure_html(maps.png_uri(rgba), "orthophoto", frame, bounds, key="ortho", crs_label=_crs_label(run),
                                metres_per_unit=h_unit, legend="",
                                caption=f"True orthophoto on the {html.escape(o['surface'])}, {fmt_m(o['cell'])} cells: "
                                        f"{fmt_pct(o['seen_percent'])} % of the grid seen by an image; "
                                        "transparent where no image sees the ground.")]
    diff_path = out_dir / "ortho_diff.tif"
    if diff_path.exists():
        d = read_raster(diff_path)
        dframe = maps.MapFrame.fit(_bounds(d))
        factor = maps.resample_factor(d.data.shape, dframe)
        shown = cv2.resize(np.nan_to_num(d.data, nan=0.0), (max(round(d.data.shape[1] * factor), 1),
                           max(round(d.data.shape[0] * factor), 1)), interpolation=cv2.INTER_NEAREST)
        known = cv2.resize(np.isfinite(d.data).astype(np.uint8), shown.shape[::-1], interpolation=cv2.INTER_NEAREST)
        rgba = np.dstack([maps.colorize(shown, 0.0, 1.2, "height"), np.where(known > 0, 255, 0).astype(np.uint8)])
        legend = maps.colour_bar(dframe, 0.0, 1.2, "height", "1 - NCC", key="ortho_diff")
        figures.append(maps.figure_html(
            maps.png_uri(rgba), "image difference", dframe, _bounds(d), key="ortho_diff", crs_label=_crs_label(run),
            metres_per_unit=h_unit, legend=legend,
            caption=f"How much the two images of each pair disagree once orthorectified on the DSM (1 - NCC): "
                    f"where the DSM is right they agree. Judged on {fmt_pct(o['judged_percent'])} % of the cells "
                    f"(the rest has no texture to compare, or one image does not see it); "
                    f"{fmt_pct(o['doubtful_percent_of_judged'])} % of those are doubtful (above {o['threshold']:g})."))
    rows = [_doubtful_row(r) for r in o.get("regions", [])[:20]]
    table = (_table(["area", "centre (x, y)", "mean 1 - NCC", "buildings touched"], rows, left={1, 3})
             if rows else "<p class=small>No doubtful area.</p>")
    return "".join(figures) + "<h3>Doubtful areas</h3>" + table + _textures_html(textures)


def _textures_html(t: dict | None) -> str:
    """One paragraph on the textured model: which images, how many walls."""
    if not t:
        return ""
    images = ", ".join(f"{html.escape(x['name'])} ({x['size'][0]} x {x['size'][1]} px"
                       + (f", reduced {x['reduced']} x" if x["reduced"] > 1 else "") + ")" for x in t["textures"])
    return (f"<h3>Textured model</h3><p class=small>buildings_textured.glb: roofs from the orthophoto, "
            f"{t['wall_surfaces_textured'] - t['wall_surfaces_from_ortho']} of {t['wall_surfaces']} walls from the "
            f"image that sees each best, {t['wall_surfaces_from_ortho']} low steps between roof parts from the "
            f"orthophoto, the others plain. Textures: {images or 'none'}.</p>")


def _doubtful_row(region: dict) -> str:
    x, y = region["centre"]
    area, mean = region["area"], region["mean"]
    touched = html.escape(", ".join(region["buildings"])) or "none"
    return f"<tr>{_td(_fmt_area(area), area)}{_td(f'{x:.1f}, {y:.1f}')}{_td(f'{mean:.2f}', mean)}{_td(touched)}</tr>"


# --------------------------------------------------------------------------- buildings


def _building_rows(out_dir: Path) -> list[dict]:
    """One dict per building: the footprint's properties, its rings and its CityJSON object."""
    path = out_dir / "footprints.geojson"
    if not path.exists():
        return []
    features = json.loads(path.read_text(encoding="utf-8")).get("features", [])
    parents, lods = _cityjson_links(out_dir / "buildings.city.json")
    rows = []
    for f in features:
        geom = f.get("geometry") or {}
        polygons = geom.get("coordinates", []) if geom.get("type") == "MultiPolygon" else [geom.get("coordinates", [])]
        p = dict(f.get("properties") or {})
        p["rings"] = [np.asarray(ring, float)[:, :2] for poly in polygons for ring in poly if len(ring) >= 3]
        p["parent"] = parents.get(p.get("id"))
        p["lods"] = lods.get(p.get("id")) or ([p["lod"]] if p.get("lod") else [])
        rows.append(p)
    return rows


def _cityjson_links(path: Path) -> tuple[dict, dict]:
    """(BuildingPart id -> its Building id, object id -> its LoDs) from the CityJSON, if there."""
    if not path.exists():
        return {}, {}
    objects = json.loads(path.read_text(encoding="utf-8")).get("CityObjects", {})
    parents = {k: o["parents"][0] for k, o in objects.items() if o.get("type") == "BuildingPart" and o.get("parents")}
    lods = {k: sorted({str(g.get("lod")) for g in o.get("geometry", [])}, key=float) for k, o in objects.items()}
    return parents, lods


def _building_count(summary: dict, rows: list[dict]) -> dict:
    """The one building count: footprints, each with its own solid or reason; the CityJSON
    holds a block of them as one Building with BuildingParts."""
    n = summary.get("count", len(rows))
    parts = sum(r.get("parent") is not None for r in rows)
    blocks = len({r["parent"] for r in rows if r.get("parent")}) or summary.get("blocks", 0)
    with_solid = summary.get("with_solid", sum(r.get("status") != "no_solid" and bool(r.get("lod")) for r in rows))
    return {"buildings": n, "with_solid": with_solid, "parts": parts, "blocks": blocks,
            "cityjson_buildings": n - parts + blocks}


def _buildings_section(out_dir: Path, run: dict, report: dict, rows: list[dict]) -> str:
    summary = report.get("buildings", {})
    c = _building_count(summary, rows)
    definition = (f"<p id=building-count><b>{c['buildings']} buildings</b>, one per footprint: "
                  f"{c['with_solid']} with a solid, {c['buildings'] - c['with_solid']} without. "
                  f"In buildings.city.json they are <b>{c['cityjson_buildings']} Building</b> objects and "
                  f"<b>{c['parts']} BuildingPart</b> objects: ")
    if c["parts"]:
        definition += (f"{c['buildings'] - c['parts']} stand alone, and {c['parts']} adjoining buildings of different "
                       f"heights form {c['blocks']} block(s), each a Building holding them as BuildingParts.</p>")
    else:
        definition += "every building stands alone.</p>"
    facts = [(f"status {html.escape(k)}", _fmt_int(v)) for k, v in summary.get("statuses", {}).items()]
    facts += [(f"LoD {html.escape(k)}", _fmt_int(v)) for k, v in summary.get("lods", {}).items()]
    facts += [(f"reason {html.escape(k)}", _fmt_int(v)) for k, v in summary.get("reasons", {}).items()]
    if c["blocks"]:
        facts.append(("blocks of BuildingParts", _fmt_int(c["blocks"])))
    return (definition + _kv(facts) + _building_map(out_dir, run, rows) + "<h3>Every building</h3>"
            + _building_table(rows))


def _building_map(out_dir: Path, run: dict, rows: list[dict]) -> str:
    dsm_path = out_dir / "dsm.tif"
    if not rows or not dsm_path.exists():
        return ""
    r = read_raster(dsm_path, max_side=2 * maps.MAP_SIZE)
    h_unit, v_unit = _metres_per_unit(run)
    bounds = _bounds(r)
    frame = maps.MapFrame.fit(bounds)
    z = r.data.astype(float) * v_unit
    base = maps.shaded_relief(z, r.resolution * h_unit, 0, 1, None, maps.resample_factor(z.shape, frame))
    heights = [b.get("height_m") for b in rows if _finite(b.get("height_m"))]
    top = max(nice_ceiling(max(heights)) if heights else 10.0, 1.0)
    shapes, labels = [], []
    for b in rows:
        if not b["rings"]:
            continue
        d = " ".join("M" + " L".join(f"{x:.1f} {y:.1f}" for x, y in zip(*frame.px(ring[:, 0], ring[:, 1]), strict=True))
                     + " Z" for ring in b["rings"])
        h = b.get("height_m")
        solid = b.get("status") != "no_solid" and bool(b.get("lod"))
        if solid and _finite(h):
            fill = "rgb({},{},{})".format(*maps.colorize(np.array(h), 0.0, top, "height"))
        else:
            fill = "url(#hatch)"
        dash = ' stroke-dasharray="5 3" style="stroke:#d35400"' if b.get("status") == "fallback" else ""
        tip = (f"{b.get('id')}: {b.get('status')}{' (' + b['reason'] + ')' if b.get('reason') else ''}, "
               f"LoD {', '.join(b['lods']) or NA}, height {fmt_m(h, ' m')}, roof RMS {fmt_m(b.get('roof_rms_m'), ' m')}")
        bid = html.escape(str(b.get("id")))
        shapes.append(f'<path data-b="{bid}" d="{d}" fill="{fill}" fill-opacity=".82"{dash}><title>{html.escape(tip)}</title></path>')
        if len(rows) <= 80:
            outer = b["rings"][0]
            px, py = frame.px(*_label_point(outer))
            labels.append(f'<text x="{px:.1f}" y="{py + 3:.1f}" text-anchor=middle>{bid}</text>')
    legend = maps.colour_bar(frame, 0.0, top, "height", "building height (m)", key="bldg", nodata=False)
    y = 20 + min(frame.height - 70, 260) + 16
    x = frame.width + 18
    legend += (f'<path d="M{x} {y} h16 v12 h-16 Z" fill="none" stroke="#d35400" stroke-dasharray="5 3" stroke-width="1.4"/>'
               f'<text class=tl x="{x + 22}" y="{y + 10}">fallback</text>'
               f'<rect x="{x}" y="{y + 20}" width="16" height="12" fill="url(#hatch)" stroke="#1b1b1b"/>'
               f'<text class=tl x="{x + 22}" y="{y + 30}">no solid</text>')
    overlay = f'<g class=bldg>{"".join(shapes)}{"".join(labels)}</g>'
    caption = ("Footprints over the DSM hillshade, coloured by building height (roof top above ground); courtyards are "
               "holes. Dashed orange: LoD1.3 fallback; hatched: no solid. Hover a building for its figures, click it "
               "to find its row in the table.")
    return maps.figure_html(maps.png_uri(base), "buildings map", frame, bounds, key="bldg", crs_label=_crs_label(run),
                            metres_per_unit=h_unit, legend=legend, overlay=overlay, caption=caption)


def nice_ceiling(v: float) -> float:
    """The next 1, 2 or 5 x 10^k step at or above ``v`` (a colour bar's top)."""
    step = maps.nice_step(v, 5)
    return float(np.ceil(v / step) * step)


def _label_point(ring: np.ndarray) -> tuple[float, float]:
    """A point inside the ring for its label (shapely's representative point)."""
    import shapely

    p = shapely.Polygon(ring).representative_point()
    return p.x, p.y


def _building_table(rows: list[dict]) -> str:
    head = ["id", "CityJSON", "LoD", "roof type", "roof planes", "ground z (m)", "roof z (m)", "height (m)",
            "area (m²)", "roof RMS (m)", "status", "fallback reason", "roof points / m²", "points > 1 m off (%)",
            "unmodelled roof parts (m²)", "cells without points (%)", "roof point RMS per LoD (m)", "validity"]
    body = []
    for b in rows:
        bid = str(b.get("id"))
        cityjson = f"BuildingPart of {b['parent']}" if b.get("parent") else "Building"
        status = str(b.get("status") or NA)
        cells = [
            _td(html.escape(bid), bid, "l"), _td(html.escape(cityjson), cityjson, "l"),
            _td(html.escape(", ".join(b["lods"])) or NA, b["lods"][-1] if b["lods"] else None),
            _td(html.escape(str(b.get("roof_type") or NA)), b.get("roof_type") or None, "l"),
            _td(_fmt_int(b.get("roof_planes")), b.get("roof_planes")),
            _td(fmt_m(b.get("ground_z")), b.get("ground_z")), _td(fmt_m(b.get("roof_z")), b.get("roof_z")),
            _td(fmt_m(b.get("height_m")), b.get("height_m")), _td(_fmt_area(b.get("area")), b.get("area")),
            _td(fmt_m(b.get("roof_rms_m")), b.get("roof_rms_m")),
            _td(html.escape(status), status, {"ok": "l", "fallback": "l fallback"}.get(status, "l bad")),
            _td(html.escape(str(b.get("reason") or "")) or "–", b.get("reason") or None, "l"),
            _td(_fmt_density(b.get("roof_points_per_m2")), b.get("roof_points_per_m2")),
            _td(_share_pct(b.get("roof_points_off_1m_share")), b.get("roof_points_off_1m_share")),
            _unmodelled_cell(b),
            _td(_share_pct(b.get("footprint_empty_share")), b.get("footprint_empty_share")),
            _lod_rms_cell(b), _validity_cell(b),
        ]
        body.append(f'<tr id="row-{html.escape(bid)}" data-b="{html.escape(bid)}">{"".join(cells)}</tr>')
    return (_table(head, body, cls="sortable buildings", left={0, 1, 3, 10, 11, 16, 17})
            + "<p class=small>Click a column to sort. Heights: ground z and roof z in the CRS's vertical reference; "
            "height is the roof top above ground. Roof RMS: the model DSM against the measured DSM on the building's "
            "cells. Points more than 1 m off: the building's roof points that far from its best solid (step walls "
            "included); unmodelled roof parts: the groups of its roof points more than 1 m inside the outline and 1 m "
            "above or below its best solid, of 2 m² and more (a dormer, a stair house or a light well the model left "
            "out), their count and area; cells without points: its footprint cells filled from their rim. Roof point RMS per LoD: all "
            "its roof points against each LoD's roof. Validity: val3dity's check of each LoD built or tried.</p>")


def _unmodelled_cell(b: dict) -> str:
    """"2 · 14.5": the count and area of the roof parts the model misses; "0" where none."""
    n, area = b.get("roof_unmodelled_parts"), b.get("roof_unmodelled_area_m2")
    if n is None:
        return _td(NA, None)
    return _td(f"{int(n)} · {_fmt_area(area)}" if n else "0", area)


def _lod_rms_cell(b: dict) -> str:
    """"LoD1 1.20 · LoD2.2 0.08", sorted by the best LoD's figure."""
    from recon3d.quality.roofs import lod_key

    rms = {lod: b.get(f"roof_point_rms_{lod_key(lod)}_m") for lod in ("1", "1.3", "2.2")}
    have = [(lod, v) for lod, v in rms.items() if _finite(v)]
    text = " · ".join(f"LoD{lod} {fmt_m(v)}" for lod, v in have)
    return _td(html.escape(text) or NA, have[-1][1] if have else None, "l")


def _validity_cell(b: dict) -> str:
    """"valid", or each failing LoD with its val3dity codes."""
    from recon3d.quality.roofs import lod_key

    found = [(lod, b[f"validity_{lod_key(lod)}"]) for lod in ("1", "1.3", "2.2") if b.get(f"validity_{lod_key(lod)}")]
    bad = [f"LoD{lod}: {v}" for lod, v in found if v != "valid"]
    text = "; ".join(bad) or ("valid" if found else NA)
    return _td(html.escape(text), text, "l" if not bad else "l bad")


def _fmt_density(v) -> str:
    return f"{v:.1f}" if _finite(v) else NA


def _share_pct(v) -> str:
    """A share in [0, 1] as a percentage to 0.1."""
    return fmt_pct(100.0 * v) if _finite(v) else NA


# --------------------------------------------------------------------------- changes, timings, parameters


def _changes_section(c: dict | None) -> str:
    if not c:
        return ""
    rows = [(html.escape(k), _fmt_num(v) if _finite(v) else html.escape(str(v))) for k, v in c["summary"].items()]
    notes = "".join(f"<li>{html.escape(n)}</li>" for n in c.get("notes", []))
    return f"<h3>Changes against the older building database</h3>{_kv(rows)}<ul class=small>{notes}</ul>"


def _timings_section(run: dict) -> str:
    """Seconds per stage, leaving out the stages that do not apply to the run."""
    inputs = run.get("inputs", {})
    skip = set()
    if str(inputs.get("kind", "")).startswith("point cloud"):
        skip.add("stereo")
    if not inputs.get("old_buildings"):
        skip.add("change")
    t = {k: v for k, v in run.get("timings_s", {}).items() if k not in skip}
    if not t:
        return ""
    total = sum(t.values())
    rows = [f"<tr><td class=l>{html.escape(k)}</td><td>{v:.2f}</td><td class=l>"
            f'<svg width="160" height="10"><rect width="{160 * v / max(total, 1e-9):.1f}" height="10" fill="#4a7ebb"/></svg>'
            "</td></tr>" for k, v in t.items()]
    rows.append(f"<tr><th class=l>total</th><th>{total:.2f}</th><th></th></tr>")
    return _table(["stage", "seconds", "share"], rows, left={0, 2})


def _parameters_section(run: dict) -> str:
    rows = []
    for key, value, unit, reason in _flatten({k: v for k, v in run.get("chosen", {}).items() if k != "stereo"}):
        shown = _short(value) + (f" {html.escape(_unit(unit))}" if unit else "")
        rows.append(f"<tr><td class=l>{html.escape(key)}</td><td>{shown}</td><td class=l>{html.escape(reason)}</td></tr>")
    if not rows:
        return ""
    return (_table(["parameter", "value", "why"], rows, cls="parameters", left={0, 2})
            + "<p class=small>Every setting left unset, chosen from the data (run.json <code>chosen</code>).</p>")


def _unit(unit: str) -> str:
    return {"metre": "m", "metres": "m", "foot": "ft", "US survey foot": "US ft"}.get(unit, unit)


def _flatten(d: dict, prefix: str = ""):
    """(key, value, unit, reason) of each chosen parameter, nested keys joined by dots."""
    for k, v in d.items():
        key = f"{prefix}{k}"
        if isinstance(v, dict) and "value" in v:
            yield key, v["value"], v.get("unit", ""), str(v.get("reason", ""))
        elif isinstance(v, dict):
            yield from _flatten(v, key + ".")
        elif not isinstance(v, list):
            yield key, v, "", ""


def _footer(run: dict) -> str:
    versions = ", ".join(f"{k} {v}" for k, v in run.get("versions", {}).items())
    return (f"<footer>recon3d {html.escape(run.get('recon3d', ''))}; {html.escape(versions)}. "
            "This report is self-contained: it needs no network.</footer>")
