"""The tool's version and the versions of the libraries that shape its results (for report.json)."""

from __future__ import annotations

import platform

DISTRIBUTION = "recon-affine"
"""The name on the package index (`pip install recon-affine`): `recon` and `matching` there are
other projects. The import packages stay `recon`, `matching` and `scenes`."""


def version() -> str:
    """The installed distribution's version (pyproject.toml's), or "unknown" from a bare checkout."""
    from importlib.metadata import PackageNotFoundError, metadata

    # an install made before the rename is registered as `recon`: ours when its summary is ours
    for dist in (DISTRIBUTION, "recon"):
        try:
            meta = metadata(dist)
        except PackageNotFoundError:
            continue
        if dist == DISTRIBUTION or ((meta.get_all("Summary") or [""])[0] or "").startswith("Extra-affine"):
            return str(meta["Version"])
    return "unknown"


def library_versions() -> dict[str, str]:
    """{"recon", "python", "pycolmap", "opencv", "numpy"}: what a report was made with."""
    import cv2
    import numpy
    import pycolmap

    return {"recon": version(), "python": platform.python_version(), "pycolmap": str(pycolmap.__version__),
            "opencv": str(cv2.__version__), "numpy": str(numpy.__version__)}
