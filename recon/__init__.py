"""recon: scenes -> extra-affine matches -> COLMAP database -> SfM -> outputs, CLI and visualisation.

OpenCV is imported here, before any module can import pycolmap: the pycolmap 4.2 wheel bundles
its own zlib, and when it is loaded first OpenCV's libpng frees through it, so the first
`cv2.imwrite` / `cv2.imencode` of a PNG aborts the process ("free(): invalid pointer"). With
OpenCV loaded first both work (tests/test_import_order.py). Scripts that import pycolmap
themselves should import cv2 (or recon) before it.
"""

import cv2 as _cv2  # noqa: F401  (load order, see above)
