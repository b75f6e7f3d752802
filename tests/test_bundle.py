import zipfile

import numpy as np
import pytest

from optitac_edge.core.bundle import CalibrationBundle
from optitac_edge.core.fiber_table import FiberTable
from optitac_edge.core.grid import SurfaceGrid
from optitac_edge.core.image_transform import ImageTransform
from optitac_edge.core.layout import hex_layout
from optitac_edge.core.options import ContactThresholds
from optitac_edge.errors import BundleError, FrameMismatchError
from optitac_edge.io.bundle_file import BUNDLE_VERSION, FACTOR_MEMBERS, load_bundle, save_bundle


def _weights(m: np.ndarray) -> np.ndarray:
    """Random weights made an interpolation's: each mesh cell's adding up to 1."""
    return (m / m.sum(axis=1, keepdims=True)).astype(np.float32)


def small_bundle(height=40, width=50, pixel_format="gray"):
    layout = hex_layout(rings=2)
    n = layout.n_fibers
    index = np.arange(2 * n, dtype=np.int32) * 3
    table = FiberTable(height=height, width=width, pixel_format=pixel_format, pixel_index=index,
                       pixel_start=np.arange(0, 2 * n + 1, 2, dtype=np.int64),
                       centroid_px=np.random.default_rng(0).uniform(0, 40, (n, 2)),
                       dead=np.arange(n) == 3, unmatched_px=np.array([[1.5, 2.5]]))
    grid = SurfaceGrid.over_layout(layout, n=10)
    return CalibrationBundle(
        layout=layout, transform=ImageTransform(12.0, 3.0, 25.0, 20.0, mirror=True, k1=0.01, r_ref_mm=3.0),
        fibers=table, grid=grid,
        interpolation=_weights(np.random.default_rng(1).random((100, n), dtype=np.float32)),
        thresholds=ContactThresholds(threshold=7.5, min_area_mm2=2.0),
        fiber_map_report={"found": n - 1}, extra_arrays={"error_x": np.ones((3, 3))},
        extra_meta={"model": "x"},
    )


def test_round_trip_keeps_everything(tmp_path):
    original = small_bundle()
    saved = save_bundle(original, tmp_path / "cal.npz")
    loaded = load_bundle(tmp_path / "cal.npz")
    assert loaded.calibration_id == saved.calibration_id and len(loaded.calibration_id) == 16
    assert loaded.transform == original.transform and loaded.grid == original.grid
    assert loaded.thresholds == original.thresholds
    for name in ("pixel_index", "pixel_start", "centroid_px", "dead", "unmatched_px"):
        np.testing.assert_array_equal(getattr(loaded.fibers, name), getattr(original.fibers, name))
    np.testing.assert_array_equal(loaded.interpolation, original.interpolation)
    np.testing.assert_array_equal(loaded.layout.xy_mm, original.layout.xy_mm)
    np.testing.assert_array_equal(loaded.extra_arrays["error_x"], np.ones((3, 3)))
    assert loaded.extra_meta == {"model": "x"} and loaded.fiber_map_report == {"found": 18}
    assert not list(tmp_path.glob("*.tmp")), "temporary file left behind"


def test_bundle_is_loaded_without_pickle(tmp_path):
    save_bundle(small_bundle(), tmp_path / "cal.npz")
    with zipfile.ZipFile(tmp_path / "cal.npz") as z:
        for name in z.namelist():
            header = z.read(name)[:128]
            assert b"'descr': '|O'" not in header and b"'descr': 'O'" not in header


def test_truncated_bundle_is_refused(tmp_path):
    path = tmp_path / "cal.npz"
    save_bundle(small_bundle(), path)
    data = path.read_bytes()
    for cut in (0, 10, len(data) // 2, len(data) - 5):
        path.write_bytes(data[:cut])
        with pytest.raises(BundleError):
            load_bundle(path)


def test_a_bit_flip_never_loads_a_different_bundle(tmp_path):
    """A flipped bit is refused, or it hit zip bookkeeping that changes nothing loaded."""
    path = tmp_path / "cal.npz"
    good = load_bundle(save_bundle(small_bundle(), path) and path)
    data = bytearray(path.read_bytes())
    rng = np.random.default_rng(3)
    refused = 0
    for pos in rng.integers(0, len(data), 200):
        damaged = bytearray(data)
        damaged[pos] ^= 1 << int(rng.integers(8))
        path.write_bytes(bytes(damaged))
        try:
            loaded = load_bundle(path)
        except BundleError:
            refused += 1
            continue
        np.testing.assert_array_equal(loaded.interpolation, good.interpolation)
        np.testing.assert_array_equal(loaded.fibers.pixel_index, good.fibers.pixel_index)
        assert loaded.transform == good.transform and loaded.calibration_id == good.calibration_id
    assert refused > 150  # nearly every byte of the file is data


def test_other_version_and_non_bundles_are_refused(tmp_path, monkeypatch):
    import optitac_edge.io.bundle_file as bundle_mod

    path = tmp_path / "cal.npz"
    monkeypatch.setattr(bundle_mod, "BUNDLE_VERSION", BUNDLE_VERSION + 1)
    save_bundle(small_bundle(), path)
    monkeypatch.undo()
    with pytest.raises(BundleError, match="version"):
        load_bundle(path)
    np.savez(tmp_path / "other.npz", a=np.zeros(3))
    with pytest.raises(BundleError, match="not a calibration bundle"):
        load_bundle(tmp_path / "other.npz")
    with pytest.raises(BundleError, match="not found"):
        load_bundle(tmp_path / "absent.npz")


def test_frame_of_another_size_or_format_is_refused():
    table = small_bundle(height=40, width=50, pixel_format="gray").fibers
    table.check_frame(np.zeros((40, 50), np.uint8), "gray")
    for frame, fmt in [(np.zeros((41, 50), np.uint8), "gray"), (np.zeros((40, 50, 3), np.uint8), "rgb"),
                       (np.zeros((40, 50), np.float32), "gray"), (np.zeros((40, 50, 2), np.uint8), "gray")]:
        with pytest.raises(FrameMismatchError, match="built for"):
            table.check_frame(frame, fmt)


def test_temporaries_of_killed_saves_are_removed_by_the_next_save(tmp_path):
    import subprocess
    import sys

    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True,
                          text=True, check=True).stdout.strip()
    stale = tmp_path / f".cal.npz.{dead}.tmp"
    stale.write_bytes(b"half a bundle")
    unrelated = tmp_path / ".other.npz.1.tmp"
    unrelated.write_bytes(b"x")
    save_bundle(small_bundle(), tmp_path / "cal.npz")
    assert not stale.exists() and unrelated.exists()
    load_bundle(tmp_path / "cal.npz")


def factored_bundle():
    """small_bundle with the real interpolation matrix and its surface factors."""
    from optitac_edge.calibration.interpolation import build_interpolation

    bundle = small_bundle()
    matrix, factors = build_interpolation(bundle.layout, bundle.grid)
    return bundle.with_updates(interpolation=matrix, surface_factors=factors)


def _resave(path, change):
    """Rewrite a saved bundle's members with ``change(members)`` applied and a valid digest."""
    from optitac_edge.io.bundle_file import _digest

    with np.load(path, allow_pickle=False) as npz:
        members = {name: npz[name] for name in npz.files}
    meta = members.pop("meta")
    members.pop("digest")
    change(members)
    digest = _digest(meta.tobytes(), members)
    np.savez(path, **members, meta=meta, digest=np.frombuffer(digest.encode(), dtype=np.uint8))


FACTOR_NAMES = ("interpolation_vertex_operator", "interpolation_cell_columns", "interpolation_cell_weights")


def test_round_trip_with_surface_factors(tmp_path):
    original = factored_bundle()
    save_bundle(original, tmp_path / "cal.npz")
    with zipfile.ZipFile(tmp_path / "cal.npz") as z:
        assert {f"{name}.npy" for name in FACTOR_NAMES} <= set(z.namelist())
    loaded = load_bundle(tmp_path / "cal.npz")
    for name in ("vertex_operator", "cell_columns", "cell_weights"):
        got, want = getattr(loaded.surface_factors, name), getattr(original.surface_factors, name)
        assert got.dtype == want.dtype
        np.testing.assert_array_equal(got, want)
    np.testing.assert_array_equal(loaded.interpolation, original.interpolation)


def test_round_trip_without_surface_factors(tmp_path):
    save_bundle(small_bundle(), tmp_path / "cal.npz")
    with zipfile.ZipFile(tmp_path / "cal.npz") as z:
        assert not any(name.startswith("interpolation_") for name in z.namelist())
    assert load_bundle(tmp_path / "cal.npz").surface_factors is None


@pytest.mark.parametrize("keep", [(0,), (1,), (2,), (0, 1), (1, 2)])
def test_bundle_with_some_factor_members_is_refused(tmp_path, keep):
    path = tmp_path / "cal.npz"
    save_bundle(factored_bundle(), path)

    def drop(members):
        for i, name in enumerate(FACTOR_NAMES):
            if i not in keep:
                del members[name]

    _resave(path, drop)
    with pytest.raises(BundleError, match="incomplete surface factors") as err:
        load_bundle(path)
    assert str(path) in str(err.value) and "\n" not in str(err.value)


@pytest.mark.parametrize("value", [-1, 10**6])
def test_tampered_cell_columns_are_refused(tmp_path, value):
    path = tmp_path / "cal.npz"
    save_bundle(factored_bundle(), path)

    def tamper(members):
        members["interpolation_cell_columns"][3, 2] = value

    _resave(path, tamper)
    with pytest.raises(BundleError, match="cell_columns outside") as err:
        load_bundle(path)
    assert str(path) in str(err.value) and "\n" not in str(err.value)


def test_tampered_factor_dtype_or_weights_are_refused(tmp_path):
    path = tmp_path / "cal.npz"
    save_bundle(factored_bundle(), path)
    _resave(path, lambda m: m.update(interpolation_cell_columns=m["interpolation_cell_columns"].astype(np.int64)))
    with pytest.raises(BundleError, match="int32"):
        load_bundle(path)
    save_bundle(factored_bundle(), path)
    _resave(path, lambda m: m["interpolation_cell_weights"].__imul__(np.float32(1.5)))
    with pytest.raises(BundleError, match=f"{path}.*do not reproduce"):
        load_bundle(path)


def test_bundle_checks_factors_against_grid_layout_and_matrix():
    from optitac_edge.calibration.interpolation import build_interpolation

    bundle = factored_bundle()
    other_grid = SurfaceGrid.over_layout(bundle.layout, n=12)
    _, factors12 = build_interpolation(bundle.layout, other_grid)
    with pytest.raises(ValueError, match="mesh cells"):
        bundle.with_updates(surface_factors=factors12)
    bigger = hex_layout(rings=3)
    _, factors_big = build_interpolation(bigger, SurfaceGrid.over_layout(bigger, n=10))
    with pytest.raises(ValueError, match="fibers"):
        bundle.with_updates(surface_factors=factors_big)
    with pytest.raises(ValueError, match="reproduce"):  # a new matrix needs new factors
        bundle.with_updates(interpolation=bundle.interpolation * np.float32(0.5))


@pytest.mark.parametrize("bad", [{"threshold": -1.0}, {"threshold": float("nan")}, {"min_area_mm2": -0.5},
                                 {"threshold": True}])
def test_contact_thresholds_must_be_finite_and_not_negative(bad) -> None:
    from optitac_edge.core.options import ContactThresholds

    with pytest.raises(ValueError, match=next(iter(bad))):
        ContactThresholds(**bad)


# -- issue 13.11: a digest proves only that nothing changed since it was computed -------------------


def _craft(src, dst, *, meta=None, arrays=None, drop=()):
    """A copy of bundle ``src`` with ``meta``/``arrays`` edited and the digest recomputed (valid)."""
    import json

    from optitac_edge.io.bundle_file import _digest

    with np.load(src, allow_pickle=False) as npz:
        members = {k: npz[k] for k in npz.files}
    m = json.loads(members.pop("meta").tobytes())
    members.pop("digest")
    if meta is not None:
        meta(m)
    if arrays is not None:
        arrays(members)
    for k in drop:
        members.pop(k)
    meta_bytes = json.dumps(m).encode()
    digest = _digest(meta_bytes, members)
    np.savez(dst, **members, meta=np.frombuffer(meta_bytes, np.uint8), digest=np.frombuffer(digest.encode(), np.uint8))
    return dst


def _set_grid(key, value):
    def edit(m):
        m["grid"][key] = value
    return edit


def _nan_in(name):
    def edit(arrays):
        a = arrays[name].copy()
        a.flat[a.size // 2] = np.nan
        arrays[name] = a
    return edit


def _scaled(name, factor):
    def edit(arrays):
        arrays[name] = (arrays[name].astype(np.float64) * factor).astype(arrays[name].dtype)
    return edit


def _all_dead(arrays):
    arrays["fiber_dead"] = np.ones_like(arrays["fiber_dead"])


@pytest.mark.parametrize(("name", "edit", "message"), [
    ("nan interpolation", {"arrays": _nan_in("interpolation"), "drop": FACTOR_MEMBERS.values()},
     "interpolation matrix must be finite"),
    ("nan surface factor", {"arrays": _nan_in("interpolation_cell_weights")}, "non-finite"),
    ("step 0", {"meta": _set_grid("step_mm", 0.0)}, "step_mm must be > 0"),
    ("step nan", {"meta": _set_grid("step_mm", float("nan"))}, "step_mm must be a finite number"),
    ("grid huge", {"meta": _set_grid("n", 10**9)}, "grid size n must be an integer"),
    ("baseline 1e12", {"meta": lambda m: m.__setitem__("baseline_frames", 10**12)}, "baseline_frames must be"),
    ("all dead", {"arrays": _all_dead}, "every fiber is dead"),
    ("nan centroid", {"arrays": _nan_in("fiber_centroid_px")}, "centroids must be finite"),
    ("frame size 0", {"meta": lambda m: m["frame"].__setitem__("width", 0)}, "frame width must be"),
    ("nan transform", {"meta": lambda m: m["transform"].__setitem__("scale_px_per_mm", float("nan"))},
     "scale_px_per_mm must be a finite"),
    # before: an AttributeError in run; replay dropping the depth model silently; an AttributeError in evaluate
    ("depth model 5", {"meta": lambda m: m["extra"].__setitem__("depth", 5)}, "invalid depth model"),
    ("width model list", {"meta": lambda m: m["extra"].__setitem__("width", [1, 2])}, "invalid width model"),
    ("extra a list", {"meta": lambda m: m.__setitem__("extra", [1, 2])}, "'extra' must be an object"),
    ("report a string", {"meta": lambda m: m.__setitem__("fiber_map_report", "x")},
     "'fiber_map_report' must be an object"),
    ("orientation 5", {"meta": lambda m: m["extra"].__setitem__("orientation", 5)}, "'extra.orientation' must be"),
    ("shape model 'x'", {"meta": lambda m: m["extra"].__setitem__("shapes", "x")}, "invalid shape model"),
    # issue 38, item 16: values inside the checks of the day made every frame a contact, or a surface of 1e38
    ("black level 1e30", {"meta": lambda m: m["contact_options"].__setitem__("black_level", 1e30)},
     "black_level must be below 255"),
    ("noise 1e30", {"meta": lambda m: m["contact_options"].__setitem__("noise_gray", 1e30)},
     "noise_gray must be at most 255"),
    ("on level 7", {"meta": lambda m: m["contact_options"].__setitem__("on_level", 7.0)}, "on_level must be at most 1"),
    ("weights x 1e38", {"arrays": _scaled("interpolation", 1e38), "drop": FACTOR_MEMBERS.values()},
     "interpolation matrix: a mesh cell's weights"),
])
def test_a_crafted_bundle_with_a_valid_digest_is_refused_in_one_line(tmp_path, bundle_path, capsys, name, edit,
                                                                       message):
    from optitac_edge.cli import main

    bad = _craft(bundle_path, tmp_path / "bad.npz", **edit)
    with pytest.raises(BundleError, match=message):
        load_bundle(bad)
    assert main(["replay", str(tmp_path / "no-rec"), "--cal", str(bad), "-o", str(tmp_path / "c.csv")]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "Traceback" not in err


def test_a_bundle_member_claiming_a_gibibyte_is_refused_before_it_is_read(tmp_path, bundle_path):
    """A 6.6 MB file whose member decompresses to 1 GiB took 2.2 GB of RSS; the .npy header is read
    first and the member refused before a byte of its data is allocated."""
    import subprocess
    import sys

    bad = tmp_path / "big.npz"
    with zipfile.ZipFile(bundle_path) as src, zipfile.ZipFile(bad, "w", zipfile.ZIP_DEFLATED) as dst:
        for info in src.infolist():
            dst.writestr(info.filename, src.read(info.filename))
        with dst.open("huge.npy", "w", force_zip64=True) as f:
            header = {"descr": "<f4", "fortran_order": False, "shape": (1 << 28,)}
            np.lib.format.write_array_header_1_0(f, header)
            zeros = bytes(64 << 20)
            for _ in range(16):  # 1 GiB of zeros: a few MB compressed
                f.write(zeros)
    assert bad.stat().st_size < 20 << 20
    code = ("import sys; from optitac_edge.io.bundle_file import load_bundle\n"
            "from optitac_edge.errors import BundleError\n"
            "try:\n    load_bundle(sys.argv[1])\nexcept BundleError as e:\n    print(e)\n"
            "print([int(l.split()[1]) for l in open('/proc/self/status') if l.startswith('VmHWM')][0])")
    out = subprocess.run([sys.executable, "-c", code, str(bad)], capture_output=True, text=True, timeout=120,
                         check=True).stdout.split("\n")
    assert "member 'huge' claims 1024 MiB" in out[0]
    assert int(out[1]) < 400_000  # peak RSS of the process (VmHWM, kB): nowhere near the gibibyte
