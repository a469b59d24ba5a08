"""Ground-truth readers (`recon.eval.gt`) and the model evaluation (`recon.eval.evaluate`), on small
synthetic fixtures written in tmp_path (no shared data)."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from matching.errors import InputError
from recon.eval.evaluate import evaluate_model, pose_auc, umeyama
from recon.eval.gt import GtCamera, find_gt, quat_to_rot, read_colmap_text, read_strecha, read_strecha_camera


# helpers ----------------------------------------------------------------------------------------
def rot(axis, deg: float) -> np.ndarray:
    a = np.asarray(axis, float)
    a = a / np.linalg.norm(a)
    K = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    th = math.radians(deg)
    return np.eye(3) + math.sin(th) * K + (1 - math.cos(th)) * K @ K


def rot_to_quat(R: np.ndarray) -> np.ndarray:
    """w-first unit quaternion of a rotation (test helper, Shepperd's method via the largest term)."""
    m = R
    tr = np.trace(m)
    if tr > 0:
        s = math.sqrt(tr + 1.0) * 2
        q = [0.25 * s, (m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s]
    else:
        i = int(np.argmax(np.diag(m)))
        j, k = (i + 1) % 3, (i + 2) % 3
        s = math.sqrt(1.0 + m[i, i] - m[j, j] - m[k, k]) * 2
        q = [0.0] * 4
        q[0] = (m[k, j] - m[j, k]) / s
        q[1 + i] = 0.25 * s
        q[1 + j] = (m[j, i] + m[i, j]) / s
        q[1 + k] = (m[k, i] + m[i, k]) / s
    return np.array(q)


def look_at(C, target=(0.0, 0.0, 0.0)) -> np.ndarray:
    """3x4 cam_from_world of a camera at C looking at target (z forward)."""
    C = np.asarray(C, float)
    f = np.asarray(target, float) - C
    f /= np.linalg.norm(f)
    r = np.cross(f, (0, 0, 1.0))
    r /= np.linalg.norm(r)
    R = np.stack([r, np.cross(f, r), f])
    return np.concatenate([R, (-R @ C)[:, None]], 1)


def ring(n: int = 6) -> dict[str, np.ndarray]:
    """n cameras on a tilted arc around the origin (not collinear, not coplanar with the target)."""
    out = {}
    for i in range(n):
        az = math.radians(20 + 25 * i)
        C = np.array([5 * math.cos(az), 5 * math.sin(az), 1.0 + 0.3 * i])
        out[f"img{i:02d}.jpg"] = look_at(C)
    return out


def similarity_transform(poses: dict[str, np.ndarray], s: float, R: np.ndarray, t: np.ndarray):
    """The same cameras in a world X' = s R X + t: cam_from_world' = [Rc R^T | s tc - Rc R^T t]."""
    out = {}
    for n, P in poses.items():
        Rc, tc = P[:, :3], P[:, 3]
        Rn = Rc @ R.T
        out[n] = np.concatenate([Rn, (s * tc - Rn @ t)[:, None]], 1)
    return out


def write_colmap_gt(gt_dir: Path, poses: dict[str, np.ndarray], with_points_lines: bool = True) -> None:
    gt_dir.mkdir(parents=True, exist_ok=True)
    (gt_dir / "cameras.txt").write_text(
        "# Camera list with one line of data per camera:\n"
        "#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]\n"
        "1 PINHOLE 640 480 500 510 320.5 240.5\n"
        "2 SIMPLE_RADIAL 800 600 700 400 300 0.01\n")
    lines = ["# Image list with two lines of data per image:", "#   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME",
             "#   POINTS2D[] as (X, Y, POINT3D_ID)"]
    for k, (name, P) in enumerate(poses.items()):
        q = rot_to_quat(P[:, :3])
        if k % 2:
            q = -q  # q and -q are the same rotation
        t = P[:, 3]
        lines.append(f"{100 + 7 * k} {' '.join(f'{v:.17g}' for v in q)} {' '.join(f'{v:.17g}' for v in t)} "
                     f"{1 + k % 2} {name}")
        if with_points_lines:
            lines.append("" if k % 2 else "10.5 20.5 -1 30.0 40.0 7")
    (gt_dir / "images.txt").write_text("\n".join(lines) + "\n")


def write_strecha_file(path: Path, K: np.ndarray, P: np.ndarray, size=(3072, 2048)) -> None:
    R_file = P[:, :3].T  # the file's R: x_cam = R^T (X - C)
    C = -P[:, :3].T @ P[:, 3]
    rows = [*(" ".join(f"{v:.17g}" for v in r) for r in K), "0 0 0",
            *(" ".join(f"{v:.17g}" for v in r) for r in R_file), " ".join(f"{v:.17g}" for v in C),
            f"{size[0]} {size[1]}"]
    path.write_text("\n".join(rows) + "\n")


def make_scene(root: Path, names) -> Path:
    (root / "images").mkdir(parents=True, exist_ok=True)
    for n in names:
        (root / "images" / n).write_bytes(b"")  # only the names matter to find_gt
    return root


# COLMAP text ------------------------------------------------------------------------------------
def test_quat_to_rot_roundtrip():
    for axis, deg in [((1, 0, 0), 30), ((0.3, -1, 2), 170), ((0, 0, 1), -95)]:
        R = rot(axis, deg)
        assert np.allclose(quat_to_rot(*rot_to_quat(R)), R, atol=1e-12)
        assert np.allclose(quat_to_rot(*(-rot_to_quat(R))), R, atol=1e-12)


@pytest.mark.parametrize("with_points_lines", [True, False])
def test_read_colmap_text(tmp_path, with_points_lines):
    poses = ring(4)
    write_colmap_gt(tmp_path / "gt", poses, with_points_lines)
    gt = read_colmap_text(tmp_path / "gt")
    assert sorted(gt) == sorted(poses)
    for n, P in poses.items():
        assert np.allclose(gt[n].cam_from_world, P, atol=1e-12)
    c0 = gt["img00.jpg"]
    assert c0.size == (640, 480)
    # COLMAP's principal point (pixel centre at 0.5) -> OpenCV convention (centre at 0)
    assert np.allclose(c0.K, [[500, 0, 320.0], [0, 510, 240.0], [0, 0, 1]])
    c1 = gt["img01.jpg"]
    assert c1.size == (800, 600) and np.allclose(c1.K, [[700, 0, 399.5], [0, 700, 299.5], [0, 0, 1]])
    P0 = poses["img00.jpg"]
    assert np.allclose(c0.center, -P0[:, :3].T @ P0[:, 3])


def test_colmap_camera_models_from_pycolmap_and_names_with_spaces(tmp_path):
    """Every COLMAP model pycolmap knows gives K from its focal / principal-point parameters;
    a model without them is refused; an image name with spaces is kept whole."""
    gt = tmp_path / "gt"
    gt.mkdir()
    (gt / "cameras.txt").write_text(
        "1 OPENCV_FISHEYE 640 480 500 510 320.5 240.5 0.1 0.01 0 0\n"
        "2 FOV 640 480 400 410 300.5 200.5 0.9\n"
        "3 EUCM 640 480 450 460 330.5 250.5 0.5 1.0\n"
        "4 SIMPLE_DIVISION 640 480 600 310.5 230.5 -0.1\n")
    (gt / "images.txt").write_text("".join(f"{k} 1 0 0 0 0 0 {k} {k} my photo {k}.jpg\n\n" for k in (1, 2, 3, 4)))
    out = read_colmap_text(gt)
    assert sorted(out) == [f"my photo {k}.jpg" for k in (1, 2, 3, 4)]
    K = {k: out[f"my photo {k}.jpg"].K for k in (1, 2, 3, 4)}
    assert np.allclose(K[1], [[500, 0, 320], [0, 510, 240], [0, 0, 1]])
    assert np.allclose(K[2], [[400, 0, 300], [0, 410, 200], [0, 0, 1]])
    assert np.allclose(K[3], [[450, 0, 330], [0, 460, 250], [0, 0, 1]])
    assert np.allclose(K[4], [[600, 0, 310], [0, 600, 230], [0, 0, 1]])
    (gt / "cameras.txt").write_text("1 EQUIRECTANGULAR 640 480 640 480\n")
    with pytest.raises(InputError, match=r"cameras\.txt:1: camera model EQUIRECTANGULAR has no focal length"):
        read_colmap_text(gt)


def test_find_gt_colmap_and_unknown_image(tmp_path):
    poses = ring(3)
    scene = make_scene(tmp_path / "s", poses)
    write_colmap_gt(scene / "gt", poses)
    gt = find_gt(scene)
    assert gt is not None and sorted(gt) == sorted(poses)
    # GT naming an image the scene lacks -> InputError naming the file
    (scene / "images" / "img01.jpg").unlink()
    with pytest.raises(InputError, match=r"images\.txt.*img01\.jpg"):
        find_gt(scene)


def test_find_gt_none(tmp_path):
    scene = make_scene(tmp_path / "s", ["a.jpg", "b.jpg"])
    assert find_gt(scene) is None
    (scene / "gt").mkdir()
    (scene / "gt" / "K.txt").write_text("1 0 0\n0 1 0\n0 0 1\n")  # intrinsics only: no GT poses
    assert find_gt(scene) is None


@pytest.mark.parametrize("cameras, images, match", [
    ("1 PINHOLE 640 480 500 510 320\n", None, r"cameras\.txt:1: .*PINHOLE takes 4"),
    ("1 NOT_A_MODEL 640 480 1 2 3\n", None, r"cameras\.txt:1: unknown camera model"),
    ("1 PINHOLE 640 480 500 abc 320 240\n", None, r"cameras\.txt:1: expected numbers"),
    (None, "1 1 0 0 0 0 0 0 1\n", r"images\.txt:1: expected IMAGE_ID"),
    (None, "1 1 0 0 0 0 0 0 9 a.jpg\n\n", r"images\.txt:1: .*camera 9"),
    (None, "1 1 0 0 x 0 0 0 1 a.jpg\n\n", r"images\.txt:1: expected numbers"),
    (None, "1 0 0 0 0 0 0 0 1 a.jpg\n\n", r"images\.txt:1: zero quaternion"),
])
def test_colmap_malformed(tmp_path, cameras, images, match):
    gt = tmp_path / "gt"
    gt.mkdir()
    (gt / "cameras.txt").write_text(cameras or "1 PINHOLE 640 480 500 500 320 240\n")
    (gt / "images.txt").write_text(images or "1 1 0 0 0 0 0 0 1 a.jpg\n\n")
    with pytest.raises(InputError, match=match):
        read_colmap_text(gt)


# Strecha ----------------------------------------------------------------------------------------
def test_read_strecha(tmp_path):
    K = np.array([[2759.48, 0, 1520.69], [0, 2764.16, 1006.81], [0, 0, 1]])
    poses = ring(3)
    d = tmp_path / "gt" / "cameras"
    d.mkdir(parents=True)
    for n, P in poses.items():
        write_strecha_file(d / f"{n}.camera", K, P)
    gt = read_strecha(d)
    assert sorted(gt) == sorted(poses)
    for n, P in poses.items():
        assert np.allclose(gt[n].cam_from_world, P, atol=1e-9)
        assert np.allclose(gt[n].K, K) and gt[n].size == (3072, 2048)
    # the projection convention: x ~ K R^T (X - C) with the file's R and C
    X = np.array([0.3, -0.2, 0.5])
    lines = (d / "img00.jpg.camera").read_text().split("\n")
    R_file = np.array([[float(v) for v in lines[i].split()] for i in (4, 5, 6)])
    C = np.array([float(v) for v in lines[7].split()])
    x_file = K @ R_file.T @ (X - C)
    c = gt["img00.jpg"]
    x_ours = c.K @ (c.R @ X + c.t)
    assert np.allclose(x_file / x_file[2], x_ours / x_ours[2])


def test_strecha_real_example_format(tmp_path):
    """The exact text of fountain_P11's 0000.jpg.camera (trailing spaces included)."""
    p = tmp_path / "0000.jpg.camera"
    p.write_text("2759.48 0 1520.69 \n0 2764.16 1006.81 \n0 0 1 \n0 0 0\n0.450927 -0.0945642 -0.887537 \n"
                 "-0.892535 -0.0401974 -0.449183 \n0.00679989 0.994707 -0.102528 \n-7.28137 -7.57667 0.204446 \n"
                 "3072 2048\n")
    c = read_strecha_camera(p)
    assert c.size == (3072, 2048)
    assert np.allclose(c.center, [-7.28137, -7.57667, 0.204446], atol=1e-5)
    assert np.allclose(c.R @ c.R.T, np.eye(3), atol=1e-5)


@pytest.mark.parametrize("text, match", [
    ("1 0 0\n0 1 0\n0 0 1\n0 0 0\n1 0 0\n0 1 0\n0 0 1\n0 0 0\n", r"expected 9 lines"),
    ("1 0 0\n0 1 0\n0 0 1\n0 0 0\n1 0 0\n0 1 0\n0 0 1\n0 0\n640 480\n", r":8: expected 3 numbers"),
    ("1 0 0\n0 1 0\n0 0 1\n0 0 0\n1 0 0\n0 1 0\n0 0 1\n0 0 0\n640 480 3\n", r":9: expected 2 numbers"),
    ("1 0 0\n0 1 0\n0 0 1\n0 0 0\n2 0 0\n0 1 0\n0 0 1\n0 0 0\n640 480\n", r"not a rotation"),
    ("1 0 0\n0 1 0\n0 0 1\n0 0 0\n1 0 0\n0 1 0\n0 0 1\n0 nan 0\n640 480\n", r":8: non-finite"),
    ("1 0 0\n0 1 0\n0 0 1\n0 0 0\n1 0 0\n0 1 0\n0 0 1\n0 0 0\n640 -1\n", r"must be positive"),
    ("a 0 0\n0 1 0\n0 0 1\n0 0 0\n1 0 0\n0 1 0\n0 0 1\n0 0 0\n640 480\n", r":1: expected numbers"),
])
def test_strecha_malformed(tmp_path, text, match):
    d = tmp_path / "scene" / "gt" / "cameras"
    d.mkdir(parents=True)
    p = d / "bad.jpg.camera"
    p.write_text(text)
    with pytest.raises(InputError, match=match) as ei:
        read_strecha(d)
    assert "bad.jpg.camera" in str(ei.value)


def test_find_gt_strecha_unknown_image(tmp_path):
    K = np.diag([1000.0, 1000.0, 1.0])
    poses = ring(3)
    scene = make_scene(tmp_path / "s", list(poses)[:2])  # the scene lacks img02.jpg
    d = scene / "gt" / "cameras"
    d.mkdir(parents=True)
    for n, P in poses.items():
        write_strecha_file(d / f"{n}.camera", K, P)
    with pytest.raises(InputError, match=r"img02\.jpg\.camera.*img02\.jpg"):
        find_gt(scene)
    assert sorted(find_gt(scene, check_names=False)) == sorted(poses)


def test_real_fountain_gt(scene_dir):
    scene = scene_dir("fountain_P11", "gt")
    gt = find_gt(scene)
    assert gt is not None and len(gt) == 11 and all(isinstance(c, GtCamera) for c in gt.values())


# evaluation -------------------------------------------------------------------------------------
def test_umeyama_recovers_similarity():
    rng = np.random.default_rng(0)
    src = rng.normal(size=(10, 3))
    R = rot((1, 2, 3), 40)
    dst = 3.0 * src @ R.T + [1, -2, 5]
    s, Re, t = umeyama(src, dst)
    assert s == pytest.approx(3.0) and np.allclose(Re, R) and np.allclose(t, [1, -2, 5])
    with pytest.raises(ValueError):
        umeyama(src[:2], dst[:2])
    with pytest.raises(ValueError):  # collinear
        umeyama(np.outer(np.arange(4.0), [1, 1, 0]), np.outer(np.arange(4.0), [0, 1, 1]))


def _umeyama_reference(src, dst):
    """Umeyama (1991) in closed form with numpy: the implementation pycolmap replaced."""
    mu_s, mu_d = src.mean(0), dst.mean(0)
    xs, xd = src - mu_s, dst - mu_d
    U, D, Vt = np.linalg.svd(xd.T @ xs / len(src))
    S = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        S[2, 2] = -1.0
    R = U @ S @ Vt
    s = float(np.trace(np.diag(D) @ S) / ((xs ** 2).sum() / len(src)))
    return s, R, mu_d - s * R @ mu_s


def test_umeyama_matches_the_closed_form_on_noisy_points():
    """pycolmap's estimate_sim3d gives the closed form's numbers (1e-9 relative) where the
    similarity does not fit exactly, including a reflection-prone case (det(U) det(V) < 0)."""
    rng = np.random.default_rng(1)
    for k in range(200):
        n = int(rng.integers(3, 40))
        src = rng.normal(size=(n, 3)) * rng.uniform(0.1, 100)
        R = rot(rng.normal(size=3), rng.uniform(-180, 180))
        dst = rng.uniform(0.01, 50) * src @ R.T + rng.normal(size=3) * 10 + rng.normal(size=(n, 3)) * rng.uniform(0, 2)
        if k == 0:
            dst = src * [1, 1, -1]  # a mirror image: the best rotation needs the sign correction
        got = np.concatenate([[umeyama(src, dst)[0]], umeyama(src, dst)[1].ravel(), umeyama(src, dst)[2]])
        s, Rr, t = _umeyama_reference(src, dst)
        want = np.concatenate([[s], Rr.ravel(), t])
        assert np.abs(got - want).max() <= 1e-9 * np.abs(want).max()
    # without scale: a rigid motion
    src = rng.normal(size=(8, 3))
    R = rot((0, 1, 1), 25)
    s, Re, t = umeyama(src, src @ R.T + [0.5, 0, 0], with_scale=False)
    assert s == 1.0 and np.allclose(Re, R) and np.allclose(t, [0.5, 0, 0])


def test_pose_auc():
    assert pose_auc([0.0, 0.0, 0.0]) == pytest.approx([1.0, 1.0, 1.0])
    assert pose_auc([math.inf, math.inf]) == pytest.approx([0.0, 0.0, 0.0])
    # one exact pair, one failure: recall 0.5 everywhere
    assert pose_auc([0.0, math.inf]) == pytest.approx([0.5, 0.5, 0.5])
    # a single error of 5 deg: the recall curve runs (0, 0) -> (5, 1) (trapezoid), then stays at 1
    assert pose_auc([5.0], [5, 10, 20]) == pytest.approx([0.0, 0.75, 0.875])
    # two errors 2 and 4 deg, AUC@5: area 0.5*2*0.5 + 2*(0.5+1)/2 + 1*1 = 3 -> 0.6
    assert pose_auc([4.0, 2.0], [5]) == pytest.approx([0.6])


def test_evaluate_similarity_gives_zero_error():
    gt = ring(6)
    est = similarity_transform(gt, 3.0, rot((0.2, 1, -0.5), 75), np.array([10.0, -4, 2]))
    gt_cams = {n: GtCamera(np.eye(3), P, (640, 480)) for n, P in gt.items()}
    r = evaluate_model(est, gt_cams)
    assert r["num_pairs"] == 15 and r["num_pairs_evaluated"] == 15
    assert r["rel_rot_err_deg_median"] < 1e-5 and r["rel_trans_err_deg_median"] < 1e-5
    assert r["auc_5"] == pytest.approx(1.0, abs=1e-6) and r["auc_20"] == pytest.approx(1.0, abs=1e-6)
    assert r["center_err_median"] < 1e-9 and r["center_err_rel_median"] < 1e-9
    assert r["alignment"]["scale"] == pytest.approx(1 / 3.0)


def test_evaluate_perturbed_rotation():
    gt = ring(5)
    est = similarity_transform(gt, 0.5, rot((1, 0, 0), 20), np.zeros(3))
    n0 = "img02.jpg"
    # rotate camera img02 about its own centre by 4 deg (centre unchanged)
    P = est[n0]
    C = -P[:, :3].T @ P[:, 3]
    Rn = rot((0, 1, 0), 4.0) @ P[:, :3]
    est[n0] = np.concatenate([Rn, (-Rn @ C)[:, None]], 1)
    r = evaluate_model(est, gt)
    errs = {(p["image0"], p["image1"]): p["rot_err_deg"] for p in r["pairs"]}
    for (a, b), e in errs.items():
        assert e == pytest.approx(4.0 if n0 in (a, b) else 0.0, abs=1e-6)
    assert r["num_pairs"] == 10
    assert r["rel_rot_err_deg_median"] == pytest.approx(0.0, abs=1e-6)  # 4 of 10 pairs involve img02
    # centres are untouched: alignment is exact
    assert r["center_err_median"] < 1e-9
    # the 4 pairs with img02 have max(rot, trans) = 4 deg (the translation direction seen from a
    # rotated camera turns by at most 4 deg too); sorted errors 0 x6, 4 x4: the recall curve runs
    # (0, 0.6) -> (4, 0.7), jumps to 1 at 4 and stays there: (4 * 0.65 + 1 * 1) / 5 = 0.72
    assert r["auc_5"] == pytest.approx(0.72)


def test_evaluate_by_name_not_by_id_or_order():
    gt = ring(5)
    est = similarity_transform(gt, 2.0, rot((0, 0, 1), 90), np.array([1.0, 2, 3]))
    shuffled = {n: est[n] for n in reversed(list(est))}  # other order ("ids" differ)
    gt_cams = {n: GtCamera(np.eye(3), P, (10, 10)) for n, P in sorted(gt.items())}
    r = evaluate_model(shuffled, gt_cams)
    assert r["rel_rot_err_deg_median"] < 1e-6 and r["center_err_median"] < 1e-9

    # a model with swapped poses of two names is wrong, whatever the order of the dict
    wrong = dict(shuffled)
    wrong["img00.jpg"], wrong["img04.jpg"] = shuffled["img04.jpg"], shuffled["img00.jpg"]
    r2 = evaluate_model(wrong, gt_cams)
    assert r2["center_err_median"] > 0.1 and r2["auc_5"] < 0.9


def test_evaluate_unregistered_counts_as_failure():
    gt = ring(4)
    est = {n: P for n, P in gt.items() if n != "img03.jpg"}  # 3 of 4 registered
    est["extra.jpg"] = look_at([1.0, 2, 3])  # an image without GT is ignored
    r = evaluate_model(est, gt)
    assert r["num_pairs"] == 6 and r["num_pairs_evaluated"] == 3 and r["num_registered_with_gt"] == 3
    assert r["auc_5"] == pytest.approx(0.5) and r["auc_20"] == pytest.approx(0.5)
    assert r["rel_rot_err_deg_median"] < 1e-6
    # too few images for the alignment -> None, never an exception
    r2 = evaluate_model({n: gt[n] for n in list(gt)[:2]}, gt)
    assert r2["center_err_median"] is None and r2["auc_5"] == pytest.approx(1 / 6)
    r3 = evaluate_model(None, gt)
    assert r3["auc_10"] == 0.0 and r3["rel_rot_err_deg_median"] is None


def test_evaluate_accepts_4x4_and_translation_error():
    gt = ring(4)
    est = {}
    for n, P in gt.items():
        M = np.eye(4)
        M[:3] = P
        est[n] = M
    # move one camera centre sideways: translation-direction errors appear, rotations stay exact
    P = gt["img01.jpg"]
    C = -P[:, :3].T @ P[:, 3] + np.array([0.0, 0.0, 1.0])
    est["img01.jpg"] = np.concatenate([P[:, :3], (-P[:, :3] @ C)[:, None]], 1)
    r = evaluate_model(est, gt)
    rows = {(p["image0"], p["image1"]): p for p in r["pairs"]}
    assert all(p["rot_err_deg"] < 1e-6 for p in rows.values())
    assert rows[("img00.jpg", "img01.jpg")]["trans_err_deg"] > 1.0
    assert rows[("img00.jpg", "img02.jpg")]["trans_err_deg"] < 1e-6


def _perturbed(poses: dict[str, np.ndarray], deg: float, seed: int) -> dict[str, np.ndarray]:
    """Each camera turned about its own centre by `deg` about a random axis (seeded)."""
    rng = np.random.default_rng(seed)
    out = {}
    for n, P in poses.items():
        C = -P[:, :3].T @ P[:, 3]
        Rn = rot(rng.normal(size=3), deg) @ P[:, :3]
        out[n] = np.concatenate([Rn, (-Rn @ C)[:, None]], 1)
    return out


def test_paired_rotation_gap_tells_a_worse_model_from_the_images_drawn():
    from recon.eval.evaluate import paired_rotation_gap

    gt = ring(14)
    pairs = {k: evaluate_model(_perturbed(gt, deg, seed), gt)["pairs"]
             for k, deg, seed in (("worse", 0.2, 1), ("good", 0.1, 2), ("good_too", 0.1, 3))}
    g = paired_rotation_gap(pairs["worse"], pairs["good"])
    assert g is not None and g["num_pairs"] == 91 and g["num_images"] == 14
    assert g["gap"] == pytest.approx(g["median_a"] - g["median_b"]) and g["gap"] > 0.05
    assert 0 < g["ci_low"] <= g["gap"] <= g["ci_high"]  # twice the noise: a real gap
    assert g["a_below_b"] < 91 // 4
    same = paired_rotation_gap(pairs["good"], pairs["good_too"])
    assert same is not None and same["ci_low"] < 0 < same["ci_high"]  # the same noise: no gap
    assert paired_rotation_gap(pairs["good"], pairs["good_too"]) == same  # deterministic for a seed
    # the errors are the cameras', so resampling the images, not the pairs, sets the width
    ea, eb = (np.array([p["rot_err_deg"] for p in pairs[k]]) for k in ("good", "good_too"))
    rng = np.random.default_rng(0)
    draws = rng.integers(0, len(ea), (2000, len(ea)))
    by_pairs = np.median(ea[draws], axis=1) - np.median(eb[draws], axis=1)
    pair_width = float(np.subtract(*np.percentile(by_pairs, [97.5, 2.5])))
    assert same["ci_high"] - same["ci_low"] > 1.3 * pair_width
    own = paired_rotation_gap(pairs["good"], pairs["good"])
    assert own is not None and own["gap"] == own["ci_low"] == own["ci_high"] == 0.0


def test_paired_rotation_gap_needs_shared_finite_pairs():
    from recon.eval.evaluate import paired_rotation_gap

    gt = ring(4)
    full = evaluate_model(gt, gt)["pairs"]
    two = {n: gt[n] for n in list(gt)[:2]}  # the other images unregistered: infinite errors
    assert paired_rotation_gap(full, evaluate_model(two, gt)["pairs"]) is None
    assert paired_rotation_gap(full, []) is None
