"""`recon export`: hand a `recon run` model to the tools that come next.

Formats (`FORMATS`), each written into one folder `DIR` (default `OUT_DIR/export/<format>`):

* `colmap-text`: `DIR/sparse/0/{cameras,images,points3D}.txt` (+ COLMAP's `rigs.txt`,
  `frames.txt`), the model as it is, for tools that read COLMAP's text format.
* `3dgs`: the layout Gaussian-splatting trainers read (graphdeco's `train.py -s DIR`, gsplat's
  COLMAP parser, nerfstudio's `colmap` dataparser): `DIR/images/` undistorted by
  `pycolmap.undistort_images` and `DIR/sparse/0/*.bin` with PINHOLE cameras only.
* `nerfstudio`: `DIR/transforms.json` in nerfstudio's format (`recon.export.nerfstudio`),
  `DIR/images/`, `DIR/sparse_pc.ply` (splatfacto's initial points) and the model the json
  describes in `DIR/colmap/sparse/0` (the layout `ns-process-data` leaves), so both
  `ns-train ... --data DIR` (nerfstudio-data) and nerfstudio's `colmap` dataparser read it.
  Undistorted PINHOLE by default; `undistort=False` keeps the original images and writes the
  distortion as nerfstudio's OPENCV k1, k2, p1, p2.

Every export is built in a temporary sibling folder and renamed into place (`recon.export.target`).
"""

from __future__ import annotations

from recon.export.api import FORMATS, ExportConfig, ExportResult, export_run

__all__ = ["FORMATS", "ExportConfig", "ExportResult", "export_run"]
