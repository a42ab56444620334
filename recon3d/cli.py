"""The ``recon3d`` command line. Each subcommand is a thin wrapper over one library call.

Only click is imported at start-up: every subcommand imports the stages it runs, so
``recon3d --help`` and ``--version`` start fast (``tests/test_startup.py`` checks that
no heavy library is loaded).
"""

from __future__ import annotations

import logging
import sys
from pathlib import Path

import click

from recon3d import __version__
from recon3d.errors import Recon3dError

log = logging.getLogger("recon3d")


def _configure_logging(verbose: int, quiet: int) -> None:
    level = max(logging.DEBUG, logging.WARNING - 10 * (verbose - quiet))
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(logging.Formatter("%(levelname)s %(name)s: %(message)s"))
    root = logging.getLogger("recon3d")
    root.handlers[:] = [handler]
    root.setLevel(level)


def _count_verbosity(ctx: click.Context, param: click.Parameter, value: int) -> None:
    """``-v`` / ``-q`` before or after the subcommand: the counts add up, logging follows them."""
    obj = ctx.ensure_object(dict)
    obj[param.name] = obj.get(param.name, 0) + value
    _configure_logging(obj.get("verbose", 0), obj.get("quiet", 0))


def _verbosity_params(where: str) -> list[click.Option]:
    """The ``-v`` and ``-q`` options, counted by :func:`_count_verbosity`; ``where`` ends their help."""
    return [
        click.Option(["-v", "--verbose"], count=True, expose_value=False, callback=_count_verbosity,
                     help=f"More messages (-vv for debug){where}."),
        click.Option(["-q", "--quiet"], count=True, expose_value=False, callback=_count_verbosity,
                     help=f"Fewer messages: errors only, no progress bar{where}."),
    ]


class _Command(click.Command):
    """A subcommand taking ``-v`` / ``-q`` too, so ``recon3d run ... -v`` works like ``recon3d -v run ...``."""

    def __init__(self, *args, **kwargs) -> None:
        super().__init__(*args, **kwargs)
        self.params.extend(_verbosity_params(""))


class _Group(click.Group):
    """Turns every recon3d error into one line on stderr and exit status 1."""

    command_class = _Command
    group_class = type  # subgroups (evaluate) are _Groups too

    def invoke(self, ctx):
        try:
            return super().invoke(ctx)
        except Recon3dError as exc:
            click.echo(f"recon3d: error: {exc}", err=True)
            sys.exit(1)


@click.group(cls=_Group, params=_verbosity_params("; also accepted after the subcommand"),
             context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(__version__, prog_name="recon3d")
@click.pass_context
def cli(ctx: click.Context) -> None:
    """recon3d: DSM, DTM and 3D city models from point clouds and stereo imagery, with accuracy reports."""
    ctx.ensure_object(dict)


def _memory_cap(ctx, param, value):
    """``--max-memory``: cap what the memory guards see (this process and its workers)."""
    from recon3d.core.memory import limit_memory, parse_size

    if value is not None:
        try:
            limit_memory(parse_size(value))
        except ValueError as exc:
            raise click.BadParameter(str(exc)) from None
    return value


def _with_old_heights(config, field_name: str | None, reference: str | None):
    """The configuration with the --old-height-* options applied."""
    import dataclasses

    values = {k: v for k, v in (("height_field", field_name), ("height_reference", reference)) if v}
    return dataclasses.replace(config, change=dataclasses.replace(config.change, **values)) if values else config


@cli.command()
@click.argument("input_path", metavar="INPUT...", nargs=-1, required=True, type=click.Path(path_type=Path))
@click.option("-o", "--out", "out_dir", required=True, type=click.Path(path_type=Path), help="Output folder.")
@click.option("--crs", help="CRS of an input without one, e.g. EPSG:7415.")
@click.option("--footprints", type=click.Path(path_type=Path), help="Building outlines (GeoJSON, GeoPackage, Shapefile) to use instead of detection.")
@click.option("--checkpoints", type=click.Path(path_type=Path), help="CSV of reference points: x,y,z[,id][,kind].")
@click.option("--old-buildings", type=click.Path(path_type=Path), help="Older building database (footprints or CityJSON) to detect changes against.")
@click.option("--old-height-field", metavar="NAME", help="Height attribute of --old-buildings when it has none of the usual names (roof_z, height, hauteur, roof_height, h_dak_max...).")
@click.option("--old-height-reference", type=click.Choice(["ground", "absolute"]), help="What the old heights are measured from  [default: known from the usual names, else decided from the data].")
@click.option("--gcps", type=click.Path(path_type=Path), help="Ground control points (CSV x,y,z in the output CRS) for a satellite pair's absolute bias.")
@click.option("--breaklines", type=click.Path(path_type=Path), help="3-D lines (roads, water edges) the DTM must honour.")
@click.option("--altimetry", type=click.Path(path_type=Path), help="Spot heights the DTM must honour (vector file or CSV x,y,z).")
@click.option("--dem", type=click.Path(path_type=Path), help="Elevation model (GeoTIFF: a coarse DEM, SRTM, Copernicus) bounding the heights a stereo scene or satellite pair is matched in.")
@click.option("--config", "config_path", type=click.Path(path_type=Path), help="TOML file of stage settings.")
@click.option("--set", "overrides", multiple=True, metavar="STAGE.KEY=VALUE", help="Override one setting, e.g. --set dsm.resolution=0.5 (repeatable).")
@click.option("--overwrite", is_flag=True, help="Replace OUT if it exists.")
@click.option("--workers", type=click.IntRange(min=1), help="Processes working the tiles and building the solids  [default: the CPUs available, where there is work for them]; the output does not depend on it.")
@click.option("--scheduler", metavar="ADDRESS", help="Run the tiles and the solids on a Dask cluster, e.g. tcp://host:8786 (dask-jobqueue, Kubernetes...); its workers must see the output folder's file system.")
@click.option("--dask", "local_dask", is_flag=True, help="Run the tiles and the solids on a Dask LocalCluster of this machine.")
@click.option("--resume", is_flag=True, help="Take up the work of an earlier run of the same inputs and settings into OUT that was killed or failed (finished tiles are not done again); a run with --resume keeps its work when it fails.")
@click.option("--max-memory", callback=_memory_cap, expose_value=False, metavar="SIZE", help="Memory the run may count on, e.g. 8G or 512M  [default: what the system has free]. Each large allocation (point reads, grids, matching strips, roof grids) is checked against it before it starts; the run stops naming the setting to change.")
@click.pass_context
def run(ctx, input_path, out_dir, crs, footprints, checkpoints, old_buildings, old_height_field, old_height_reference, gcps, breaklines, altimetry, dem, config_path, overwrite, workers, scheduler, local_dask, resume, overrides):
    """Reconstruct INPUT into OUT: a LAS/LAZ or PLY point cloud, LAS/LAZ tiles of one
    survey (the files, their folder or a quoted glob such as "tiles/*.laz"), a stereo
    scene folder, or two satellite images with RPCs (GeoTIFF RPC tags or an OSSIM .geom
    beside each).

    A scene folder holds images/, a COLMAP model in sparse/ and optionally
    georef.json {"crs": "EPSG:N", "offset": [x0, y0, z0]} (world = model + offset).

    OUT receives dsm.tif, dtm.tif, ndsm.tif, model_dsm.tif, cloud.laz,
    buildings.city.json, buildings.obj (with its materials, buildings.mtl),
    buildings.glb, buildings_3dtiles/ (3D Tiles 1.1), footprints.geojson,
    footprints.gpkg, report.json, report.html and run.json; with --old-buildings
    also changes.geojson, changes.tif and buildings_updated.city.json; from stereo
    inputs also ortho.tif (true orthophoto) and ortho_diff.tif (the images'
    disagreement on the DSM). Parameters left unset are chosen from the data and
    recorded, with the reason, in run.json.

    \b
    Examples
    --------
      recon3d run delft.laz --crs EPSG:7415 -o out
      recon3d run "ahn_tiles/*.laz" -o out
      recon3d run village.laz --footprints bati.shp --checkpoints gcp.csv -o out
      recon3d run city.laz -o out --set dsm.resolution=0.5 --overwrite
      recon3d run img1.tif img2.tif -o out
    """
    from recon3d.config import PipelineConfig
    from recon3d.core.geo import parse_crs
    from recon3d.pipeline.run import run as run_pipeline

    config = PipelineConfig.from_toml(config_path) if config_path else PipelineConfig()
    config = _with_old_heights(config.with_overrides(list(overrides)), old_height_field, old_height_reference)
    user_crs = parse_crs(crs) if crs else None
    with _StageProgress(enabled=not ctx.obj.get("quiet")) as progress:
        state = run_pipeline(
            tuple(input_path),
            out_dir,
            crs=user_crs,
            footprints=footprints,
            checkpoints=checkpoints,
            breaklines=breaklines,
            altimetry=altimetry,
            dem=dem,
            old_buildings=old_buildings,
            gcps=gcps,
            config=config,
            overwrite=overwrite,
            workers=workers,
            progress=progress,
            scheduler=scheduler or ("local" if local_dask else None),
            resume=resume,
            keep_points=False,
        )
    if not ctx.obj.get("quiet"):
        _print_summary(state)


@cli.command()
@click.argument("left", type=click.Path(path_type=Path))
@click.argument("right", type=click.Path(path_type=Path))
@click.option("-o", "--out", "out_path", required=True, type=click.Path(path_type=Path), help="Disparity GeoTIFF (float32, NaN invalid).")
@click.option("--min-disparity", default=0, show_default=True, help="Smallest disparity searched (px).")
@click.option("--max-disparity", default=64, show_default=True, help="Largest disparity searched (px).")
@click.option("--overwrite", is_flag=True, help="Replace OUT if it exists.")
@click.option("--max-memory", callback=_memory_cap, expose_value=False, metavar="SIZE", help="Most memory matching may take, e.g. 2G  [default: what the system has free].")
def disparity(left, right, out_path, min_disparity, max_disparity, overwrite):
    """Dense disparity of a rectified pair LEFT RIGHT (left-image disparity: x_right = x_left - d).

    \b
    Examples
    --------
      recon3d disparity left.png right.png -o disp.tif --max-disparity 64
    """
    import cv2
    import numpy as np
    from affine import Affine

    from recon3d.core.raster import Raster
    from recon3d.errors import InputError
    from recon3d.io.geotiff import write_raster
    from recon3d.stereo.match import MatchParams, match

    if out_path.exists() and not overwrite:
        raise InputError(f"{out_path}: exists; use --overwrite to replace it")
    images = []
    for path in (left, right):
        image = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE) if path.is_file() else None
        if image is None:
            raise InputError(f"{path}: missing or unreadable image")
        images.append(image)
    result = match(images[0], images[1], MatchParams(min_disparity=min_disparity, max_disparity=max_disparity))
    write_raster(Raster(result.disparity, Affine.identity(), None, {"product": "disparity"}), out_path)
    valid = float(np.isfinite(result.disparity).mean()) * 100
    click.echo(f"wrote {out_path}: {result.params.get('matched_percent', valid):.1f} % of pixels matched, "
               f"{valid:.1f} % with a disparity after gap filling")


@cli.command()
@click.option("-o", "--out", "out_dir", default="recon3d-demo", show_default=True, type=click.Path(path_type=Path), help="Output folder; the rendered scene goes to OUT/scene.")
@click.option("--seed", default=0, show_default=True, help="Seed of the procedural city.")
@click.option("--overwrite", is_flag=True, help="Replace OUT if it exists.")
@click.pass_context
def demo(ctx, out_dir, seed, overwrite):
    """Render a small synthetic city as an aerial stereo pair, reconstruct it, check it against its truth.

    \b
    Examples
    --------
      recon3d demo -o demo
    """
    import shutil

    from recon3d.errors import InputError
    from recon3d.pipeline.run import run as run_pipeline
    from recon3d.synthetic import write_scene

    if out_dir.exists() and any(out_dir.iterdir()) and not overwrite:
        raise InputError(f"{out_dir}: exists and is not empty; use --overwrite to replace it")
    shutil.rmtree(out_dir, ignore_errors=True)
    scene_dir = out_dir / "scene"
    with _StageProgress(enabled=not ctx.obj.get("quiet")) as progress:
        progress("render", 0, 1)
        write_scene(scene_dir, seed=seed)
        state = run_pipeline(
            scene_dir, out_dir / "products", checkpoints=scene_dir / "truth" / "checkpoints.csv",
            truth_dsm=scene_dir / "truth" / "dsm.tif", progress=progress,
        )
    if not ctx.obj.get("quiet"):
        _print_summary(state)


@cli.command()
@click.argument("out_dir", metavar="OUT", type=click.Path(path_type=Path))
def report(out_dir):
    """Regenerate OUT/report.html from the products and report.json of a run."""
    from recon3d.report import write_report

    click.echo(f"wrote {write_report(out_dir)}")


@cli.command()
@click.argument("out_dir", metavar="OUT", type=click.Path(path_type=Path))
@click.option("--port", type=click.IntRange(0, 65535), help="Port on 127.0.0.1  [default: a free one; one in use is replaced by a free one, with a warning].")
@click.option("--no-browser", is_flag=True, help="Only serve; open the printed address yourself.")
def view(out_dir, port, no_browser):
    """Show the buildings of a finished run in the browser, on its hillshade (or ortho.tif).

    Serves OUT on localhost (three.js is shipped with recon3d: no network needed)
    until Ctrl-C. Buildings are coloured by LoD or by quality (roof RMS against the
    DSM, status); a click shows a building's attributes.

    \b
    Examples
    --------
      recon3d view out
      recon3d view out --port 8000 --no-browser
    """
    from recon3d.viewer import serve, start_server

    server = start_server(out_dir, port)
    click.echo(f"serving {out_dir} at {server.url}  (Ctrl-C to stop)")
    try:
        serve(server, open_browser=not no_browser)
    except KeyboardInterrupt:
        click.echo("stopped")


#: File name ending of each export format.
_EXPORT_SUFFIX = {"cityjson": ".city.json", "cityjsonseq": ".city.jsonl", "obj": ".obj", "gltf": ".gltf", "glb": ".glb",
                  "3dtiles": "_3dtiles"}


def _check_gltf_name(dest: Path, fmt: str) -> None:
    """Refuse a .glb name for JSON glTF and a .gltf name for GLB: readers go by the ending."""
    from recon3d.errors import InputError

    ending = dest.suffix.lower()
    if fmt in ("gltf", "glb") and ending in (".gltf", ".glb") and ending != _EXPORT_SUFFIX[fmt]:
        kind = "JSON glTF" if fmt == "gltf" else "binary glTF"
        raise InputError(f"{dest}: --format {fmt} writes {kind}, which is read as {_EXPORT_SUFFIX[fmt]}; "
                         f"name the file {dest.stem}{_EXPORT_SUFFIX[fmt]} or use --format {ending[1:]}")


@cli.command()
@click.argument("out_dir", metavar="OUT", type=click.Path(path_type=Path))
@click.option("--format", "fmt", required=True, type=click.Choice(["cityjson", "cityjsonseq", "obj", "gltf", "glb", "3dtiles"]), help="Target format (3dtiles: a folder, tileset.json and tiles/*.glb).")
@click.option("-o", "--output", "dest", type=click.Path(path_type=Path), help="File to write (default: OUT/export/buildings.<ext>, so the run's own files stay as they are).")
@click.option("--overwrite", is_flag=True, help="Replace the file if it exists.")
def export(out_dir, fmt, dest, overwrite):
    """Convert the buildings of a run (OUT/buildings.city.json) to another format.

    gltf writes one JSON .gltf file (buffer embedded), glb the binary form.

    \b
    Examples
    --------
      recon3d export out --format cityjsonseq
      recon3d export out --format glb -o city.glb
      recon3d export out --format gltf -o city.gltf
      recon3d export out --format 3dtiles -o site/buildings_3dtiles
    """
    from recon3d.errors import InputError
    from recon3d.io import cityjson, gltf, obj, tiles3d
    from recon3d.pipeline.output import FinishedRun, Products

    dest = dest or out_dir / "export" / f"buildings{_EXPORT_SUFFIX[fmt]}"
    _check_gltf_name(dest, fmt)
    _refuse_existing([dest, dest.with_suffix(".mtl")] if fmt == "obj" else [dest], overwrite)  # OBJ writes its .mtl
    finished = FinishedRun(out_dir)
    source = finished.path(Products.CITY)
    city = finished.city(parts=True)  # every BuildingPart's solid, not the first one
    kinds = [s.kind for b in city for s in b.solids.values()]
    geometries = ", ".join(f"{kinds.count(k)} {'solids' if k == 'Solid' else k}" for k in sorted(set(kinds), reverse=True))
    skipped = ", ".join(f"{n} {k}" for k, n in sorted(city.metadata.get("skipped_geometries", {}).items()))
    if not kinds:
        raise InputError(f"{source}: no geometry to export ({len(city)} buildings"
                         + (f"; skipped: {skipped})" if skipped else ")"))
    writers = {"cityjson": cityjson.write_cityjson, "cityjsonseq": cityjson.write_cityjsonseq,
               "obj": obj.write_obj, "gltf": gltf.write_gltf, "glb": gltf.write_glb, "3dtiles": tiles3d.write_3dtiles}
    writers[fmt](city, dest)
    click.echo(f"wrote {dest} ({len(city)} buildings: {geometries})")
    if skipped:
        click.echo(f"skipped: {skipped}")


@cli.command()
@click.argument("out_dir", metavar="OUT", type=click.Path(path_type=Path))
@click.option("--old-buildings", required=True, type=click.Path(path_type=Path), help="Older building database (Shapefile, GeoPackage, GeoJSON or CityJSON).")
@click.option("--old-height-field", metavar="NAME", help="Height attribute of --old-buildings when it has none of the usual names (roof_z, height, hauteur, roof_height, h_dak_max...).")
@click.option("--old-height-reference", type=click.Choice(["ground", "absolute"]), help="What the old heights are measured from  [default: known from the usual names, else decided from the data].")
@click.option("--overwrite", is_flag=True, help="Replace earlier change products in OUT.")
def change(out_dir, old_buildings, old_height_field, old_height_reference, overwrite):
    """Compare an older building database with the buildings of a run (OUT).

    Writes OUT/changes.geojson (one feature per change: class, confidence, old and new
    values), OUT/changes.tif (change classes on the product grid) and
    OUT/buildings_updated.city.json (old ids kept where unchanged, lineage attributes).

    \b
    Examples
    --------
      recon3d change out --old-buildings bati_2015.shp
    """
    from recon3d.core.geo import crs_units
    from recon3d.io.cityjson import write_cityjson
    from recon3d.io.geotiff import write_raster
    from recon3d.io.vectors import read_footprints, write_features
    from recon3d.pipeline.output import FinishedRun, Products
    from recon3d.quality import change as change_mod

    finished = FinishedRun(out_dir)
    target, raster, updated = (finished.path(n, required=False)
                               for n in (Products.CHANGES, Products.CHANGES_RASTER, Products.UPDATED_CITY))
    _refuse_existing([target, raster, updated], overwrite)
    city = finished.city()
    ndsm = finished.raster(Products.NDSM)
    crs = city.crs or ndsm.crs
    old, _ = read_footprints(old_buildings, crs=crs)
    params = change_mod.ChangeParams(height_field=old_height_field, height_reference=old_height_reference)
    result = change_mod.detect_changes(old, city, ndsm, units=crs_units(crs), config=params)
    write_features(target, *change_mod.change_features(result), crs)
    write_raster(change_mod.change_raster(result, ndsm), raster)
    write_cityjson(change_mod.updated_model(old, city, result), updated)
    click.echo("changes: " + ", ".join(f"{k} {v}" for k, v in sorted(result.summary.items()) if v))
    for note in result.notes:
        click.echo(f"note: {note}")
    for warning in result.warnings:
        click.echo(f"warning: {warning}", err=True)


@cli.command()
@click.argument("path", metavar="FILE", type=click.Path(path_type=Path))
@click.option("--planarity", default=0.01, show_default=True, help="Largest distance (CRS units) of a vertex to its face's plane.")
@click.option("--meshes", is_flag=True, help="Check the building meshes of a run's buildings.glb and buildings.obj (FILE: the run's folder, or one GLB or OBJ file) instead of CityJSON solids.")
def validate(path, planarity, meshes):
    """Check every solid of every city object of a CityJSON file (BuildingParts and
    MultiSolids included) the way val3dity does (closed, 2-manifold, outward, planar
    faces, no degenerate face, positive volume); exit 1 if any fails or there is none.
    Geometries that are not solids (MultiSurface) are counted, not checked.

    With --meshes, every building mesh of the GLB and OBJ exports is loaded by trimesh
    as stored (nothing merged) and must be watertight, consistently wound and outward,
    and accepted by manifold3d; each file's count passing and failing is printed with
    the failing building ids; exit 1 if any fails or there is none.

    \b
    Examples
    --------
      recon3d validate out/buildings.city.json
      recon3d validate --meshes out
    """
    if meshes:
        _validate_meshes(path)
        return
    from recon3d.io.cityjson import solid_inventory
    from recon3d.quality.meshcheck import check_solid

    solids, others = solid_inventory(path)
    n_bad = 0
    for oid, kind, label, solid in solids:
        issues = check_solid(solid, planarity_tol=planarity)
        if issues:
            n_bad += 1
            text = "; ".join(f"{i.code} {i.name}" + (f" (surface {i.surface})" if i.surface is not None else "") for i in issues[:5])
            click.echo(f"{oid} ({kind}) {label}: {text}")
    objects = len({oid for oid, *_ in solids})
    click.echo(f"{len(solids) - n_bad} of {len(solids)} solids valid in {objects} city objects")
    if others:
        listed = ", ".join(f"{n} {k}" for k, n in sorted(others.items()))
        click.echo(f"not solids, so not checked: {listed} geometries")
    if n_bad or not solids:
        sys.exit(1)


def _validate_meshes(path: Path) -> None:
    """``validate --meshes``: check the GLB and OBJ building meshes of a run folder or of one file."""
    from recon3d.errors import InputError
    from recon3d.quality.meshcheck import check_mesh_file

    files = [p for p in (path / "buildings.glb", path / "buildings.obj") if p.exists()] if path.is_dir() else [path]
    if not files or not path.exists():
        raise InputError(f"{path}: no buildings.glb or buildings.obj to check (give a run's folder, a GLB or an OBJ file)")
    n_bad = n_solids = 0
    for file in files:
        results = check_mesh_file(file)
        solids = [r for r in results if r.kind == "Solid"]
        failing = [r for r in solids if not r.ok]
        for r in failing:
            click.echo(f"{file.name}: {r.id}: {', '.join(r.problems())}")
        line = f"{file.name}: {len(solids) - len(failing)} of {len(solids)} building meshes pass, {len(failing)} fail"
        line += f" ({', '.join(r.id for r in failing)})" if failing else ""
        others = len(results) - len(solids)
        click.echo(line + (f"; {others} MultiSurface meshes not checked" if others else ""))
        n_bad += len(failing)
        n_solids += len(solids)
    if n_bad or not n_solids:
        sys.exit(1)


@cli.group()
def evaluate():
    """Measure products against references (ISPRS definitions)."""


@evaluate.command("ground")
@click.argument("cloud_path", metavar="CLOUD", type=click.Path(path_type=Path))
@click.option("--reference", required=True, type=click.Path(path_type=Path), help="The same cloud classified by its provider (class 2 ground).")
@click.option("--crs", help="CRS for files without one, e.g. EPSG:7415.")
@click.option("--dtm", "dtm_path", type=click.Path(path_type=Path), help="DTM to check; default: dtm.tif beside CLOUD, if there.")
@click.option("--checkpoints", type=click.Path(path_type=Path), help="CSV x,y,z[,id][,kind] to check the DTM against.")
@click.option("--json", "json_path", type=click.Path(path_type=Path), help="Also write the numbers as JSON.")
@click.option("--overwrite", is_flag=True, help="Replace the --json file if it exists.")
def evaluate_ground(cloud_path, reference, crs, dtm_path, checkpoints, json_path, overwrite):
    """Type I, Type II, total error and kappa of the ground in CLOUD, and the DTM's RMS.

    Points the provider labelled ground (2) are scored against vegetation and
    building (3, 4, 5, 6); unclassified points are left out, as in the ISPRS filter test.

    \b
    Examples
    --------
      recon3d evaluate ground out/cloud.laz --reference delft.laz --crs EPSG:7415
    """
    from recon3d.core.geo import crs_units, parse_crs
    from recon3d.errors import InputError
    from recon3d.io.checkpoints import read_checkpoints
    from recon3d.io.geotiff import read_raster
    from recon3d.io.las import read_las
    from recon3d.quality.evaluate import evaluate_ground as run_evaluation

    _refuse_existing([json_path] if json_path else [], overwrite)
    user_crs = parse_crs(crs) if crs else None
    ref = read_las(reference, crs=user_crs)
    classified = read_las(cloud_path, crs=user_crs or ref.crs)
    _require_overlap(reference, _cloud_box(ref), f"the classified cloud {cloud_path}", _cloud_box(classified))
    dtm_path = dtm_path or (cloud_path.parent / "dtm.tif" if (cloud_path.parent / "dtm.tif").exists() else None)
    dtm = read_raster(dtm_path) if dtm_path else None
    if dtm is not None:
        _require_overlap(reference, _cloud_box(ref), f"the DTM {dtm_path}", dtm.bounds)
    points = read_checkpoints(checkpoints) if checkpoints else None
    result = run_evaluation(classified, ref, crs_units(ref.crs, source=str(reference)), dtm=dtm, checkpoints=points)
    p = result["points"]
    if not p["n"]:
        raise InputError(f"{reference}: no point classified ground (2) or vegetation / building (3-6) "
                         "where the run has points: nothing to score")
    click.echo(f"points scored {p['n']}: Type I {p['type_i_percent']:.2f} %  Type II {p['type_ii_percent']:.2f} %  "
               f"total {p['total_percent']:.2f} %  kappa {p['kappa']:.4f}")
    _echo_accuracy(result["accuracy"])
    _write_json_result(json_path, result)


@evaluate.command("buildings")
@click.argument("out_dir", metavar="OUT", type=click.Path(path_type=Path))
@click.option("--reference", required=True, type=click.Path(path_type=Path), help="Reference footprints (Shapefile, GeoPackage, GeoJSON, CityJSON) or a provider-classified LAS/LAZ (class 6).")
@click.option("--crs", help="CRS of a reference LAS/LAZ without one.")
@click.option("--json", "json_path", type=click.Path(path_type=Path), help="Also write the numbers as JSON.")
@click.option("--overwrite", is_flag=True, help="Replace the --json file if it exists.")
def evaluate_buildings(out_dir, reference, crs, json_path, overwrite):
    """Completeness, correctness and quality (area and object, ISPRS 50 % rule) and outline RMS of OUT's buildings.

    Only the reference inside the run's data extent is scored.

    \b
    Examples
    --------
      recon3d evaluate buildings out --reference bduni_buildings.shp
      recon3d evaluate buildings out --reference delft.laz --crs EPSG:7415
    """
    from recon3d.pipeline.output import FinishedRun

    _refuse_existing([json_path] if json_path else [], overwrite)
    city = FinishedRun(out_dir).city()
    detected = [b.footprint for b in city if b.status == "ok"]
    extent = _run_extent(out_dir, detected)
    if reference.suffix.lower() in (".las", ".laz"):
        result = _buildings_against_cloud(reference, crs, detected, extent)
    else:
        result = _buildings_against_footprints(reference, city.crs or _user_crs(crs), detected, extent)
    for key in sorted(result):
        value = result[key]
        if isinstance(value, float | int):
            click.echo(f"{key:<32} {value:.3f}" if isinstance(value, float) else f"{key:<32} {value}")
    _write_json_result(json_path, result)


def _user_crs(text: str | None):
    """The ``--crs`` given, parsed, or None."""
    from recon3d.core.geo import parse_crs

    return parse_crs(text) if text else None


def _run_extent(out_dir: Path, detected: list) -> tuple[float, float, float, float] | None:
    """(x0, y0, x1, y1) of the run's data: its DSM's grid, else its buildings, else None."""
    import shapely

    from recon3d.pipeline.output import FinishedRun, Products

    finished = FinishedRun(out_dir)
    if finished.path(Products.DSM, required=False).exists():
        return finished.raster(Products.DSM).bounds
    return shapely.MultiPolygon(detected).bounds if detected else None


def _buildings_against_cloud(reference: Path, crs: str | None, detected: list, extent) -> dict:
    """Scores of the detected footprints against a provider-classified cloud's building class."""
    from recon3d.core.geo import crs_units
    from recon3d.io.las import read_las
    from recon3d.quality import buildings as building_quality

    cloud = read_las(reference, crs=_user_crs(crs))
    if extent is not None:
        _require_overlap(reference, _cloud_box(cloud), "the run", extent)
    return building_quality.evaluate_against_classes(detected, cloud, cloud.classification, units=crs_units(cloud.crs))


def _buildings_against_footprints(reference: Path, crs, detected: list, extent) -> dict:
    """Scores of the detected footprints against the reference footprints inside the run's extent."""
    import shapely

    from recon3d.core.geo import crs_units
    from recon3d.errors import InputError
    from recon3d.io.vectors import read_footprints
    from recon3d.quality import buildings as building_quality

    refs, _ = read_footprints(reference, crs=crs)
    polys = [f.polygon for f in refs]
    if extent is not None and polys:
        _require_overlap(reference, shapely.MultiPolygon(polys).bounds, "the run", extent)
        polys = [p for p in polys if p.within(shapely.box(*extent))]
        if not polys:
            raise InputError(f"{reference}: none of its {len(refs)} footprints lies wholly inside the run "
                             f"({_box_text(extent)}): nothing to score")
    return building_quality.evaluate_footprints(detected, polys, units=crs_units(crs))


def _cloud_box(cloud) -> tuple[float, float, float, float]:
    """(x0, y0, x1, y1) of a point cloud."""
    (x0, y0, _), (x1, y1, _) = cloud.bounds
    return float(x0), float(y0), float(x1), float(y1)


def _box_text(box) -> str:
    return "x {:.1f} to {:.1f}, y {:.1f} to {:.1f}".format(box[0], box[2], box[1], box[3])


def _require_overlap(reference: Path, ref_box, what: str, box) -> None:
    """Refuse a reference whose extent ``ref_box`` does not overlap ``box`` (``what``'s extent).

    Raises
    ------
    InputError
        Naming both extents: a reference elsewhere, or in another CRS, would score zeros.
    """
    from recon3d.errors import InputError

    if not (ref_box[0] < box[2] and box[0] < ref_box[2] and ref_box[1] < box[3] and box[1] < ref_box[3]):
        raise InputError(f"{reference}: the reference ({_box_text(ref_box)}) does not overlap {what} "
                         f"({_box_text(box)}); is it the same area, in the same CRS?")


def _write_json_result(json_path: Path | None, result: dict) -> None:
    """``result`` as indented JSON at ``json_path`` (atomic), when one was given."""
    if json_path:
        import json

        from recon3d.io import atomic_path

        with atomic_path(json_path) as tmp:
            tmp.write_text(json.dumps(result, indent=2, default=str), encoding="utf-8")


def _refuse_existing(paths: list[Path], overwrite: bool) -> None:
    """One error naming every file of ``paths`` that exists, unless ``overwrite``."""
    from recon3d.errors import InputError

    existing = [str(p) for p in paths if p.exists()]
    if existing and not overwrite:
        raise InputError(f"{', '.join(existing)}: {'exist' if len(existing) > 1 else 'exists'}; "
                         "use --overwrite to replace")


class _StageProgress:
    """A progress bar over pipeline stages on a terminal; silent otherwise."""

    def __init__(self, enabled: bool) -> None:
        self.enabled = enabled and sys.stderr.isatty()
        self.bar = None

    def __enter__(self):
        if self.enabled:
            from tqdm import tqdm

            self.bar = tqdm(total=1, unit="stage", file=sys.stderr, leave=False)
        return self

    def __call__(self, name: str, index: int, total: int) -> None:
        if self.bar is not None:
            self.bar.total = total
            self.bar.n = index
            self.bar.set_description(name)
            self.bar.refresh()

    def __exit__(self, *exc):
        if self.bar is not None:
            self.bar.close()


def _print_summary(state) -> None:
    click.echo(f"wrote {state.out_dir}  ({len(state.city)} buildings, {sum(state.timings.values()):.1f} s)")
    _echo_accuracy(state.report.get("accuracy", []))
    if state.warnings:
        click.echo(f"{len(state.warnings)} warning(s), repeated in report.html and run.json:")
        for w in state.warnings:
            click.echo(f"  - {w}")


def _echo_accuracy(rows: list[dict]) -> None:
    """The accuracy table (metres, percentages) on stdout."""
    if rows:
        w = max(len("product"), *(len(r["product"]) for r in rows)) + 1  # the header fits too
        click.echo(f"{'product':<{w}}{'reference':<32}{'n':>8}{'mean':>8}{'std':>7}{'RMS':>7}{'max':>7}{'NMAD':>7}{'<=1m%':>7}{'<=2m%':>7}")
        for r in rows:
            if not r["n"]:
                continue
            click.echo(
                f"{r['product']:<{w}}{r['reference'][:31]:<32}{r['n']:>8}{r['mean']:>8.3f}{r['std']:>7.3f}"
                f"{r['rms']:>7.3f}{r['max_abs']:>7.2f}{r['nmad']:>7.3f}{r['within_1m']:>7.1f}{r['within_2m']:>7.1f}"
            )


class Terminated(SystemExit):
    """SIGTERM, raised in the main thread so that every ``finally`` cleans up."""


#: The signals this process received (Ctrl-C, SIGTERM): an interrupted run ends as
#: interrupted whatever exception the signal turned into on its way out (a Ctrl-C in a
#: compiled module's import comes out as "ImportError: initialization failed").
_RECEIVED: list[int] = []


def _on_signal(signum, frame) -> None:
    import signal

    _RECEIVED.append(signum)
    if signum == signal.SIGTERM:
        raise Terminated(143)
    raise KeyboardInterrupt


def main() -> None:
    """Console-script entry point: errors as one line (exit 1), Ctrl-C exit 130, SIGTERM 143."""
    import signal

    if signal.getsignal(signal.SIGINT) is signal.default_int_handler:  # not when started ignoring Ctrl-C
        signal.signal(signal.SIGINT, _on_signal)
    signal.signal(signal.SIGTERM, _on_signal)
    try:
        cli(prog_name="recon3d", standalone_mode=False)
    except BaseException as exc:
        # a signal ends the run as interrupted whatever it became on its way out
        # (click.Abort: Ctrl-C inside a prompt or click's own handling)
        signum = _RECEIVED[0] if _RECEIVED else None
        if signum is None and isinstance(exc, (click.exceptions.Abort, KeyboardInterrupt)):
            signum = signal.SIGINT
        if signum is not None and not (isinstance(exc, SystemExit) and not exc.code):
            _interrupted(signum)
        if isinstance(exc, click.exceptions.ClickException):
            exc.show()
            sys.exit(exc.exit_code)
        raise


def entry() -> None:
    """The ``recon3d`` command: :func:`main`, and an interrupted run leaves without the
    interpreter's teardown once its own clean-up has run: a native thread of a library
    still winding down can crash that teardown (exit -11 instead of 130 / 143)."""
    import os

    try:
        main()
    except SystemExit as exc:
        if _RECEIVED and exc.code in (130, 143):
            sys.stdout.flush()
            sys.stderr.flush()
            os._exit(exc.code)
        raise


def _interrupted(signum: int) -> None:
    """Say so and leave: exit 130 for Ctrl-C, 143 for SIGTERM."""
    import signal

    terminated = signum == signal.SIGTERM
    click.echo("recon3d: interrupted" + (" (terminated)" if terminated else ""), err=True)
    sys.exit(143 if terminated else 130)
