"""Randomised aerial survey scenes: the range of cameras, terrains and cities users fly.

A :class:`SceneSpec` fixes everything about one synthetic survey: the camera block
(image size, focal length, principal point, heading, base direction, base-to-height
ratio, attitude errors, strips), the terrain, the building layout and the trees.
:func:`random_spec` draws one from the ranges of real surveys, :data:`CONFIGURATIONS`
names the corner cases every release is tested on, and
:func:`~recon3d.synthetic.scene.write_block_scene` renders a spec to a scene folder.

Ranges of :func:`random_spec` (each drawn independently from the seed):

=====================  ================================================================
heading                0-360 degrees (flight direction)
base direction         along the image x axis, the y axis, or diagonal (45 degrees)
attitude errors        0.5-5 degrees about each axis (roll, pitch, yaw)
image aspect           1:2 to 2:1 (width : height), non-square in general
principal point        up to 15 % of the image size off centre, either way
lens distortion        none for half the surveys, else k1 -0.08..0.05, k2, p1, p2 small
base-to-height         0.1-1.0
forward overlap        55-80 %; the focal length follows from it and the ratio
                       (0.35 to 3 times the image side, as survey cameras have)
GSD                    0.1-0.5 m
terrain                flat, gentle, a 10 % slope or hills (``city.TERRAINS``)
layout                 regular, dense or sparse lots (``city.LAYOUTS``)
trees                  beside the buildings or also over their roofs
block                  a pair, a strip of 3, or 2 strips of 3 with 30 % side overlap
=====================  ================================================================
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np

from recon3d.synthetic.render import PinholeCamera, block_cameras

__all__ = ["CONFIGURATIONS", "SceneSpec", "family", "random_spec"]


@dataclass(frozen=True)
class SceneSpec:
    """One synthetic aerial survey.

    Attributes
    ----------
    seed : int
        Seed of the city, the attitude errors, the sparse points and the sensor noise.
    width, height : int
        Image size in pixels.
    focal : float
        Focal length in pixels.
    principal_offset : (float, float)
        Principal point minus the image centre, pixels.
    gsd : float
        Ground sample distance at nadir, metres (the flying height is ``focal * gsd``).
    heading : float
        Flight direction, degrees clockwise from north.
    base_angle : float
        Angle from the image x axis to the flight direction, degrees.
    base_to_height : float
    attitude : float
        Largest roll, pitch and yaw error, degrees.
    strips, images_per_strip : int
    side_overlap : float
    distortion : (k1, k2, p1, p2)
        Lens distortion (COLMAP's OPENCV model), zeros for a distortion-free camera.
    terrain, layout, trees : str
        See :func:`~recon3d.synthetic.city.make_city`.
    n_sparse : int
        3-D points of the COLMAP model, each seen by at least two images.
    name : str
        Short label for tables.
    """

    seed: int = 0
    width: int = 2000
    height: int = 1500
    focal: float = 3000.0
    principal_offset: tuple[float, float] = (0.0, 0.0)
    gsd: float = 0.2
    heading: float = 0.0
    base_angle: float = 0.0
    base_to_height: float = 0.3
    attitude: float = 1.7
    strips: int = 1
    images_per_strip: int = 2
    side_overlap: float = 0.3
    distortion: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 0.0)
    terrain: str = "gentle"
    layout: str = "regular"
    trees: str = "beside"
    n_sparse: int = 300
    name: str = ""

    @property
    def flying_height(self) -> float:
        """Metres above the ground at the block centre."""
        return self.focal * self.gsd

    @property
    def forward_overlap(self) -> float:
        """Share of an image's extent along the flight that the next image sees too."""
        beta = math.radians(self.base_angle)
        along = (self.width * abs(math.cos(beta)) + self.height * abs(math.sin(beta))) * self.gsd
        return 1.0 - self.base_to_height * self.flying_height / along

    def cameras(self, target: np.ndarray) -> tuple[PinholeCamera, ...]:
        """The block's cameras over the local point ``target`` (see
        :func:`~recon3d.synthetic.render.block_cameras`)."""
        return block_cameras(
            target, width=self.width, height=self.height, focal=self.focal, gsd=self.gsd,
            base_to_height=self.base_to_height, heading=self.heading, base_angle=self.base_angle,
            principal_offset=self.principal_offset, attitude=self.attitude, strips=self.strips,
            images_per_strip=self.images_per_strip, side_overlap=self.side_overlap, seed=self.seed,
            distortion=self.distortion,
        )

    def with_width(self, width: int) -> SceneSpec:
        """The same survey geometry (angles, overlaps, GSD) with smaller or larger
        images: the ground each image covers scales with them. For fast tests."""
        k = width / self.width
        return dataclasses.replace(
            self, width=int(width), height=max(16, round(self.height * k)), focal=self.focal * k,
            principal_offset=(self.principal_offset[0] * k, self.principal_offset[1] * k),
        )

    def to_dict(self) -> dict:
        doc = dataclasses.asdict(self)
        doc["principal_offset"] = list(self.principal_offset)
        doc["distortion"] = list(self.distortion)
        doc["flying_height"] = round(self.flying_height, 3)
        doc["forward_overlap"] = round(self.forward_overlap, 4)
        return doc


#: The corner cases of the camera family, run by the test suite at small image sizes.
CONFIGURATIONS: dict[str, SceneSpec] = {
    # the unseen scene of issue 15: base along x, off-centre principal point, 1.7 degrees
    "nadir_pair": SceneSpec(seed=11, principal_offset=(6.0, -4.0), base_to_height=0.3, name="nadir_pair"),
    "heading_90": SceneSpec(seed=12, heading=90.0, base_angle=90.0, base_to_height=0.2, attitude=3.0,
                            name="heading_90"),
    "heading_180": SceneSpec(seed=13, heading=180.0, attitude=5.0, terrain="slope", name="heading_180"),
    "diagonal_base": SceneSpec(seed=14, heading=30.0, base_angle=45.0, width=1600, height=1600, focal=2400.0,
                               base_to_height=0.35, terrain="hilly", name="diagonal_base"),
    "portrait_wide": SceneSpec(seed=15, width=1200, height=2000, focal=1500.0, principal_offset=(-150.0, 200.0),
                               base_angle=90.0, base_to_height=0.6, heading=250.0, layout="dense", trees="over",
                               distortion=(-0.06, 0.015, 0.0004, -0.0003), name="portrait_wide"),
    "narrow_base": SceneSpec(seed=16, base_to_height=0.1, width=2000, height=1400, focal=4000.0, heading=315.0,
                             layout="sparse", name="narrow_base"),
    "wide_base": SceneSpec(seed=17, base_to_height=1.0, width=2000, height=1500, focal=900.0, heading=135.0,
                           attitude=4.0, trees="over", distortion=(-0.03, 0.004, 0.0, 0.0), name="wide_base"),
    "strip_of_3": SceneSpec(seed=18, images_per_strip=3, base_to_height=0.25, focal=3000.0, heading=60.0,
                            name="strip_of_3"),
    "block_2x3": SceneSpec(seed=19, strips=2, images_per_strip=3, base_to_height=0.25, heading=200.0,
                           side_overlap=0.3, terrain="hilly", trees="over", name="block_2x3"),
}


def random_spec(seed: int) -> SceneSpec:
    """A survey drawn from the ranges of the module table, deterministic for ``seed``."""
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), 90]))
    aspect = float(np.exp(rng.uniform(math.log(0.5), math.log(2.0))))
    pixels = 3.0e6
    width = int(round(math.sqrt(pixels * aspect) / 8) * 8)
    height = int(round(width / aspect / 8) * 8)
    base_angle = float(rng.choice([0.0, 90.0, 45.0, -90.0, 180.0]))
    beta = math.radians(base_angle)
    along = width * abs(math.cos(beta)) + height * abs(math.sin(beta))
    side = max(width, height)
    b_h = float(rng.uniform(0.1, 1.0))
    overlap = float(rng.uniform(0.55, 0.8))
    focal = float(np.clip((1.0 - overlap) * along / b_h, 0.35 * side, 3.0 * side))
    # the clip may leave less overlap than 55 %: narrow the base instead
    b_h = min(b_h, 0.45 * along / focal)
    blocks = [(1, 2), (1, 2), (1, 2), (1, 3), (2, 3)]
    strips, per_strip = blocks[int(rng.integers(len(blocks)))]
    return SceneSpec(
        seed=int(seed),
        width=width,
        height=height,
        focal=round(focal, 1),
        principal_offset=tuple(float(v) for v in np.round(rng.uniform(-0.15, 0.15, 2) * [width, height], 1)),
        gsd=round(float(rng.uniform(0.1, 0.5)), 3),
        heading=round(float(rng.uniform(0.0, 360.0)), 1),
        base_angle=base_angle,
        base_to_height=round(b_h, 3),
        attitude=round(float(rng.uniform(0.5, 5.0)), 2),
        strips=strips,
        images_per_strip=per_strip,
        side_overlap=0.3,
        distortion=_distortion(rng),
        terrain=str(rng.choice(["flat", "gentle", "slope", "hilly"])),
        layout=str(rng.choice(["regular", "dense", "sparse"])),
        trees=str(rng.choice(["beside", "over"])),
        name=f"random_{seed}",
    )


def _distortion(rng: np.random.Generator) -> tuple[float, float, float, float]:
    if rng.random() < 0.5:
        return (0.0, 0.0, 0.0, 0.0)
    k1 = float(rng.uniform(-0.08, 0.05))
    return (round(k1, 4), round(float(-0.2 * k1 * rng.uniform(0.5, 1.5)), 5),
            round(float(rng.uniform(-5e-4, 5e-4)), 6), round(float(rng.uniform(-5e-4, 5e-4)), 6))


def family(n: int, *, start: int = 0) -> list[SceneSpec]:
    """The named configurations, then ``n`` random surveys (seeds ``start`` ...)."""
    return [*CONFIGURATIONS.values(), *(random_spec(start + k) for k in range(n))]
