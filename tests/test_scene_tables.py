"""The scene benchmark tables report the share of observations in inconsistent tracks
(`benchmarks/scene_tables.py` for the README, `recon.eval.compare.scenes_table` / `compare_table`
for the console)."""

from __future__ import annotations

import importlib.util

from rich.console import Console

from recon.eval.compare import compare_table, inconsistent_share, scenes_table
from shared_paths import REPO

_spec = importlib.util.spec_from_file_location("scene_tables", REPO / "benchmarks" / "scene_tables.py")
assert _spec is not None and _spec.loader is not None
scene_tables = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(scene_tables)


def _methods():
    pairs = [{"image0": "a", "image1": "b", "verified_inliers": 100}]
    ours = {"status": "ok", "registered_images": 2, "num_images": 2, "num_points3D": 10, "pairs": pairs,
            "tracks": {"merged": {"inconsistent_share": 0.0}, "raw_merged": {"inconsistent_share": 0.5}}}
    stock = {"status": "ok", "registered_images": 2, "num_images": 2, "num_points3D": 12, "pairs": pairs,
             "tracks": {"graph": {"inconsistent_share": 0.0957}}}
    old = {"status": "ok", "registered_images": 2, "num_images": 2, "pairs": pairs,
           "tracks": {"graph": {"inconsistent": 3}}}  # written before the share was measured
    return {"stock-default": stock, "extra_affine": ours, "stock-high": old}


def test_inconsistent_share_reads_ours_and_stock():
    m = _methods()
    assert inconsistent_share(m["extra_affine"]) == 0.0  # the verified graph, not raw_merged
    assert inconsistent_share(m["stock-default"]) == 0.0957
    assert inconsistent_share(m["stock-high"]) is None and inconsistent_share({}) is None


def test_readme_table_has_the_inconsistent_column():
    lines = scene_tables.rows({"scenes": [{"scene": "/x/castle", "methods": _methods()}]})
    header = [c.strip() for c in lines[0].strip("|").split("|")]
    col = header.index("inconsistent tracks (obs.)")
    cells = {ln.split("|")[2].strip(): ln.strip("|").split("|")[col].strip() for ln in lines[2:]}
    assert cells == {"stock default": "9.6 %", "extra-affine": "0.0 %", "stock high": "-"}
    assert all(ln.count("|") == lines[0].count("|") for ln in lines)


def test_console_tables_show_the_share():
    res = {"scene": "/x/castle", "methods": _methods(), "config": {"max_size": 1000, "pairs": "exhaustive"}}
    console = Console(width=250, record=True)
    console.print(scenes_table([res], 1000))
    console.print(compare_table(res))
    text = console.export_text()
    assert "incons. %" in text and "obs. in inconsistent tracks %" in text
    assert " 9.6 " in text and " 0.0 " in text


def test_readme_table_shows_distinct_inliers_where_the_results_hold_them():
    methods = _methods()
    methods["stock-default"] = {**methods["stock-default"],
                                "pairs": [{"image0": "a", "image1": "b", "verified_inliers": 100, "distinct_inliers": 80}]}
    lines = scene_tables.rows({"scenes": [{"scene": "/x/castle", "methods": methods}]})
    header = [c.strip() for c in lines[0].strip("|").split("|")]
    col = next(i for i, c in enumerate(header) if c.startswith("median verified inliers"))
    cells = {ln.split("|")[2].strip(): ln.strip("|").split("|")[col].strip() for ln in lines[2:]}
    assert cells["stock default"] == "100 / nan (80 / nan distinct)"
    assert cells["extra-affine"] == "100 / nan"  # written before distinct inliers were counted


def test_compare_table_shows_the_rotation_gap_to_stock_with_its_interval():
    res = {"scene": "/x/castle", "methods": _methods(), "config": {"max_size": 1000, "pairs": "exhaustive"},
           "gt": {"source": "strecha"},
           "rotation_gap_by_stock": {"default": {"gap": 0.0084, "ci_low": 0.0036, "ci_high": 0.0143, "a_below_b": 88,
                                                 "num_pairs": 435},
                                     "high": None}}
    res["methods"]["extra_affine"]["rel_rot_err_deg_median"] = 0.06979
    console = Console(width=250, record=True)
    console.print(compare_table(res))
    text = console.export_text()
    line = next(ln for ln in text.splitlines() if "minus stock-default" in ln)
    assert "+0.0084 [+0.0036, +0.0143], lower on 88/435" in line
    assert "minus stock-high" not in text  # no gap where a model is missing
    assert "0.0698" in text  # four decimals: the real scenes' errors are a few hundredths of a degree
