"""Read and write Gaussians in the INRIA 3DGS PLY layout (``point_cloud/iteration_N/point_cloud.ply``).

Layout written (all ``float`` = little-endian float32, one row per Gaussian, pre-activation values)::

    x y z  nx ny nz  f_dc_0..2  f_rest_0..(3*(K-1)-1)  opacity  scale_0..2  rot_0..3

- ``nx ny nz`` are zeros, kept for compatibility with the INRIA viewers.
- ``f_rest`` is channel-major: the model's ``shN`` [N, K-1, 3] is transposed to [N, 3, K-1] before
  flattening, so ``f_rest_{c*(K-1)+j}`` is coefficient ``j`` of colour channel ``c``.
- ``opacity`` is a logit, ``scale_*`` are log standard deviations, ``rot_*`` a quaternion (w, x, y, z).

The reader matches properties by name, so files from other tools (gsplat without normals, extra
``red green blue`` uchar properties, double precision, ascii, big endian) load too. It refuses, naming the
property, NaN/inf values, log-scales above `MAX_LOG_SCALE` and zero quaternions (what garbage or data in
the wrong byte order decode to), and a vertex count that the file is too short for.
"""

from __future__ import annotations

import os
import re
import warnings
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from metegs.errors import DataError
from metegs.files import atomic_output
from metegs.gaussians.model import PARAM_NAMES, GaussianModel

_PLY_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1",
    "short": "i2", "int16": "i2", "ushort": "u2", "uint16": "u2",
    "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}  # fmt: skip
_FORMATS = {"binary_little_endian": "<", "binary_big_endian": ">", "ascii": "="}
_REQUIRED = ("x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity",
             "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3")  # fmt: skip
_F_REST = re.compile(r"f_rest_(\d+)$")
_MAX_HEADER_BYTES = 1 << 20
WORLD_TO_FILE = "metegs world_to_file"
"""Header comment (then the 9 row-major entries of a rotation) of a file written turned from metegs's world."""
MAX_LOG_SCALE = 20.0
"""Largest ``scale_*`` (log standard deviation) a PLY may hold: exp(20) ≈ 5e8 scene units."""


def _property_names(num_rest: int) -> list[str]:
    """Property names in the order the INRIA layout writes them (``num_rest`` = 3*(K-1))."""
    return (
        ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
        + [f"f_rest_{i}" for i in range(num_rest)]
        + ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    )


def _state_arrays(model_or_state: GaussianModel | Mapping[str, torch.Tensor]) -> dict[str, np.ndarray]:
    """Parameters as float32 numpy arrays on the CPU, shapes checked."""
    if isinstance(model_or_state, GaussianModel):
        state = {k: v for k, v in model_or_state.params.items()}
    elif isinstance(model_or_state, Mapping):
        missing = [k for k in PARAM_NAMES if k not in model_or_state]
        if missing:
            raise ValueError(f"save_ply: state is missing parameter(s) {missing}")
        state = model_or_state
    else:
        raise TypeError(f"save_ply: expected a GaussianModel or a state dict, got {type(model_or_state).__name__}")
    arrays = {k: torch.as_tensor(state[k]).detach().to("cpu", torch.float32).numpy() for k in PARAM_NAMES}
    n = arrays["means"].shape[0]
    expected = {"means": (n, 3), "scales": (n, 3), "quats": (n, 4), "opacities": (n,), "sh0": (n, 1, 3)}
    for k, shape in expected.items():
        if arrays[k].shape != shape:
            raise ValueError(f"save_ply: {k} has shape {tuple(arrays[k].shape)}, expected {shape}")
    shn = arrays["shN"]
    if shn.ndim != 3 or shn.shape[0] != n or shn.shape[2] != 3:
        raise ValueError(f"save_ply: shN has shape {tuple(shn.shape)}, expected ({n}, K-1, 3)")
    return arrays


def save_ply(
    model_or_state: GaussianModel | Mapping[str, torch.Tensor],
    path: str | Path,
    *,
    comments: Iterable[str] = (),
    world_to_file: np.ndarray | None = None,
) -> int:
    """Write Gaussians as an INRIA 3DGS PLY (binary little-endian float32), atomically.

    model_or_state: a `GaussianModel` or a ``state_tensors()``-style dict (means [N,3], scales [N,3] log,
        quats [N,4] wxyz, opacities [N] logit, sh0 [N,1,3], shN [N,K-1,3]).
    comments: extra header lines, each written as ``comment <text>`` after ``comment metegs <version>``
        (e.g. ``"Vertical Axis: z"``).
    world_to_file: a [3, 3] rotation to write the Gaussians in (e.g. `metegs.gaussians.rotate.upright_rotation`,
        so that splat viewers show the scene upright); it is recorded in the header (`WORLD_TO_FILE`) and
        `load_ply` turns the Gaussians back. None or the identity: written as they are.

    Rows with any non-finite value are dropped with a warning saying how many. The file is written to a
    temporary file in the destination folder and renamed over ``path``, so an existing file is never
    left half-written. Returns the number of Gaussians written.
    """
    from metegs import __version__

    path = Path(path)
    comments = list(comments)
    if world_to_file is not None and not np.allclose(world_to_file, np.eye(3)):
        from metegs.gaussians.rotate import rotate_state

        state = model_or_state.params if isinstance(model_or_state, GaussianModel) else model_or_state
        model_or_state = rotate_state({k: torch.as_tensor(state[k]).detach() for k in PARAM_NAMES}, world_to_file)
        numbers = " ".join(f"{float(x):.17g}" for x in np.asarray(world_to_file, np.float64).reshape(-1))
        comments.append(f"{WORLD_TO_FILE} {numbers}")
    a = _state_arrays(model_or_state)
    n, k1 = a["means"].shape[0], a["shN"].shape[1]
    rest = a["shN"].transpose(0, 2, 1).reshape(n, 3 * k1)  # channel-major [N, 3*(K-1)]
    table = np.concatenate(
        [a["means"], np.zeros((n, 3), np.float32), a["sh0"].reshape(n, 3), rest,
         a["opacities"].reshape(n, 1), a["scales"], a["quats"]],
        axis=1,
    ).astype("<f4", copy=False)  # fmt: skip
    finite = np.isfinite(table).all(axis=1)
    dropped = int(n - finite.sum())
    if dropped:
        table = table[finite]
        warnings.warn(
            f"save_ply: dropped {dropped} of {n} Gaussians with non-finite values while writing {path}"
            + (" (nothing left to write)" if dropped == n else ""),
            RuntimeWarning,
            stacklevel=2,
        )

    lines = ["ply", "format binary_little_endian 1.0", f"comment metegs {__version__}"]
    for c in comments:
        c = str(c)
        if "\n" in c or "\r" in c:
            raise ValueError(f"save_ply: a header comment must be one line, got {c!r}")
        lines.append(f"comment {c}")
    lines.append(f"element vertex {table.shape[0]}")
    lines += [f"property float {name}" for name in _property_names(3 * k1)]
    lines.append("end_header")
    header = ("\n".join(lines) + "\n").encode("ascii")

    with atomic_output(path) as tmp, open(tmp, "wb") as f:
        f.write(header)
        f.write(np.ascontiguousarray(table).tobytes())
    return int(table.shape[0])


# --- reading -----------------------------------------------------------------------------------------


@dataclass
class _Element:
    name: str
    count: int
    props: list[tuple[str, str]] = field(default_factory=list)  # (name, numpy type code)
    has_list: bool = False


@dataclass
class _Header:
    fmt: str
    elements: list[_Element]
    comments: list[str]
    size: int  # bytes up to and including the end_header line


def _read_header(path: Path, f) -> _Header:
    """Parse the ascii header at the start of ``f`` (positioned at 0)."""
    first = f.readline(16)
    if first.rstrip(b"\r\n") != b"ply":
        raise DataError(path, "not a PLY file (it does not start with 'ply')")
    fmt, elements, comments = None, [], []
    size = len(first)
    while True:
        raw = f.readline(_MAX_HEADER_BYTES)
        size += len(raw)
        if not raw or size > _MAX_HEADER_BYTES:
            raise DataError(path, "PLY header has no 'end_header' line (truncated or not a PLY file)")
        try:
            line = raw.decode("ascii").strip()
        except UnicodeDecodeError as exc:
            raise DataError(path, "PLY header contains non-ascii bytes") from exc
        words = line.split()
        if not words:
            continue
        key = words[0]
        if key == "end_header":
            break
        if key == "format":
            if len(words) < 2 or words[1] not in _FORMATS:
                raise DataError(path, f"unsupported PLY format line {line!r} (expected one of {list(_FORMATS)})")
            fmt = words[1]
        elif key in ("comment", "obj_info"):
            comments.append(line[len(key) :].strip())
        elif key == "element":
            if len(words) != 3 or not words[2].isdigit():
                raise DataError(path, f"malformed PLY element line {line!r}")
            elements.append(_Element(words[1], int(words[2])))
        elif key == "property":
            if not elements:
                raise DataError(path, f"PLY property before any element: {line!r}")
            if len(words) >= 2 and words[1] == "list":
                elements[-1].has_list = True
                elements[-1].props.append((words[-1], "list"))
                continue
            if len(words) != 3 or words[1] not in _PLY_TYPES:
                raise DataError(path, f"unsupported PLY property line {line!r}")
            elements[-1].props.append((words[2], _PLY_TYPES[words[1]]))
        else:
            raise DataError(path, f"unexpected PLY header line {line!r}")
    if fmt is None:
        raise DataError(path, "PLY header has no 'format' line")
    return _Header(fmt, elements, comments, size)


def read_ply_vertices(path: Path) -> np.ndarray:
    """The ``vertex`` element of a PLY file as a numpy structured array [N] (fields named as in the header).

    Binary data is read in the byte order the header states; the vertex count is checked against the file
    size before anything is allocated. DataError naming the file when it is missing, malformed or truncated.
    """
    path = Path(path)
    if not path.is_file():
        raise DataError(path, "PLY file not found")
    with open(path, "rb") as f:
        header = _read_header(path, f)
        names = [e.name for e in header.elements]
        if "vertex" not in names:
            raise DataError(path, "PLY file has no 'vertex' element")
        vi = names.index("vertex")
        vertex = header.elements[vi]
        if vertex.has_list:
            raise DataError(path, "PLY 'vertex' element has list properties (a mesh, not Gaussians)")
        seen = set()
        for pname, _ in vertex.props:
            if pname in seen:
                raise DataError(path, f"PLY 'vertex' element lists property {pname!r} twice")
            seen.add(pname)
        order = _FORMATS[header.fmt]

        if header.fmt == "ascii":
            skip = sum(e.count for e in header.elements[:vi])
            text = f.read().decode("ascii", errors="replace").splitlines()
            rows = [ln for ln in text if ln.strip()][skip : skip + vertex.count]
            if len(rows) < vertex.count:
                raise DataError(path, f"PLY data truncated: {vertex.count} vertices declared, {len(rows)} found")
            dtype = np.dtype([(pname, t) for pname, t in vertex.props])
            try:
                values = np.array([r.split() for r in rows], dtype=np.float64).reshape(vertex.count, len(dtype))
            except ValueError as exc:
                raise DataError(path, f"malformed ascii PLY vertex data: {exc}") from exc
            out = np.empty(vertex.count, dtype)
            for i, pname in enumerate(dtype.names):
                out[pname] = values[:, i]
            return out

        offset = 0
        for e in header.elements[:vi]:
            if e.has_list:
                raise DataError(path, f"PLY element {e.name!r} with list properties precedes 'vertex' (unsupported)")
            offset += e.count * np.dtype([(p, order + t) for p, t in e.props]).itemsize
        dtype = np.dtype([(pname, order + t) for pname, t in vertex.props])
        need = vertex.count * dtype.itemsize
        found = max(0, os.fstat(f.fileno()).st_size - header.size - offset)
        if need > found:  # checked before reading: a header may claim far more vertices than the file holds
            raise DataError(
                path,
                f"PLY data truncated: the header declares {vertex.count} vertices of {dtype.itemsize} bytes "
                f"({need} bytes) but the file holds {found} bytes of vertex data",
            )
        f.seek(header.size + offset)
        return np.frombuffer(f.read(need), dtype=dtype)


_HINT = "(a corrupt file, or data in another byte order than the header states?)"


def check_finite(path: Path, v: np.ndarray, props: list[str]) -> None:
    """DataError naming the first of ``props`` of the vertices ``v`` [N] with NaN or infinite values."""
    for p in props:
        bad = np.count_nonzero(~np.isfinite(v[p]))
        if bad:
            raise DataError(path, f"property '{p}' is NaN or infinite in {bad} of {len(v)} vertices {_HINT}")


def _check_values(path: Path, v: np.ndarray, props: list[str]) -> None:
    """DataError naming the property of ``v`` [N] with non-finite values, absurd scales or zero quaternions."""
    check_finite(path, v, props)
    n = len(v)
    for p in ("scale_0", "scale_1", "scale_2"):
        big = np.count_nonzero(v[p] > MAX_LOG_SCALE)
        if big:
            raise DataError(
                path,
                f"property '{p}' (log standard deviation) is above {MAX_LOG_SCALE:g} in {big} of {n} vertices "
                f"(max {v[p].max():.3g}): absurd scales {_HINT}",
            )
    quats = np.stack([np.asarray(v[f"rot_{i}"], np.float64) for i in range(4)], axis=1)
    zero = np.count_nonzero(np.linalg.norm(quats, axis=1) < 1e-8)
    if zero:
        raise DataError(path, f"properties 'rot_0'..'rot_3' are a zero quaternion in {zero} of {n} vertices {_HINT}")


def load_ply(path: str | Path) -> GaussianModel:
    """Load Gaussians from a 3DGS PLY (INRIA layout; properties matched by name).

    Needs ``x y z f_dc_0..2 opacity scale_0..2 rot_0..3`` and ``f_rest_0..3*((d+1)^2-1)-1`` (channel-major);
    ``nx ny nz`` and any other properties are ignored. Any PLY scalar type and ascii / binary formats are
    accepted; values are cast to float32. The SH degree ``d`` follows from the number of ``f_rest_*``
    properties, and the returned model has ``active_sh_degree = max_sh_degree = d``.

    Returns a CPU `GaussianModel` (means [N,3], log-scales [N,3], quats wxyz [N,4], opacity logits [N],
    sh0 [N,1,3], shN [N,K-1,3]). Raises `DataError` naming the file when it is missing, not a PLY, lacks
    required properties, is truncated, has an f_rest count that matches no SH degree, holds no vertices,
    or when a property has NaN/inf values, a log-scale above `MAX_LOG_SCALE` or a zero quaternion.
    """
    path = Path(path)
    v = read_ply_vertices(path)
    names = set(v.dtype.names or ())
    missing = [p for p in _REQUIRED if p not in names]
    if missing:
        raise DataError(path, f"PLY 'vertex' element is missing required propert(y/ies): {', '.join(missing)}")
    rest_idx = sorted(int(m.group(1)) for p in names if (m := _F_REST.match(p)))
    m = len(rest_idx)
    if rest_idx != list(range(m)):
        raise DataError(path, f"f_rest_* properties are not numbered 0..{m - 1} without gaps")
    degree = 0
    while 3 * ((degree + 1) ** 2 - 1) < m:
        degree += 1
    if 3 * ((degree + 1) ** 2 - 1) != m:
        raise DataError(path, f"{m} f_rest_* properties match no SH degree (expected 3*((d+1)^2-1): 0, 9, 24, 45, ...)")
    k1 = m // 3
    n = v.shape[0]
    if n == 0:
        raise DataError(path, "the PLY holds no Gaussians ('element vertex 0')")
    _check_values(path, v, [*_REQUIRED, *(f"f_rest_{i}" for i in range(m))])

    def cols(*props: str) -> np.ndarray:
        if not props:
            return np.zeros((n, 0), np.float32)
        return np.stack([np.asarray(v[p], dtype=np.float32) for p in props], axis=1)

    rest = cols(*(f"f_rest_{i}" for i in range(m))).reshape(n, 3, k1).transpose(0, 2, 1)
    state = {
        "means": cols("x", "y", "z"),
        "scales": cols("scale_0", "scale_1", "scale_2"),
        "quats": cols("rot_0", "rot_1", "rot_2", "rot_3"),
        "opacities": cols("opacity").reshape(n),
        "sh0": cols("f_dc_0", "f_dc_1", "f_dc_2").reshape(n, 1, 3),
        "shN": np.ascontiguousarray(rest),
    }
    tensors = {k: torch.from_numpy(np.ascontiguousarray(a)) for k, a in state.items()}
    rotation = world_to_file(path)
    if rotation is not None:  # written turned (upright for viewers): back into the world it was trained in
        from metegs.gaussians.rotate import rotate_state

        tensors = rotate_state(tensors, rotation.T)
    model = GaussianModel.from_state(tensors, degree)
    model.active_sh_degree = degree
    return model


def world_to_file(path: Path) -> np.ndarray | None:
    """The [3, 3] rotation a metegs PLY was written in (its `WORLD_TO_FILE` header comment), or None."""
    with open(path, "rb") as f:
        comments = _read_header(path, f).comments
    for c in comments:
        if c.startswith(WORLD_TO_FILE):
            from metegs.gaussians.rotate import is_rotation

            try:
                r = np.array([float(x) for x in c[len(WORLD_TO_FILE) :].split()], np.float64).reshape(3, 3)
            except ValueError:
                r = None
            if r is None or not is_rotation(r):
                raise DataError(path, f"header comment {c!r} is not a rotation (9 numbers, row-major)")
            return r
    return None
