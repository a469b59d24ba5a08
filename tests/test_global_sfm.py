"""The global mapper (`recon.core.global_sfm`) on a database written by the pipeline."""

from __future__ import annotations

import pytest

from recon.core import global_sfm as G
from recon.log import quiet_colmap


def test_options_are_seeded_and_cpu_only():
    o = G.global_options(seed=5, num_threads=1)
    assert o.random_seed == 5 and o.mapper.random_seed == 5 and o.mapper.rotation_averaging.random_seed == 5
    assert o.min_num_matches == 15 and o.min_model_size == 3
    assert not o.mapper.global_positioning.use_gpu and not o.mapper.bundle_adjustment.ceres.use_gpu
    assert not o.mapper.bundle_adjustment.refine_principal_point
    assert G.options_summary(o)["mapper"] == "global"


def test_unknown_mapper_is_one_line(tmp_path):
    with pytest.raises(ValueError) as e:
        G.run_mapper("hierarchical", tmp_path / "database.db", tmp_path)
    assert "incremental, global" in str(e.value) and "\n" not in str(e.value)


@pytest.fixture(scope="module")
def facade6_db(tmp_path_factory):
    """The pipeline's database of a 6-view facade sweep (+-30 deg, 320x240), SIFT matcher."""
    from recon.core.pipeline import RunConfig, run_scene
    from scenes.render import render_scene

    root = tmp_path_factory.mktemp("facade6")
    render_scene(root / "scene", "facade-6x30", image_size=(320, 240))
    run_scene(root / "scene", RunConfig.from_options(out=root / "out", method="sift", progress=False))
    return root / "scene", root / "out" / "database.db"


def _geometries(db) -> list[tuple]:
    """The database's two-view geometries: (pair, configuration, inliers, has a relative pose)."""
    import pycolmap

    d = pycolmap.Database.open(str(db))
    try:
        ids, geoms = d.read_two_view_geometries()
    finally:
        d.close()
    return [(int(i), int(g.config), len(g.inlier_matches), g.cam2_from_cam1 is not None) for i, g in zip(ids, geoms)]


@pytest.mark.slow
def test_global_mapper_registers_every_image(facade6_db):
    from recon.eval.evaluate import evaluate_model
    from recon.eval.gt import find_gt

    scene, db = facade6_db
    assert G.needs_calibration(db)  # rendered PNGs have no EXIF focal length
    before = _geometries(db)
    updates = []
    with quiet_colmap():
        res = G.run_global(db, scene / "images", G.global_options(seed=0, num_threads=1),
                           on_update=lambda rec: updates.append(rec.num_reg_images()))
    rec = res.reconstruction
    assert rec is not None and rec.num_reg_images() == 6 and res.model_sizes[0] == 6
    assert rec.num_points3D() > 100 and res.growth == [] and res.hook_error is None
    ev = evaluate_model(rec, find_gt(scene), with_pairs=False)
    assert ev["rel_rot_err_deg_median"] < 1.0
    assert updates  # the model-update hook fired

    with quiet_colmap():  # focal-length calibration works on a copy, never on the pipeline's database
        res_cal = G.run_global(db, scene / "images", G.global_options(seed=0, num_threads=1), calibrate=True)
    assert res_cal.reconstruction is not None
    assert _geometries(db) == before
    assert not list(db.parent.glob(".calibrate-*"))

    def bad(_rec):
        raise RuntimeError("sink gone")

    with quiet_colmap():
        res2 = G.run_global(db, scene / "images", G.global_options(seed=0, num_threads=1), on_update=bad,
                            calibrate=False)
    assert res2.reconstruction is not None and res2.reconstruction.num_reg_images() == 6
    assert res2.hook_error == "RuntimeError: sink gone"
