"""Visualisation: the Rerun recordings and match pictures."""
