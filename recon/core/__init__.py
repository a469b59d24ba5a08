"""The pipeline core: scene, pairs, tracks, database, SfM, report, and the run."""
