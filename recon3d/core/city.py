"""Buildings, their solids and the city model."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np
import pyproj
import shapely

from recon3d.core.geo import LocalFrame
from recon3d.core.mesh import SolidMesh, newell_normal, solid_mesh, triangulate_surface

if TYPE_CHECKING:  # trimesh (and scipy with it) is imported by to_trimesh, when a mesh is wanted
    import trimesh

__all__ = ["SEMANTIC_TYPES", "Building", "CityModel", "Solid", "newell_normal", "triangulate_surface"]

#: CityJSON semantic surface types used for building solids.
SEMANTIC_TYPES = ("GroundSurface", "WallSurface", "RoofSurface")


@dataclass
class Solid:
    """A closed polyhedral solid made of planar polygonal surfaces (CityJSON-style).

    Parameters
    ----------
    vertices : (n, 3) float64
        Coordinates in the city model's :class:`LocalFrame`.
    surfaces : list of list of (k,) int arrays
        Each surface is an outer ring followed by its inner rings (holes); rings are
        vertex indices, not closed (first vertex not repeated). Outer rings are
        counter-clockwise seen from outside the solid; inner rings clockwise.
    semantics : list of str
        One of :data:`SEMANTIC_TYPES` per surface.
    kind : {"Solid", "MultiSurface"}
        "MultiSurface": surfaces read from another tool's MultiSurface or
        CompositeSurface, not known to close a volume. They are exported as they came
        (CityJSON MultiSurface, OBJ and glTF faces) and never checked as a solid.
    """

    vertices: np.ndarray
    surfaces: list[list[np.ndarray]]
    semantics: list[str]
    kind: str = "Solid"
    _mesh: SolidMesh | None = field(default=None, init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        self.vertices = np.asarray(self.vertices, dtype=np.float64).reshape(-1, 3)
        self.surfaces = [[np.asarray(r, dtype=np.int64) for r in s] for s in self.surfaces]
        if len(self.surfaces) != len(self.semantics):
            raise ValueError("one semantic type per surface is required")

    def mesh(self) -> SolidMesh:
        """The solid's triangles on welded vertices, without T-junctions (:func:`~recon3d.core.mesh.solid_mesh`).

        A solid is not changed once built, so they are computed once (the model DSM,
        the OBJ, the GLB and the checks all ask for them).
        """
        if self._mesh is None:
            self._mesh = solid_mesh(self.vertices, self.surfaces)
        return self._mesh

    def __getstate__(self) -> dict:
        """Pickled with its rings packed into one array: a city's solids hold tens of
        thousands of small ring arrays, and pickling them one by one was most of the
        cost of handing buildings to the worker processes."""
        state = self.__dict__.copy()
        rings = [ring for surface in self.surfaces for ring in surface]
        state["surfaces"] = (
            np.concatenate(rings) if rings else np.zeros(0, np.int64),
            np.array([len(ring) for ring in rings], np.int64),
            np.array([len(surface) for surface in self.surfaces], np.int64),
        )
        return state

    def __setstate__(self, state: dict) -> None:
        flat, ring_sizes, surface_sizes = state["surfaces"]
        rings = np.split(flat, np.cumsum(ring_sizes)[:-1]) if len(ring_sizes) else []
        ends = np.cumsum(surface_sizes)
        state["surfaces"] = [rings[end - size:end] for size, end in zip(surface_sizes, ends, strict=True)]
        self.__dict__.update(state)

    def to_trimesh(self) -> trimesh.Trimesh:
        """The triangles of :meth:`mesh` as a :class:`trimesh.Trimesh` (not processed).

        A closed solid gives a watertight, consistently wound mesh with outward
        normals. ``metadata["semantics"]`` holds one surface type per triangle and
        ``metadata["surface_index"]`` each triangle's surface.
        """
        import trimesh

        vertices, faces, index = self.mesh()
        mesh = trimesh.Trimesh(vertices.copy(), faces.copy(), process=False)
        mesh.metadata["semantics"] = [self.semantics[i] for i in index]
        mesh.metadata["surface_index"] = index.copy()
        return mesh


@dataclass
class Building:
    """One building of the city model.

    Parameters
    ----------
    id : str
        Stable identifier (from the given footprint, or ``b<n>`` for detected ones).
    footprint : shapely.Polygon
        Outline in world CRS coordinates (holes for courtyards).
    ground_z, roof_z : float
        Terrain height under the footprint and representative roof height (LoD1),
        in CRS height units.
    solids : dict of str to Solid
        Solids by LoD ("1", "2.2"), in the city model's :class:`LocalFrame`.
    status : str
        "ok" when every requested LoD was built, "failed" when none was; ``reason``
        says why (a short code such as "no_points" or "too_low").
    attributes : dict
        Extra values written to CityJSON and footprints.geojson.
    parent : str or None
        Id of the block this building is a part of, when detection split one connected
        block of roofs at height jumps (:func:`recon3d.buildings.detect.assign_blocks`);
        None for a stand-alone building. CityJSON writes the parts of a block as
        ``BuildingPart`` children of one parent ``Building`` with that id.
    """

    id: str
    footprint: shapely.Polygon
    ground_z: float = float("nan")
    roof_z: float = float("nan")
    solids: dict[str, Solid] = field(default_factory=dict)
    status: str = "ok"
    reason: str | None = None
    attributes: dict[str, Any] = field(default_factory=dict)
    parent: str | None = None

    @property
    def height(self) -> float:
        """Roof height above the terrain, in CRS height units."""
        return self.roof_z - self.ground_z


@dataclass
class CityModel:
    """The buildings of one run, their CRS and the local frame of their solids."""

    buildings: list[Building]
    crs: pyproj.CRS | None
    frame: LocalFrame = field(default_factory=LocalFrame)
    metadata: dict[str, Any] = field(default_factory=dict)

    def __len__(self) -> int:
        return len(self.buildings)

    def __iter__(self):
        return iter(self.buildings)

    def blocks(self) -> dict[str, list[Building]]:
        """The parts of each block, by block id (:attr:`Building.parent`), in model order."""
        out: dict[str, list[Building]] = {}
        for b in self.buildings:
            if b.parent is not None:
                out.setdefault(b.parent, []).append(b)
        return out
