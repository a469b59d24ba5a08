"""`python -m recon ...` runs the CLI (same as the `recon` console script).

The guard matters: Dask's local worker processes are spawned and re-import the main module,
which must not start another run (`--engine dask`).
"""

import sys

from recon.cli import main

if __name__ == "__main__":
    sys.exit(main())
