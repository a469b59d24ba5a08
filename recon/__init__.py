"""recon: scenes -> extra-affine matches -> COLMAP database -> SfM -> outputs, CLI and visualisation.

Two things happen on import, both before any heavy module loads:

* the `recon` program installs its Ctrl-C / SIGTERM handlers (`recon._signals`), so an
  interrupt during start-up gives one line, never a traceback;
* OpenCV is imported before any module can import pycolmap: the pycolmap 4.2 wheel bundles its
  own zlib, and when it is loaded first OpenCV's libpng frees through it, so the first
  `cv2.imwrite` / `cv2.imencode` of a PNG aborts the process ("free(): invalid pointer"). With
  OpenCV loaded first both work (tests/test_import_order.py). Scripts that import pycolmap
  themselves should import cv2 (or recon) before it.
"""

from recon import _signals

if _signals.is_program_entry():  # the `recon` program: Ctrl-C / SIGTERM handled before any heavy import
    _signals.install_early()

import cv2 as _cv2  # noqa: E402, F401  (load order, see above)
