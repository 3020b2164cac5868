"""Appearance maps (eq. 1): building, the map file round trip, and every bad-file case."""

from __future__ import annotations

import json
import zipfile
from pathlib import Path

import cv2
import numpy as np
import pytest

from lino_loc.appearance_map import (
    MAP_FORMAT_VERSION,
    AppearanceMap,
    build_map,
    load_vectors,
)
from lino_loc.dataset import CameraInfo, Dataset, DatasetMeta, DatasetWriter
from lino_loc.errors import LinoLocError
from lino_loc.preprocessing import preprocess, to_vector

W, H = 32, 24
SIZE = (16, 12)


def _scene(x: float, theta: float, rng: np.random.Generator) -> np.ndarray:
    """A smooth pattern that shifts with the pose, plus sensor noise."""
    u = np.arange(W)[None, :] / W
    v = np.arange(H)[:, None] / H
    img = 120 + 60 * np.sin(2 * np.pi * (u + 0.3 * x + theta)) * np.cos(2 * np.pi * (v - 0.2 * x))
    return np.clip(img + rng.normal(0, 3, (H, W)), 0, 255).astype(np.uint8)


@pytest.fixture(scope="module")
def dataset(tmp_path_factory: pytest.TempPathFactory) -> Dataset:
    root = tmp_path_factory.mktemp("ds") / "tiny"
    rng = np.random.default_rng(0)
    cam = CameraInfo(width=W, height=H, fx=25.0, fy=25.0, cx=16.0, cy=12.0, baseline_m=0.075)
    with DatasetWriter(root, DatasetMeta(name="tiny", camera=cam, source="unit test")) as w:
        for i in range(40):
            x, theta = 0.1 * (i % 20), 0.2 * (i // 20)
            depth = rng.uniform(0.5, 4.0, (H, W))
            depth[rng.random((H, W)) < 0.3] = np.nan  # sparse, as real stereo is
            w.add(_scene(x, theta, rng), (x, 0.0, theta), condition="tube" if i % 2 == 0 else "bulb", depth=depth)
    return Dataset.open(root)


@pytest.fixture(scope="module")
def amap(dataset: Dataset) -> AppearanceMap:
    return build_map(dataset, n_features=6, preprocess="histeq", size=SIZE)


@pytest.fixture(scope="module")
def map_file(amap: AppearanceMap, tmp_path_factory: pytest.TempPathFactory) -> Path:
    return amap.save(tmp_path_factory.mktemp("map") / "tiny.map.npz")


def test_build_features_are_eq1_of_each_image(dataset: Dataset, amap: AppearanceMap) -> None:
    ch = amap.channels["intensity"]
    assert ch.features.shape == (40, 6) and ch.features.dtype == np.float32
    assert ch.size == SIZE and ch.preprocess == "histeq" and amap.size == SIZE
    np.testing.assert_array_equal(amap.poses, dataset.poses)
    for i in (0, 17, 39):
        z = to_vector(preprocess(dataset.image(i), "histeq"), SIZE)
        np.testing.assert_allclose(ch.features[i], ch.pca.components @ (z - ch.pca.mean), atol=1e-4)
        np.testing.assert_allclose(ch.project(dataset.image(i)), ch.features[i], atol=1e-4)
    # features are centred (the mean image has y = 0) and ordered by variance
    np.testing.assert_allclose(ch.features.mean(0), 0.0, atol=1e-4)
    var = ch.features.var(0)
    assert np.all(np.diff(var) <= 1e-6)
    np.testing.assert_allclose(var, ch.pca.explained_variance, rtol=1e-3)


def test_threaded_loading_equals_serial(dataset: Dataset) -> None:
    a = load_vectors(dataset, "gradient", SIZE, workers=1)
    seen: list[tuple[int, int]] = []
    b = load_vectors(dataset, "gradient", SIZE, workers=3, chunk=7, progress=lambda d, n: seen.append((d, n)))
    # OpenCV may stripe its filters differently across threads: equal to float32 rounding
    np.testing.assert_allclose(a, b, rtol=1e-6, atol=1e-7)
    assert seen[-1] == (40, 40) and len(seen) == 6


def test_condition_and_argument_checks(dataset: Dataset) -> None:
    tube = build_map(dataset, n_features=3, size=SIZE, condition="tube")
    assert len(tube) == 20 and tube.condition == "tube"
    np.testing.assert_array_equal(tube.poses, dataset.poses[0::2])
    with pytest.raises(LinoLocError, match="no rows with condition 'natural'.*bulb, tube"):
        build_map(dataset, size=SIZE, condition="natural")
    with pytest.raises(LinoLocError, match="allow at most 19"):
        build_map(dataset, n_features=20, size=SIZE, condition="tube")
    with pytest.raises(LinoLocError, match="at most the camera"):
        build_map(dataset, n_features=3, size=(64, 48))
    with pytest.raises(LinoLocError, match="unknown method"):
        build_map(dataset, n_features=3, size=SIZE, preprocess="blur")  # type: ignore[arg-type]


def test_round_trip_bit_exact(amap: AppearanceMap, map_file: Path) -> None:
    back = AppearanceMap.load(map_file)
    assert back.meta.model_dump() == amap.meta.model_dump()
    assert back.info() == {**amap.info(), "file": str(map_file)}
    np.testing.assert_array_equal(back.poses, amap.poses)
    assert back.poses.dtype == np.float64
    a, b = amap.channels["intensity"], back.channels["intensity"]
    for x, y in [
        (a.features, b.features),
        (a.pca.mean, b.pca.mean),
        (a.pca.components, b.pca.components),
        (a.pca.explained_variance, b.pca.explained_variance),
    ]:
        assert x.dtype == y.dtype
        np.testing.assert_array_equal(x, y)
    assert (b.preprocess, b.size, b.method) == (a.preprocess, a.size, a.method)
    assert back.camera == amap.camera and back.source == "unit test" and back.name == "tiny"
    img = np.random.default_rng(3).integers(0, 256, (H, W), dtype=np.uint8)
    np.testing.assert_array_equal(a.project(img), b.project(img))


def test_header_contents(map_file: Path) -> None:
    with np.load(map_file, allow_pickle=False) as z:
        header = json.loads(z["header"].tobytes())
        names = set(z.files)
    assert header["magic"] == "lino-loc-map" and header["format_version"] == MAP_FORMAT_VERSION
    assert len(header["sha256"]) == 64
    ch = header["channels"]["intensity"]
    assert ch["preprocess"] == "histeq" and ch["size"] == list(SIZE) and ch["n_features"] == 6
    assert {"poses", "intensity/features", "intensity/mean", "intensity/components"} <= names
    assert header["camera"]["width"] == W


def test_disparity_channel_round_trip(dataset: Dataset, tmp_path: Path) -> None:
    m = build_map(dataset, n_features=4, size=SIZE, channels=("intensity", "disparity"))
    disp = m.channels["disparity"]
    assert disp.features.shape == (40, 4) and disp.method == "em-missing"
    assert disp.params["units"] == "disparity_px"
    back = AppearanceMap.load(m.save(tmp_path / "d.npz"))
    np.testing.assert_array_equal(back.channels["disparity"].features, disp.features)
    query = 25.0 * 0.075 / dataset.depth(3)  # f B / Z with NaN where no depth
    np.testing.assert_allclose(back.channels["disparity"].project(query), disp.project(query), rtol=1e-6)
    np.testing.assert_allclose(disp.project(query), disp.features[3], rtol=1e-3, atol=1e-3)
    # A map with no stereo match at all observes nothing: NaN features, not the prior mean.
    assert np.all(np.isnan(disp.project(np.full_like(query, np.nan))))
    # the disparity channel may have fewer features than intensity
    few = build_map(dataset, n_features=4, size=SIZE, channels=("intensity", "disparity"), disparity_features=2)
    assert few.channels["disparity"].features.shape == (40, 2) and few.channels["intensity"].features.shape == (40, 4)
    np.testing.assert_array_equal(few.channels["intensity"].features, m.channels["intensity"].features)
    # the disparity rows are read by a thread pool in chunks; without one they are the same
    from lino_loc.appearance_map import _disparity_rows

    pooled = _disparity_rows(dataset, SIZE, 0.25, None, workers=3, chunk=7)
    np.testing.assert_array_equal(pooled, _disparity_rows(dataset, SIZE, 0.25, None, workers=1))
    assert np.isnan(pooled).any() and np.isfinite(pooled).any()


# ----------------------------------------------------------------- bad files
def _fails(path: Path, *needles: str) -> None:
    with pytest.raises(LinoLocError) as info:
        AppearanceMap.load(path)
    msg = str(info.value)
    assert "\n" not in msg and str(path) in msg, msg
    for needle in needles:
        assert needle in msg, f"{needle!r} not in {msg!r}"


def _rewrite(src: Path, dst: Path, header_fn=None, array_fn=None) -> Path:
    with np.load(src, allow_pickle=False) as z:
        arrays = {k: z[k] for k in z.files}
    header = json.loads(arrays["header"].tobytes())
    if header_fn:
        header_fn(header)
    if array_fn:
        array_fn(arrays)
    arrays["header"] = np.frombuffer(json.dumps(header).encode(), dtype=np.uint8)
    with open(dst, "wb") as fh:
        np.savez(fh, **arrays)
    return dst


def test_missing_and_empty(tmp_path: Path) -> None:
    _fails(tmp_path / "none.npz", "no such map file")
    (tmp_path / "empty.npz").write_bytes(b"")
    _fails(tmp_path / "empty.npz", "empty file")


@pytest.mark.parametrize("keep", [0.5, 0.9, 0.999])
def test_truncated(map_file: Path, tmp_path: Path, keep: float) -> None:
    data = map_file.read_bytes()
    bad = tmp_path / "cut.npz"
    bad.write_bytes(data[: int(len(data) * keep)])
    _fails(bad, "truncated or corrupt")


def test_corrupted_bytes_inside_an_array(map_file: Path, tmp_path: Path) -> None:
    data = bytearray(map_file.read_bytes())
    with zipfile.ZipFile(map_file) as zf:
        info = zf.getinfo("intensity/components.npy")
    pos = info.header_offset + 30 + len(info.filename) + 200  # inside the member's data
    data[pos] ^= 0xFF
    bad = tmp_path / "flip.npz"
    bad.write_bytes(bytes(data))
    _fails(bad, "corrupt")


def test_foreign_text_png_npy_npz(tmp_path: Path) -> None:
    (tmp_path / "notes.txt").write_text("hello, this is not a map\n")
    _fails(tmp_path / "notes.txt", "not a lino-loc map file")
    cv2.imwrite(str(tmp_path / "img.png"), np.zeros((4, 4), np.uint8))
    _fails(tmp_path / "img.png", "not a lino-loc map file", "PNG")
    np.save(tmp_path / "arr.npy", np.zeros(3))
    _fails(tmp_path / "arr.npy", "not a lino-loc map file")
    np.savez(tmp_path / "other.npz", weights=np.ones((3, 3)))
    _fails(tmp_path / "other.npz", "not a lino-loc map file")
    np.savez(tmp_path / "hdr.npz", header=np.frombuffer(b'{"magic": "something-else"}', np.uint8))
    _fails(tmp_path / "hdr.npz", "not a lino-loc map file", "magic")
    np.savez(tmp_path / "txt.npz", header=np.array("just text"))
    _fails(tmp_path / "txt.npz", "not a lino-loc map file")


def test_newer_version(map_file: Path, tmp_path: Path) -> None:
    bad = _rewrite(map_file, tmp_path / "v2.npz", header_fn=lambda h: h.update(format_version=2))
    _fails(bad, "format version 2 is newer", "upgrade")


def test_checksum_mismatch(map_file: Path, tmp_path: Path) -> None:
    def tamper(arrays):
        f = arrays["intensity/features"].copy()
        f[0, 0] += 1.0
        arrays["intensity/features"] = f

    _fails(_rewrite(map_file, tmp_path / "t.npz", array_fn=tamper), "checksum mismatch")
    _fails(
        _rewrite(map_file, tmp_path / "extra.npz", array_fn=lambda a: a.update(smuggled=np.zeros(2))),
        "checksum mismatch",
    )


def test_bad_header_and_missing_array(map_file: Path, tmp_path: Path) -> None:
    _fails(
        _rewrite(map_file, tmp_path / "h.npz", header_fn=lambda h: h.pop("camera")),
        "bad map header", "camera",
    )

    def drop(arrays):
        del arrays["intensity/mean"]

    # the checksum (recomputed by a careless tool) would match; the structure check catches it
    from lino_loc.appearance_map import _checksum

    def drop_and_fix(h):
        with np.load(map_file, allow_pickle=False) as z:
            arrays = {k: z[k] for k in z.files if k not in ("header", "intensity/mean")}
        h["sha256"] = _checksum(arrays)

    _fails(_rewrite(map_file, tmp_path / "m.npz", header_fn=drop_and_fix, array_fn=drop), "missing array 'mean'")


# ------------------------------------------------------------------ content, not only the checksum


def _resigned(map_file: Path, dst: Path, array_fn=None, header_fn=None) -> Path:
    """The map with its arrays changed by ``array_fn`` and the checksum recomputed (what a
    careless or hostile tool would write)."""
    from lino_loc.appearance_map import _checksum

    def fix(h):
        if header_fn:
            header_fn(h)
        with np.load(map_file, allow_pickle=False) as z:
            arrays = {k: z[k] for k in z.files if k != "header"}
        if array_fn:
            array_fn(arrays)
        h["sha256"] = _checksum(arrays)

    return _rewrite(map_file, dst, header_fn=fix, array_fn=array_fn)


def _poses_scaled(arrays, row: int | None = None, value: float = 0.0, scale: float = 1.0) -> None:
    p = arrays["poses"].copy()
    p[:, :2] *= scale
    if row is not None:
        p[row, 0] = value
    arrays["poses"] = p


@pytest.mark.parametrize(
    "edit, needles",
    [
        (lambda a: _poses_scaled(a, 7, 1e300), ("'poses' row 7: field 'x': 1e+300 is not a position in metres",)),
        (lambda a: _poses_scaled(a, 3, np.nan), ("'poses' holds nan (row 3): not finite",)),
        (lambda a: _poses_scaled(a, 2, -np.inf), ("'poses' holds -inf (row 2): not finite",)),
        (lambda a: _poses_scaled(a, scale=1000.0), ("'poses': extent 1900 x 0 m: are the poses in millimetres?",)),
        (lambda a: a["intensity/features"].__setitem__((5, 2), np.nan), ("'intensity/features' holds nan (row 5)",)),
        (lambda a: a.update({"intensity/mean": a["intensity/mean"].astype(np.float64) * 0 + 1e300}),
         ("'intensity/mean' holds 1e+300 (row 0): beyond +-1e+09",)),
        (lambda a: a["intensity/components"].__setitem__((1, 4), np.inf), ("'intensity/components' holds inf (row 1)",)),
        (lambda a: a["intensity/explained_variance"].__setitem__(0, -1.0),
         ("'intensity/explained_variance' holds -1 (row 0): negative",)),
    ],
)
def test_resigned_implausible_content_is_refused(map_file: Path, tmp_path: Path, edit, needles) -> None:
    bad = _resigned(map_file, tmp_path / "bad.npz", array_fn=edit)
    _fails(bad, "implausible map content", *needles)


def test_non_finite_header_parameter_is_refused(map_file: Path, tmp_path: Path) -> None:
    def nan_param(h):
        h["channels"]["intensity"]["params"]["total_variance"] = float("nan")

    # the header is outside the checksum: no re-signing needed
    _fails(_rewrite(map_file, tmp_path / "h.npz", header_fn=nan_param),
           "implausible map content", "'total_variance' is nan")


def test_build_refuses_an_image_of_another_size(dataset: Dataset, tmp_path: Path) -> None:
    root = tmp_path / "odd"
    rng = np.random.default_rng(4)
    with DatasetWriter(root, DatasetMeta(name="odd", camera=dataset.meta.camera)) as w:
        for i in range(8):
            w.add(_scene(0.1 * i, 0.0, rng), (0.1 * i, 0.0, 0.0))
    cv2.imwrite(str(root / "images" / "000003.png"), np.zeros((H, W + 8), np.uint8))
    with pytest.raises(LinoLocError, match=rf"000003.png: {W + 8}x{H} pixels, the camera of the dataset is {W}x{H}"):
        build_map(Dataset.open(root), n_features=3, size=SIZE, workers=1)


def test_build_refuses_implausible_poses(dataset: Dataset, tmp_path: Path) -> None:
    root = tmp_path / "far"
    rng = np.random.default_rng(5)
    with DatasetWriter(root, DatasetMeta(name="far", camera=dataset.meta.camera)) as w:
        for i in range(8):
            w.add(_scene(0.1 * i, 0.0, rng), (300.0 * i, 0.0, 0.0))
    with pytest.raises(LinoLocError, match=r"poses.csv: extent 2100 x 0 m: are the poses in millimetres"):
        build_map(Dataset.open(root), n_features=3, size=SIZE)
