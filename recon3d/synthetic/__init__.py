"""Procedural test cities with exact ground truth, rendered to aerial stereo pairs.

- :mod:`recon3d.synthetic.city`: terrain, buildings and trees as meshes, truth rasters
  and check points;
- :mod:`recon3d.synthetic.render`: a convergent, non-rectified pinhole stereo pair
  (COLMAP conventions) and ray-cast rendering with texture, sun and shadows;
- :mod:`recon3d.synthetic.scene`: the scene folder (images, COLMAP model, georef.json,
  truth/).
"""

from recon3d.synthetic.city import SyntheticCity, checkpoints, make_city, truth_dsm, truth_dtm
from recon3d.synthetic.scene import SceneInfo, write_scene

__all__ = [
    "SceneInfo",
    "SyntheticCity",
    "checkpoints",
    "make_city",
    "truth_dsm",
    "truth_dtm",
    "write_scene",
]
