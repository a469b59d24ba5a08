"""Importing recon makes PNG encoding safe even when pycolmap is imported right after it.

The pycolmap 4.2 wheel bundles a zlib that OpenCV's libpng frees through when pycolmap is
loaded first, aborting the process on the first PNG write (see recon/__init__.py). Runs in a
subprocess because the failure is an abort, not an exception.
"""

from __future__ import annotations

import subprocess
import sys

SCRIPT = """
import recon, pycolmap, cv2, numpy as np
ok, buf = cv2.imencode(".png", np.full((64, 64, 3), 128, np.uint8))
assert ok and len(buf) > 0
print("png ok")
"""


def test_png_encoding_survives_pycolmap_after_recon():
    res = subprocess.run([sys.executable, "-c", SCRIPT], capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stderr[-2000:]
    assert "png ok" in res.stdout
