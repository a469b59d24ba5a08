"""recon: scenes -> extra-affine matches -> COLMAP database -> SfM -> outputs, CLI and visualisation."""
