"""`lino-loc map extend` (lino_loc.map_extend): a session added by projection or by an
incremental refit; old maps (no sessions in the header) load; sessions listed."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

import services.cli as cli
from lino_loc.appearance_map import HEADER_KEY, AppearanceMap, build_map, virtual_setup
from lino_loc.dataset import CameraInfo, Dataset, DatasetMeta, DatasetWriter
from lino_loc.errors import LinoLocError
from lino_loc.map_extend import extend_map

CAM = CameraInfo(width=32, height=24, fx=30.0, fy=30.0, cx=16.0, cy=12.0)
SIZE = (16, 12)


def _scene(x: float, t: float, light: str, rng: np.random.Generator) -> np.ndarray:
    """A grey image that varies smoothly with the pose; ``bulb`` adds a warm gradient the
    tube survey never saw (new directions for the basis)."""
    u = np.linspace(0, 1, CAM.width)[None, :]
    v = np.linspace(0, 1, CAM.height)[:, None]
    img = 100 + 60 * np.sin(6 * u + 2 * x + t) * np.cos(3 * v + t) + 20 * np.cos(9 * v - x)
    if light == "bulb":
        img = 0.7 * img + 70 * v * (1 - u) + 30 * np.sin(15 * u * v)
    img += rng.normal(0, 12, img.shape)
    return np.clip(img, 0, 255).astype(np.uint8)


def _dataset(root: Path, light: str, xs: np.ndarray, seed: int) -> Path:
    rng = np.random.default_rng(seed)
    with DatasetWriter(root, DatasetMeta(name=f"synthetic-{light}", camera=CAM)) as w:
        for x in xs:
            for t in np.radians(np.arange(0, 360, 45)):
                w.add(_scene(float(x), float(t), light, rng), (float(x), 0.0, float(t)), condition=light)
    return root


@pytest.fixture
def tube(tmp_path: Path) -> tuple[AppearanceMap, Path]:
    ds = _dataset(tmp_path / "tube", "tube", np.arange(0, 4.01, 0.125), 0)
    amap = build_map(Dataset.open(ds), n_features=6, size=SIZE, workers=1)
    return amap, amap.save(tmp_path / "tube.npz")


@pytest.fixture
def bulb(tmp_path: Path) -> Dataset:
    return Dataset.open(_dataset(tmp_path / "bulb", "bulb", np.arange(0.25, 4.01, 0.75), 1))


def test_old_map_loads_with_one_session(tube: tuple[AppearanceMap, Path]) -> None:
    """A map of one survey is written without a ``sessions`` key (as every map before
    sessions existed), loads, and lists its survey as one built session."""
    _, path = tube
    with np.load(path, allow_pickle=False) as npz:
        header = json.loads(npz[HEADER_KEY].tobytes().decode())
    assert "sessions" not in header
    amap = AppearanceMap.load(path)
    (s,) = amap.session_list()
    assert s.basis == "built" and s.first_entry == 0 and s.n_entries == len(amap)


def test_projection_keeps_the_basis(tube: tuple[AppearanceMap, Path], bulb: Dataset, tmp_path: Path) -> None:
    amap, _ = tube
    new, rep = extend_map(amap, bulb, refit="never", workers=1)
    ch0, ch1 = amap.channels["intensity"], new.channels["intensity"]
    assert not rep.refitted and rep.session.basis == "projected"
    np.testing.assert_array_equal(ch1.pca.components, ch0.pca.components)
    np.testing.assert_array_equal(ch1.features[: len(amap)], ch0.features)
    assert len(new) == len(amap) + len(bulb)
    # the new entries are what the sensor model computes for those images
    for i in (0, 7, len(bulb) - 1):
        np.testing.assert_allclose(ch1.features[len(amap) + i], ch1.project(bulb.image(i)), atol=1e-3)
    np.testing.assert_array_equal(new.poses[len(amap):], bulb.poses)
    path = new.save(tmp_path / "ext.npz")
    back = AppearanceMap.load(path)
    assert [s.name for s in back.session_list()] == [amap.name, "bulb"]
    assert [s.basis for s in back.session_list()] == ["built", "projected"]
    assert back.session_list()[1].first_entry == len(amap)


def test_refit_represents_the_new_light(tube: tuple[AppearanceMap, Path], bulb: Dataset) -> None:
    amap, _ = tube
    new, rep = extend_map(amap, bulb, refit="always", workers=1)
    assert rep.refitted and rep.session.basis == "refitted"
    assert rep.residual_after < 0.5 * rep.residual_before
    ch = new.channels["intensity"]
    np.testing.assert_allclose(ch.pca.components @ ch.pca.components.T, np.eye(6), atol=1e-4)
    # the old entries re-projected: project(reconstruction under the old basis)
    old = amap.channels["intensity"]
    recon = old.pca.reconstruct(old.features)
    np.testing.assert_allclose(ch.features[: len(amap)], ch.pca.project(recon), atol=1e-2)
    for i in (0, 11):
        np.testing.assert_allclose(ch.features[len(amap) + i], ch.project(bulb.image(i)), atol=1e-3)
    # the total variance is that of the tube and bulb images together
    from lino_loc.appearance_map import load_vectors

    tube_ds = Dataset.open(Path(amap.source)) if Path(amap.source).is_dir() else None
    assert tube_ds is not None
    X = np.vstack([load_vectors(tube_ds, "none", SIZE), load_vectors(bulb, "none", SIZE)]).astype(np.float64)
    assert ch.params["total_variance"] == pytest.approx(float(np.sum(X.var(axis=0))), rel=1e-4)


def test_auto_refits_a_new_light_not_the_same_light(tube: tuple[AppearanceMap, Path], bulb: Dataset,
                                                    tmp_path: Path) -> None:
    amap, _ = tube
    _, rep = extend_map(amap, bulb, workers=1)
    assert rep.refitted and rep.residual_before > 1.2 * rep.map_residual
    same = Dataset.open(_dataset(tmp_path / "tube2", "tube", np.arange(0, 4.01, 0.25), 2))  # a re-survey
    _, rep2 = extend_map(amap, same, workers=1)
    assert not rep2.refitted and rep2.residual_before <= 1.2 * rep2.map_residual


def test_sessions_accumulate(tube: tuple[AppearanceMap, Path], bulb: Dataset, tmp_path: Path) -> None:
    amap, _ = tube
    a, _ = extend_map(amap, bulb, refit="always", workers=1)
    b, _ = extend_map(AppearanceMap.load(a.save(tmp_path / "a.npz")), bulb, name="bulb-2", refit="never", workers=1)
    back = AppearanceMap.load(b.save(tmp_path / "b.npz"))
    assert [(s.name, s.first_entry, s.n_entries) for s in back.session_list()] == [
        (amap.name, 0, len(amap)), ("bulb", len(amap), len(bulb)), ("bulb-2", len(amap) + len(bulb), len(bulb))]


def test_bad_inputs(tube: tuple[AppearanceMap, Path], bulb: Dataset, tmp_path: Path) -> None:
    amap, _ = tube
    with pytest.raises(LinoLocError, match="no rows with condition 'night'"):
        extend_map(amap, bulb, condition="night")
    other = CAM.model_copy(update={"fx": 31.0})
    with DatasetWriter(tmp_path / "cam", DatasetMeta(name="cam", camera=other)) as w:
        w.add(np.zeros((24, 32), np.uint8), (0, 0, 0))
    with pytest.raises(LinoLocError, match="differs from the map"):
        extend_map(amap, Dataset.open(tmp_path / "cam"))


def test_cli_extend_and_info(tube: tuple[AppearanceMap, Path], bulb: Dataset, tmp_path: Path,
                             monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]) -> None:
    monkeypatch.setattr(cli, "COMMAND_MODULES", ("services.commands.map",))
    _, path = tube
    out = tmp_path / "ext.npz"
    code = cli.main(["map", "extend", str(path), str(bulb.root), "--out", str(out), "--json"])
    o, err = capsys.readouterr()
    assert code == 0, err
    summary = json.loads(o)
    assert summary["basis"] == "refitted" and summary["sessions"][-1] == "bulb"
    assert cli.main(["map", "info", str(out)]) == 0
    o, _ = capsys.readouterr()
    assert "session    bulb: entries 264..311 (48), condition bulb, refitted" in o
    assert cli.main(["map", "extend", str(path), str(bulb.root), "--out", str(path)]) == 2
    _, err = capsys.readouterr()
    assert len(err.strip().splitlines()) == 1 and "--out must differ" in err


def test_several_datasets_make_one_session(tube: tuple[AppearanceMap, Path], tmp_path: Path) -> None:
    """The parts the daemon's map refresh writes: one session, rows in order."""
    amap, _ = tube
    a = Dataset.open(_dataset(tmp_path / "p1", "bulb", np.array([0.5, 1.0]), 3))
    b = Dataset.open(_dataset(tmp_path / "p2", "bulb", np.array([2.0]), 4))
    new, rep = extend_map(amap, [a, b], refit="never", workers=1)
    assert rep.session.n_entries == len(a) + len(b) and rep.session.condition == "bulb"
    np.testing.assert_array_equal(new.poses[len(amap):], np.vstack([a.poses, b.poses]))
    ch = new.channels["intensity"]
    np.testing.assert_allclose(ch.features[-1], ch.project(b.image(len(b) - 1)), atol=1e-3)


def test_a_map_with_virtual_headings_extends_with_its_headings(tmp_path: Path, bulb: Dataset) -> None:
    """Every new image becomes the map's V turned views, as at build time."""
    import math

    from lino_loc.virtual_views import offsets

    ds = Dataset.open(_dataset(tmp_path / "vt", "tube", np.arange(0, 4.01, 0.25), 5))
    amap = build_map(ds, n_features=6, size=SIZE, workers=1, virtual_offsets=offsets(math.radians(3), 3))
    assert len(amap) == 3 * len(ds)
    new, rep = extend_map(amap, bulb, refit="always", workers=1)
    assert rep.session.n_entries == 3 * len(bulb)
    np.testing.assert_allclose(new.poses[len(amap) + 1], bulb.poses[0])  # the middle offset is 0
    ch = new.channels["intensity"]
    np.testing.assert_allclose(ch.features[len(amap) + 1], ch.project(bulb.image(0)), atol=1e-3)


def test_a_session_gets_its_disparity_features_by_projection_onto_the_channel(tmp_path: Path) -> None:
    """With a disparity channel and virtual headings, the new rows' sparse disparity is turned,
    projected onto the channel's model (never refitted), and appended: each new entry's features
    are the model's projection of that view."""
    import math

    from lino_loc.appearance_map import _disparity_rows, _disparity_views
    from lino_loc.virtual_views import offsets

    cam = CAM.model_copy(update={"baseline_m": 0.075})

    def survey(root: Path, xs: np.ndarray, seed: int) -> Dataset:
        rng = np.random.default_rng(seed)
        v = np.linspace(0, 1, cam.height)[:, None]
        with DatasetWriter(root, DatasetMeta(name="synthetic-stereo", camera=cam)) as w:
            for x in xs:
                for t in np.radians(np.arange(0, 360, 45)):
                    disp = 2.0 + np.sin(2 * x + t) + v * np.cos(x - t) + rng.normal(0, 0.05, (cam.height, cam.width))
                    disp[rng.random(disp.shape) < 0.4] = np.nan  # the matcher's holes
                    w.add(_scene(float(x), float(t), "tube", rng), (float(x), 0.0, float(t)), condition="tube",
                          disparity=disp)
        return Dataset.open(root)

    base = survey(tmp_path / "base", np.arange(0, 2.01, 0.25), 0)
    turns = offsets(math.radians(3.0), 3)
    amap = build_map(base, n_features=6, size=SIZE, workers=1, channels=("intensity", "disparity"),
                     disparity_features=3, virtual_offsets=turns)
    new = survey(tmp_path / "new", np.array([0.6, 1.4]), 1)
    out, _ = extend_map(amap, new, refit="never", workers=1)
    ch, old = out.channels["disparity"], amap.channels["disparity"]
    n_old = len(old.features)
    np.testing.assert_array_equal(ch.features[:n_old], old.features)  # the old entries untouched
    virtual = virtual_setup(cam, SIZE, turns)
    views = _disparity_views(_disparity_rows(new, SIZE, float(old.params["min_valid_fraction"]), None), SIZE, virtual)
    assert len(ch.features) == n_old + len(views) == len(out.poses)
    np.testing.assert_allclose(ch.features[n_old:], old.pca.project(views), rtol=1e-5, atol=1e-5)
