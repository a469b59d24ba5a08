"""recon: scenes -> extra-affine matches -> COLMAP database -> SfM -> outputs, CLI and visualisation."""

from recon import _signals

if _signals.is_program_entry():  # the `recon` program: Ctrl-C / SIGTERM handled before any heavy import
    _signals.install_early()
