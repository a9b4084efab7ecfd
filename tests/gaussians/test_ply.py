"""INRIA 3DGS PLY writer / reader: round trips, channel-major f_rest, robustness and clear errors."""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
import pytest
import torch

from metegs.errors import DataError
from metegs.gaussians import ply as ply_mod
from metegs.gaussians.model import PARAM_NAMES, GaussianModel
from metegs.gaussians.ply import load_ply, save_ply
from metegs.gaussians.sh import num_sh_bases


def random_model(n: int, degree: int, seed: int = 0) -> GaussianModel:
    g = torch.Generator().manual_seed(seed)
    k = num_sh_bases(degree)
    params = {
        "means": torch.randn(n, 3, generator=g) * 5,
        "scales": torch.randn(n, 3, generator=g) - 3,
        "quats": torch.randn(n, 4, generator=g),
        "opacities": torch.randn(n, generator=g) * 2,
        "sh0": torch.randn(n, 1, 3, generator=g),
        "shN": torch.randn(n, k - 1, 3, generator=g) * 0.3,
    }
    return GaussianModel(params, degree)


def split_header(path: Path) -> tuple[list[str], bytes]:
    """Independent parser: header lines and the raw bytes after ``end_header``."""
    raw = path.read_bytes()
    end = raw.index(b"end_header\n") + len(b"end_header\n")
    return raw[:end].decode("ascii").splitlines(), raw[end:]


def write_custom_ply(path: Path, props: list[tuple[str, str]], rows: np.ndarray, fmt: str = "binary_little_endian"):
    """Write a PLY with arbitrary (name, numpy dtype) properties; rows is a structured array."""
    ply_types = {"f4": "float", "f8": "double", "u1": "uchar", "i4": "int"}
    lines = ["ply", f"format {fmt} 1.0", f"element vertex {len(rows)}"]
    lines += [f"property {ply_types[t]} {name}" for name, t in props]
    lines.append("end_header")
    header = ("\n".join(lines) + "\n").encode()
    if fmt == "ascii":
        body = "".join(" ".join(str(r[name]) for name, _ in props) + "\n" for r in rows).encode()
    else:
        body = rows.tobytes()
    path.write_bytes(header + body)


@pytest.mark.parametrize("degree", [3, 0])
def test_round_trip_bit_exact(tmp_path, degree):
    model = random_model(257, degree)
    path = tmp_path / "point_cloud.ply"
    assert save_ply(model, path) == 257
    loaded = load_ply(path)
    assert loaded.max_sh_degree == degree
    assert loaded.active_sh_degree == degree
    before, after = model.state_tensors(), loaded.state_tensors()
    for name in PARAM_NAMES:
        assert after[name].dtype == torch.float32
        assert after[name].shape == before[name].shape, name
        assert torch.equal(after[name], before[name]), name
    # a state dict saves the same bytes as the model
    path2 = tmp_path / "state.ply"
    save_ply(model.state_tensors(), path2)
    assert path2.read_bytes() == path.read_bytes()


def test_header_layout_and_comments(tmp_path):
    path = tmp_path / "a.ply"
    save_ply(random_model(4, 1), path, comments=["Vertical Axis: z"])
    lines, body = split_header(path)
    assert lines[:2] == ["ply", "format binary_little_endian 1.0"]
    assert "comment metegs 0.1.0" in lines
    assert "comment Vertical Axis: z" in lines
    assert "element vertex 4" in lines
    props = [ln.split() for ln in lines if ln.startswith("property")]
    assert all(p[1] == "float" for p in props)
    expected = (
        ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
        + [f"f_rest_{i}" for i in range(9)]
        + ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    )
    assert [p[2] for p in props] == expected
    assert len(body) == 4 * len(expected) * 4
    with pytest.raises(ValueError, match="one line"):
        save_ply(random_model(1, 0), tmp_path / "b.ply", comments=["two\nlines"])


def test_f_rest_channel_major(tmp_path):
    n, degree = 5, 3
    k1 = num_sh_bases(degree) - 1
    model = random_model(n, degree)
    j = torch.arange(k1, dtype=torch.float32)[:, None]
    c = torch.arange(3, dtype=torch.float32)[None, :]
    with torch.no_grad():
        model.params["shN"].copy_((100 * c + j).expand(n, k1, 3))
    path = tmp_path / "cm.ply"
    save_ply(model, path)
    lines, body = split_header(path)
    names = [ln.split()[2] for ln in lines if ln.startswith("property")]
    table = np.frombuffer(body, dtype="<f4").reshape(n, len(names))
    for cc in range(3):
        for jj in range(k1):
            col = table[:, names.index(f"f_rest_{cc * k1 + jj}")]
            assert np.all(col == 100 * cc + jj), (cc, jj)
    # the other columns land where their names say
    np.testing.assert_array_equal(table[:, names.index("opacity")], model.params["opacities"].detach().numpy())
    np.testing.assert_array_equal(table[:, names.index("rot_0")], model.params["quats"][:, 0].detach().numpy())
    np.testing.assert_array_equal(table[:, names.index("nx")], 0)
    assert torch.equal(load_ply(path).params["shN"], model.params["shN"])


def test_non_finite_rows_dropped_with_warning(tmp_path):
    model = random_model(10, 2)
    with torch.no_grad():
        model.params["means"][1, 0] = float("nan")
        model.params["scales"][4, 2] = float("inf")
        model.params["shN"][7, 3, 1] = float("-inf")
    path = tmp_path / "nf.ply"
    with pytest.warns(RuntimeWarning, match="dropped 3 of 10"):
        assert save_ply(model, path) == 7
    loaded = load_ply(path)
    keep = [i for i in range(10) if i not in (1, 4, 7)]
    for name in PARAM_NAMES:
        assert torch.equal(loaded.params[name], model.params[name][keep]), name


def test_all_rows_non_finite_still_warns(tmp_path):
    model = random_model(3, 0)
    with torch.no_grad():
        model.params["opacities"][:] = float("nan")
    with pytest.warns(RuntimeWarning, match="dropped 3 of 3"):
        assert save_ply(model, tmp_path / "empty.ply") == 0
    with pytest.raises(DataError, match="no Gaussians"):  # an empty model would render black
        load_ply(tmp_path / "empty.ply")


def test_finite_model_does_not_warn(tmp_path):
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        save_ply(random_model(3, 1), tmp_path / "ok.ply")


def _inria_props(degree: int, normals: bool = True) -> list[str]:
    k1 = num_sh_bases(degree) - 1
    return (
        ["x", "y", "z"] + (["nx", "ny", "nz"] if normals else []) + ["f_dc_0", "f_dc_1", "f_dc_2"]
        + [f"f_rest_{i}" for i in range(3 * k1)]
        + ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    )  # fmt: skip


@pytest.mark.parametrize("fmt", ["binary_little_endian", "ascii"])
def test_extra_uchar_colour_no_normals_mixed_types(tmp_path, fmt):
    n = 6
    rng = np.random.default_rng(1)
    props = [(p, "f4") for p in _inria_props(1, normals=False)]
    props[0] = ("x", "f8")  # a double among floats
    props = props[:3] + [("red", "u1"), ("green", "u1"), ("blue", "u1")] + props[3:] + [("extra", "i4")]
    rows = np.zeros(n, dtype=[(name, "<" + t) for name, t in props])
    for name, t in props:
        rows[name] = rng.integers(0, 255, n) if t in ("u1", "i4") else rng.normal(size=n).astype(np.float32)
    path = tmp_path / "other.ply"
    write_custom_ply(path, props, rows, fmt)
    model = load_ply(path)
    assert len(model) == n and model.max_sh_degree == 1
    np.testing.assert_array_equal(model.params["means"][:, 0].detach().numpy(), rows["x"].astype(np.float32))
    np.testing.assert_array_equal(model.params["quats"][:, 3].detach().numpy(), rows["rot_3"])
    # f_rest_{c*3+j} -> shN[:, j, c]
    np.testing.assert_array_equal(model.params["shN"][:, 2, 1].detach().numpy(), rows["f_rest_5"])
    np.testing.assert_array_equal(model.params["sh0"][:, 0, 2].detach().numpy(), rows["f_dc_2"])


def test_missing_file(tmp_path):
    with pytest.raises(DataError, match="not found") as info:
        load_ply(tmp_path / "nope.ply")
    assert info.value.path == tmp_path / "nope.ply"


def test_not_a_ply(tmp_path):
    path = tmp_path / "bad.ply"
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + bytes(100))
    with pytest.raises(DataError, match="not a PLY") as info:
        load_ply(path)
    assert "bad.ply" in str(info.value)
    path.write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 3\n")  # no end_header
    with pytest.raises(DataError, match="end_header"):
        load_ply(path)


def test_truncated(tmp_path):
    path = tmp_path / "t.ply"
    save_ply(random_model(20, 3), path)
    raw = path.read_bytes()
    path.write_bytes(raw[:-10])
    with pytest.raises(DataError, match="truncated") as info:
        load_ply(path)
    assert "t.ply" in str(info.value)


def test_missing_properties_listed(tmp_path):
    props = [(p, "f4") for p in _inria_props(0) if p not in ("opacity", "rot_2")]
    rows = np.zeros(2, dtype=[(name, "<" + t) for name, t in props])
    path = tmp_path / "m.ply"
    write_custom_ply(path, props, rows)
    with pytest.raises(DataError, match="opacity, rot_2") as info:
        load_ply(path)
    assert "m.ply" in str(info.value)


def test_bad_f_rest_count(tmp_path):
    props = [(p, "f4") for p in _inria_props(0)] + [(f"f_rest_{i}", "f4") for i in range(10)]
    rows = np.zeros(2, dtype=[(name, "<" + t) for name, t in props])
    path = tmp_path / "r.ply"
    write_custom_ply(path, props, rows)
    with pytest.raises(DataError, match="10 f_rest"):
        load_ply(path)


def test_failed_write_leaves_existing_file_untouched(tmp_path, monkeypatch):
    path = tmp_path / "keep.ply"
    save_ply(random_model(8, 1, seed=1), path)
    original = path.read_bytes()

    real_open = open

    class FailingFile:
        """Writes the header, then fails on the data (a full disk midway)."""

        def __init__(self, f):
            self.f, self.calls = f, 0

        def write(self, data):
            self.calls += 1
            if self.calls > 1:
                raise OSError("disk full")
            return self.f.write(data)

        def __enter__(self):
            return self

        def __exit__(self, *exc):
            self.f.close()

    monkeypatch.setattr(ply_mod, "open", lambda file, mode: FailingFile(real_open(file, mode)), raising=False)
    with pytest.raises(OSError, match="disk full"):
        save_ply(random_model(50, 3, seed=2), path)
    monkeypatch.undo()
    assert path.read_bytes() == original
    assert sorted(p.name for p in tmp_path.iterdir()) == ["keep.ply"]  # no temp file left behind


def _inria_rows(n: int, degree: int = 1, order: str = "<", seed: int = 2) -> tuple[list[tuple[str, str]], np.ndarray]:
    """Plausible INRIA-layout properties and [n] rows (log-scales near -3, random quaternions)."""
    rng = np.random.default_rng(seed)
    props = [(p, "f4") for p in _inria_props(degree)]
    rows = np.zeros(n, dtype=[(name, order + t) for name, t in props])
    for name, _ in props:
        rows[name] = rng.normal(size=n) + (-3.0 if name.startswith("scale") else 0.0)
    return props, rows


def test_huge_vertex_count_refused_before_allocating(tmp_path):
    props, rows = _inria_rows(4)
    path = tmp_path / "huge.ply"
    write_custom_ply(path, props, rows)
    path.write_bytes(path.read_bytes().replace(b"element vertex 4\n", b"element vertex 1000000000\n"))
    with pytest.raises(DataError, match=r"huge.ply.*1000000000 vertices.*holds 4\d* bytes"):
        load_ply(path)


@pytest.mark.parametrize("prop", ["x", "f_dc_1", "f_rest_4", "opacity", "scale_2", "rot_0"])
@pytest.mark.parametrize("value", [float("nan"), float("inf")])
def test_non_finite_property_is_named(tmp_path, prop, value):
    props, rows = _inria_rows(5)
    rows[prop][[1, 3]] = value
    path = tmp_path / "nan.ply"
    write_custom_ply(path, props, rows)
    with pytest.raises(DataError, match=rf"nan.ply: property '{prop}' is NaN or infinite in 2 of 5 vertices"):
        load_ply(path)


def test_non_finite_in_ascii_ply(tmp_path):
    props, rows = _inria_rows(3)
    rows["y"][0] = float("nan")
    write_custom_ply(tmp_path / "a.ply", props, rows, "ascii")
    with pytest.raises(DataError, match="property 'y'"):
        load_ply(tmp_path / "a.ply")


def test_absurd_scale_and_zero_quaternion_refused(tmp_path):
    props, rows = _inria_rows(4)
    rows["scale_1"][2] = 25.0
    write_custom_ply(tmp_path / "s.ply", props, rows)
    with pytest.raises(DataError, match=r"s.ply: property 'scale_1' .* above 20 in 1 of 4 vertices \(max 25\)"):
        load_ply(tmp_path / "s.ply")
    props, rows = _inria_rows(4)
    for i in range(4):
        rows[f"rot_{i}"][0] = 0.0
    write_custom_ply(tmp_path / "q.ply", props, rows)
    with pytest.raises(DataError, match=r"q.ply: .*'rot_0'..'rot_3' are a zero quaternion in 1 of 4"):
        load_ply(tmp_path / "q.ply")


def test_big_endian_is_read_in_its_byte_order(tmp_path):
    props, little = _inria_rows(6)
    big = little.astype([(name, ">" + t) for name, t in props])
    write_custom_ply(tmp_path / "le.ply", props, little)
    write_custom_ply(tmp_path / "be.ply", props, big, "binary_big_endian")
    assert (tmp_path / "le.ply").read_bytes()[-8:] != (tmp_path / "be.ply").read_bytes()[-8:]
    a, b = load_ply(tmp_path / "le.ply"), load_ply(tmp_path / "be.ply")
    for name in PARAM_NAMES:
        assert torch.equal(a.params[name], b.params[name]), name


def test_big_endian_data_under_a_little_endian_header_is_refused(tmp_path):
    props, rows = _inria_rows(50)
    big = rows.astype([(name, ">" + t) for name, t in props])
    path = tmp_path / "swapped.ply"
    write_custom_ply(path, props, big, "binary_little_endian")
    with pytest.raises(DataError, match="swapped.ply: propert.*byte order"):
        load_ply(path)
