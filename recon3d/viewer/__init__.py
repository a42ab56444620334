"""``recon3d view OUT``: a finished run's buildings in the browser, served from localhost.

The page (``static/index.html`` + ``static/viewer.js``, three.js bundled in
``static/three.min.js``: nothing is fetched from the network) shows ``buildings.glb`` on
a ground made of the run's DTM draped with the DSM's hillshade, or with ``ortho.tif``
when the run has one, everything in the city model's local frame.
"""

from recon3d.viewer.server import check_run, serve, site_files, start_server

__all__ = ["check_run", "serve", "site_files", "start_server"]
