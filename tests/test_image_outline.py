"""Outlines moved to the eaves the images show (recon3d.buildings.image_outline).

The scenes are drawn exactly: a flat-roofed box seen by cameras with a known relief
displacement, so the true outline is known to the pixel and the walls each camera
sees beside the roof are where that camera puts them.
"""

import cv2
import numpy as np
import pytest
import shapely
from affine import Affine

from recon3d.buildings.image_outline import _moved_ring, edge_offsets, refine_outlines
from recon3d.core.raster import Raster
from recon3d.stereo.ortho import View

TRUE = shapely.box(0.0, 0.0, 20.0, 10.0)  # the eaves, at EAVE_Z
EAVE_Z = 10.0
GSD = 0.1
ORIGIN = (-8.0, 14.0)  # world x, y of pixel (0, 0)
COLOURS = {"roof": (200, 90, 60), "wall": (120, 120, 130), "ground": (60, 140, 50)}


def camera_view(name: str, lean: tuple[float, float], *, wall=COLOURS["wall"], seed=0) -> View:
    """A view of the box with ``lean`` metres of relief displacement (x, y) per metre of height."""
    lx, ly = lean

    def project(x, y, z):
        x, y, z = np.broadcast_arrays(*(np.asarray(v, dtype=np.float64) for v in (x, y, z)))
        return (x + lx * z - ORIGIN[0]) / GSD, (ORIGIN[1] - (y + ly * z)) / GSD

    rows, cols = np.mgrid[0:280, 0:360].astype(np.float64)
    # world point at height z seen at a pixel: x = ORIGIN + col * GSD - lean * z
    heights = np.linspace(EAVE_Z, 0.0, 41)
    x = ORIGIN[0] + cols[..., None] * GSD - lx * heights
    y = ORIGIN[1] - rows[..., None] * GSD - ly * heights
    inside = (x >= 0) & (x <= 20) & (y >= 0) & (y <= 10)
    image = np.empty((*rows.shape, 3), np.float64)
    image[:] = COLOURS["ground"]
    image[inside.any(axis=-1)] = wall  # the ray meets the box below the eaves: a wall
    image[inside[..., 0]] = COLOURS["roof"]  # at eave height inside the box: the roof
    noise = np.random.default_rng(seed).normal(0.0, 6.0, image.shape)
    return View(name, np.clip(image + noise, 0, 255).astype(np.uint8), project)


def box_dsm(outline: shapely.Polygon) -> Raster:
    """0.5 m DSM: the eave height inside ``outline`` (the blurred nDSM edge), 0 outside."""
    transform = Affine(0.5, 0.0, -8.0, 0.0, -0.5, 14.0)
    rows, cols = np.mgrid[0:56, 0:72]
    x, y = -8.0 + 0.5 * (cols + 0.5), 14.0 - 0.5 * (rows + 0.5)
    return Raster(np.where(shapely.contains_xy(outline, x, y), EAVE_Z, 0.0).astype(np.float32), transform, None)


def boundary_error(a: shapely.Polygon, b: shapely.Polygon) -> float:
    """Largest distance between the two outlines' vertices and the other outline."""
    pa = shapely.points(np.asarray(a.exterior.coords))
    pb = shapely.points(np.asarray(b.exterior.coords))
    return float(max(shapely.distance(pa, b.exterior).max(), shapely.distance(pb, a.exterior).max()))


# the nDSM outline: 0.6 m too far east, 0.4 m too far north, 0.3 m short in the west
NDSM = shapely.box(0.3, 0.0, 20.6, 10.4)


def test_edges_move_to_the_eaves_two_views_agree_on():
    views = [camera_view("a", (0.12, 0.05), seed=1), camera_view("b", (-0.15, -0.08), seed=2)]
    (result,) = refine_outlines([NDSM], views, box_dsm(NDSM))
    assert boundary_error(NDSM, TRUE) == pytest.approx(np.hypot(0.6, 0.4))
    assert result.source == "images"
    assert boundary_error(result.polygon, TRUE) < 0.15  # measured 0.12 m at the worst corner (1 pixel), from 0.72
    assert result.moved_share > 0.9
    assert 0.2 < result.mean_shift < 0.6


def test_a_wall_of_roof_colour_in_one_view_does_not_move_the_edge():
    # view "a" leans east: at eave height it sees the west wall beyond the roof's west
    # edge, here in the roof's own colour, so on its own it puts that edge at the wall's
    # foot, 1.2 m out; view "b" does not agree, so the west edge stays where the nDSM had it
    roof_wall = camera_view("a", (0.12, 0.05), wall=COLOURS["roof"], seed=1)
    views = [roof_wall, camera_view("b", (-0.15, -0.08), seed=2)]
    ring = np.asarray(shapely.geometry.polygon.orient(NDSM, 1.0).exterior.coords)[:-1]
    image = cv2.GaussianBlur(roof_wall.image.astype(np.float32), (0, 0), 1.0)
    offsets, found = edge_offsets(ring, roof_wall, image, EAVE_Z)
    west = int(np.argmin(ring[:, 0] + np.roll(ring[:, 0], -1)))  # the edge with the smallest x
    assert found[west] and offsets[west] > 1.2  # measured 1.45: x = -1.15, the wall's foot (the true edge: 0.3 out)
    (result,) = refine_outlines([NDSM], views, box_dsm(NDSM))
    x0, _, x1, _ = result.polygon.bounds
    assert x0 == pytest.approx(0.3, abs=1e-9)  # not moved: the two views disagree
    assert x1 == pytest.approx(20.0, abs=0.12)  # the east edge, which both see, moved


def test_one_view_is_not_enough():
    views = [camera_view("a", (0.12, 0.05), seed=1)]
    (result,) = refine_outlines([NDSM], views, box_dsm(NDSM))
    assert result.source == "ndsm" and result.polygon.equals(NDSM)


def test_moved_ring_keeps_directions_and_steps():
    # an L-shaped ring: moving every edge out by 0.5 m gives the 0.5 m outward buffer
    ell = shapely.geometry.polygon.orient(shapely.Polygon([(0, 0), (10, 0), (10, 4), (4, 4), (4, 8), (0, 8)]), 1.0)
    ring = np.asarray(ell.exterior.coords)[:-1]
    moved = shapely.Polygon(_moved_ring(ring, np.full(len(ring), 0.5)))
    assert moved.symmetric_difference(ell.buffer(0.5, join_style="mitre")).area < 1e-9
