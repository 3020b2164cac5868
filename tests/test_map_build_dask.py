"""The map built on a Dask LocalCluster, and the local build streamed from disk, equal the
in-memory local build (principal angles near zero, features equal up to sign, poses equal);
the cluster's one-line errors."""

from __future__ import annotations

import socket
import sys
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

import services.cli as cli
from lino_loc.appearance_map import AppearanceMap, build_map
from lino_loc.dataset import CameraInfo, Dataset, DatasetMeta, DatasetWriter
from lino_loc.errors import LinoLocError
from lino_loc.pca import principal_angles
from lino_loc.row_file import RowFile
from lino_loc.virtual_views import offsets

pytest.importorskip("distributed")

N_IMAGES = 300
CAM = CameraInfo(width=160, height=120, fx=140.0, fy=140.0, cx=80.0, cy=60.0)
SIZE = (40, 30)
FEATURES = 8


def _patterns(k: int) -> np.ndarray:
    """k smooth, mutually orthogonal cosine patterns over the image (k, H, W)."""
    yy, xx = np.mgrid[0 : CAM.height, 0 : CAM.width].astype(np.float64)
    pats = []
    for fy in range(4):
        for fx in range(4):
            if fx == fy == 0:
                continue
            pats.append(np.cos(np.pi * fx * (xx + 0.5) / CAM.width) * np.cos(np.pi * fy * (yy + 0.5) / CAM.height))
    return np.stack(pats[:k])


@pytest.fixture(scope="module")
def survey(tmp_path_factory: pytest.TempPathFactory) -> Dataset:
    """300 images: 12 patterns with amplitudes 40 * 0.6^k (a spectrum with clear gaps, so each
    component is well defined and the features can be compared one by one) + sensor noise."""
    rng = np.random.default_rng(18)
    pats = _patterns(12)
    amp = 40.0 * 0.6 ** np.arange(12)
    root = tmp_path_factory.mktemp("dask") / "survey"
    with DatasetWriter(root, DatasetMeta(name="synthetic", camera=CAM)) as w:
        for i in range(N_IMAGES):
            a = rng.uniform(-1.0, 1.0, 12) * amp
            img = 128.0 + np.tensordot(a, pats, axes=1) + rng.normal(0.0, 2.0, (CAM.height, CAM.width))
            w.add(np.clip(np.rint(img), 0, 255).astype(np.uint8), (0.1 * (i % 30), 0.1 * (i // 30), 0.01 * i))
    return Dataset.open(root)


@pytest.fixture(scope="module")
def local_map(survey: Dataset) -> AppearanceMap:
    return build_map(survey, FEATURES, "none", SIZE, workers=1)


@pytest.fixture(scope="module")
def cluster() -> Iterator[object]:
    from services.dask_cluster import dask_client

    with dask_client(None, workers=2) as client:
        yield client


def _assert_same_map(a: AppearanceMap, b: AppearanceMap) -> None:
    ca, cb = a.channels["intensity"], b.channels["intensity"]
    np.testing.assert_array_equal(a.poses, b.poses)
    assert principal_angles(ca.pca.components, cb.pca.components).max() < 1e-3
    np.testing.assert_allclose(ca.pca.mean, cb.pca.mean, atol=1e-5)
    np.testing.assert_allclose(ca.pca.explained_variance, cb.pca.explained_variance, rtol=1e-4)
    # features per component, up to sign (the sign rule fixes it, but a near-tie of the largest
    # coefficient could flip it legitimately)
    scale = float(np.abs(ca.features).max())
    for k in range(ca.n_features):
        s = np.sign(float(ca.features[:, k] @ cb.features[:, k]))
        assert np.abs(ca.features[:, k] - s * cb.features[:, k]).max() < 1e-4 * scale, k
    assert ca.params["total_variance"] == pytest.approx(cb.params["total_variance"], rel=1e-5)


def test_dask_build_equals_local(survey: Dataset, local_map: AppearanceMap, cluster: object) -> None:
    dask_map = build_map(survey, FEATURES, "none", SIZE, engine="dask", chunk_rows=128)
    _assert_same_map(local_map, dask_map)


def test_streamed_build_equals_in_memory(survey: Dataset, local_map: AppearanceMap, tmp_path: Path) -> None:
    # 300 x 1200 float32 = 1.4 MiB over a 0.5 MiB budget: streamed in chunks of 37 rows (the
    # last one short) from a scratch file, which is deleted afterwards
    streamed = build_map(survey, FEATURES, "none", SIZE, memory_budget_mb=0.5, scratch_dir=tmp_path,
                         chunk_rows=37, workers=2)
    _assert_same_map(local_map, streamed)
    assert list(tmp_path.iterdir()) == []


def test_streamed_gram_over_budget_is_an_error(survey: Dataset) -> None:
    with pytest.raises(LinoLocError, match="needs the whole data matrix in memory"):
        build_map(survey, FEATURES, "none", SIZE, method="gram", memory_budget_mb=0.5)


def test_row_file_round_trip(tmp_path: Path) -> None:
    X = np.random.default_rng(1).standard_normal((53, 7)).astype(np.float32)
    with RowFile(53, 7, tmp_path, chunk_rows=10) as rows:
        rows.write(40, X[40:])  # any order
        rows.write(0, X[:40])
        got = list(rows.chunks())
        assert [lo for lo, _ in got] == [0, 10, 20, 30, 40, 50]
        np.testing.assert_array_equal(np.vstack([r for _, r in got]), X)
        with pytest.raises(LinoLocError):
            rows.write(50, X[:5])
    assert list(tmp_path.iterdir()) == []


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def test_unreachable_scheduler_is_one_line() -> None:
    from services.dask_cluster import dask_client

    address = f"tcp://127.0.0.1:{_free_port()}"
    with pytest.raises(LinoLocError, match="cannot reach the Dask scheduler") as exc:
        with dask_client(address, timeout_s=1.0):
            pass
    assert address in str(exc.value) and "\n" not in str(exc.value)


def test_cli_dask_build_and_missing_extra(survey: Dataset, cluster: object, tmp_path: Path,
                                          monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]) -> None:
    monkeypatch.setattr(cli, "COMMAND_MODULES", ("services.commands.map",))
    out = tmp_path / "m.npz"
    argv = ["map", "build", str(survey.root), "--out", str(out), "--features", str(FEATURES), "--size", "40x30"]
    address = cluster.scheduler.address  # type: ignore[attr-defined]
    assert cli.main([*argv, "--scheduler", address]) == 2
    assert "--scheduler needs --engine dask" in capsys.readouterr().err
    # an existing cluster (the fixture's LocalCluster, by its address), with virtual headings
    # (every image's 3 turned views: 900 rows in blocks of 3 x 150)
    assert cli.main([*argv, "--engine", "dask", "--scheduler", address, "--chunk-rows", "150",
                     "--virtual-headings", "3", "--preprocess", "gradient"]) == 0, capsys.readouterr().err
    ref = build_map(survey, FEATURES, "gradient", SIZE, virtual_offsets=offsets(np.radians(3.0), 3), workers=1)
    got = AppearanceMap.load(out)
    assert len(got) == 3 * N_IMAGES
    _assert_same_map(ref, got)
    # a bad image is found by the worker that decodes it: one line naming the file
    bad = tmp_path / "bad"
    with DatasetWriter(bad, DatasetMeta(name="bad", camera=CAM)) as w:
        for i in range(30):
            w.add(np.full((CAM.height, CAM.width), 8 * i, np.uint8), (0.1 * i, 0.0, 0.0))
    (bad / "images" / "000017.png").write_bytes(b"not a png")
    capsys.readouterr()
    assert cli.main(["map", "build", str(bad), "--out", str(tmp_path / "bad.npz"), "--features", "3", "--size",
                     "40x30", "--engine", "dask", "--scheduler", address, "--chunk-rows", "10"]) == 2
    err = capsys.readouterr().err.strip()
    assert "000017.png" in err and "unreadable" in err and len(err.splitlines()) == 1, err
    monkeypatch.setitem(sys.modules, "distributed", None)  # the extra not installed
    capsys.readouterr()
    assert cli.main([*argv, "--engine", "dask"]) == 2
    err = capsys.readouterr().err.strip()
    assert "pip install lino-loc[cluster]" in err and len(err.splitlines()) == 1


@pytest.mark.parametrize("rank", [None, 5])
def test_streamed_and_dask_pca_equal_in_memory(rank: int | None, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The fused one-pass-per-iteration PCA (Cholesky QR) on a well-conditioned sketch, and on
    a rank-5 matrix (sketch of 16 columns rank deficient) the fallback to the two-pass
    randomized SVD: both equal the in-memory fit_pca."""
    import dask
    import dask.array as da

    import lino_loc.pca as pca_mod
    from lino_loc.pca_dask import fit_pca_dask

    rng = np.random.default_rng(7)
    n, dim, d = 400, 300, 3
    scales = 0.8 ** np.arange(rank or 40)
    X = (rng.standard_normal((n, len(scales))) * scales) @ np.linalg.qr(rng.standard_normal((dim, len(scales))))[0].T
    X = (X + 0.5).astype(np.float32)
    ref = pca_mod.fit_pca(X, d)
    calls: list[int] = []
    two_pass = pca_mod.randomized_svd
    monkeypatch.setattr(pca_mod, "randomized_svd", lambda *a, **k: calls.append(1) or two_pass(*a, **k))
    with RowFile(n, dim, tmp_path, chunk_rows=64) as rows:
        rows.write(0, X)
        streamed = pca_mod.fit_pca_streamed(rows, d)
    assert len(calls) == (1 if rank else 0)  # the fallback ran only for the rank-deficient sketch
    monkeypatch.setattr("lino_loc.pca_dask.randomized_svd", pca_mod.randomized_svd)
    with dask.config.set(scheduler="synchronous"):  # the algorithm, not the cluster (tested above)
        on_dask = fit_pca_dask(da.from_array(X, chunks=(64, dim)), d)
    assert len(calls) == (2 if rank else 0)
    for got in (streamed, on_dask):
        assert principal_angles(ref.components, got.components).max() < 1e-3
        np.testing.assert_allclose(got.explained_variance, ref.explained_variance, rtol=1e-4)
        np.testing.assert_allclose(np.abs(got.components @ ref.components.T), np.eye(d), atol=1e-3)
