"""A mesh's vertex colours from its texture image, for model files that colour it that way.

Model libraries often ship a texture instead of vertex colours: BOP's YCB-V PLYs give every vertex
``texture_u`` / ``texture_v`` and name the image in a ``comment TextureFile NAME`` header line; OBJ
files give each triangle corner a UV and a material's image, which Open3D reads; some PLYs give
each face a ``texcoord`` list of its corners' UVs. Verification judges a pixel's colour against
the model's colours there, so each vertex takes the texture's colour at its UV (v up from the
image's bottom row, as OpenGL and the BOP toolkit read it; nearest texel, coordinates wrapped). A
texture that cannot be read leaves the model colourless, with a warning: recognition then runs on
depth alone for that object.
"""

from __future__ import annotations

import logging
import re
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import open3d as o3d

log = logging.getLogger(__name__)

#: PLY scalar types as numpy's.
PLY_TYPES = {
    "char": "i1",
    "int8": "i1",
    "uchar": "u1",
    "uint8": "u1",
    "short": "i2",
    "int16": "i2",
    "ushort": "u2",
    "uint16": "u2",
    "int": "i4",
    "int32": "i4",
    "uint": "u4",
    "uint32": "u4",
    "float": "f4",
    "float32": "f4",
    "double": "f8",
    "float64": "f8",
}
#: Names a PLY gives a vertex's texture coordinates.
UV_NAMES = (("texture_u", "texture_v"), ("s", "t"), ("u", "v"))


def texture_colours(mesh: o3d.geometry.TriangleMesh, path: str | Path) -> np.ndarray | None:
    """Vertex colours (V, 3), rgb 0-1, of a mesh read from ``path`` that carries its colour as a
    texture: an OBJ's per-corner UVs and material images (as Open3D read them), a PLY's vertex UVs
    and TextureFile; None otherwise (other formats' textures are not read)."""
    suffix = Path(path).suffix.lower()
    if suffix == ".obj" and mesh.has_triangle_uvs() and any(np.asarray(t).size for t in mesh.textures):
        return _corner_colours(mesh)
    if suffix == ".ply":
        return ply_texture_colours(Path(path), len(mesh.vertices))
    return None


def sample_texture(image: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Colours (N, 3), rgb 0-1, of an rgb image (H, W, 3, uint8) at texture coordinates uv (N, 2);
    coordinates outside 0..1 wrap (a tiled texture)."""
    H, W = image.shape[:2]
    u, v = (np.where((c < 0) | (c > 1), np.mod(c, 1.0), c) for c in (uv[:, 0], uv[:, 1]))
    cols = np.clip(np.round(u * (W - 1)).astype(np.int64), 0, W - 1)
    rows = np.clip(np.round((1.0 - v) * (H - 1)).astype(np.int64), 0, H - 1)
    return image[rows, cols, :3].astype(np.float64) / 255.0


@dataclass(frozen=True)
class _PlyHeader:
    """What a PLY header says: its format, the TextureFile it names (None: none), its elements as
    (name, count, each property line's words after ``property``), and where the data starts (byte
    offset, and line for ASCII)."""

    fmt: str
    texture: str | None
    elements: list[tuple[str, int, list[list[str]]]]
    body_byte: int
    body_line: int

    @property
    def order(self) -> str:
        """numpy's byte order of a binary body."""
        return "<" if self.fmt == "binary_little_endian" else ">"

    @classmethod
    def read(cls, path: Path) -> _PlyHeader | None:
        """The header of a PLY in one of the three formats; None for anything else."""
        with path.open("rb") as f:
            head = f.read(65536)
        end = head.find(b"end_header")
        if not head.startswith(b"ply") or end < 0:
            return None
        body = head.index(b"\n", end) + 1
        lines = head[:end].decode("ascii", "replace").splitlines()
        texture = next(
            (m.group(1).strip() for line in lines if (m := re.match(r"comment\s+TextureFile\s+(.+)", line))), None
        )
        fmt = next((line.split()[1] for line in lines if line.startswith("format ")), "")
        elements: list[tuple[str, int, list[list[str]]]] = []
        for words in (line.split() for line in lines if line.startswith(("element ", "property "))):
            if words[0] == "element":
                elements.append((words[1], int(words[2]), []))
            elif elements:
                elements[-1][2].append(words[1:])
        if fmt not in ("ascii", "binary_little_endian", "binary_big_endian"):
            return None
        return cls(fmt, texture, elements, body, len(head[:body].splitlines()))


def ply_texture_colours(path: Path, n_vertices: int) -> np.ndarray | None:
    """Vertex colours (V, 3), rgb 0-1, of a PLY whose header names a TextureFile and whose vertices
    (the file's first element, ``n_vertices`` of them) carry texture coordinates, or whose triangles
    do (a ``texcoord`` list of 6 beside ``vertex_indices``: a vertex then takes the mean of its
    corners'); None otherwise."""
    head = _PlyHeader.read(path)
    if head is None or head.texture is None or not head.elements:
        return None
    name, count, vertex_props = head.elements[0]
    if name != "vertex" or count != n_vertices or any(p[0] == "list" or p[0] not in PLY_TYPES for p in vertex_props):
        return None  # a vertex with a list property: not a layout this reads
    names = [p[1] for p in vertex_props]
    vertex_dtype = np.dtype([(p[1], head.order + PLY_TYPES[p[0]]) for p in vertex_props])
    uv_names = next((pair for pair in UV_NAMES if set(pair) <= set(names)), None)
    triangles = None  # with UVs per vertex; else the faces whose corners carry them
    if uv_names is not None and head.fmt == "ascii":
        uv = np.loadtxt(
            path, skiprows=head.body_line, max_rows=n_vertices, ndmin=2, usecols=[names.index(n) for n in uv_names]
        ).astype(np.float64)
    elif uv_names is not None:
        vertices = np.fromfile(path, dtype=vertex_dtype, count=n_vertices, offset=head.body_byte)
        if len(vertices) < n_vertices:
            return None
        uv = np.stack([vertices[n].astype(np.float64) for n in uv_names], axis=1)
    else:
        faces = _face_uvs(path, head, vertex_dtype.itemsize * n_vertices)
        if faces is None:
            return None
        triangles, uv = faces
    image = _texture(path, head.texture)
    if image is None:
        return None
    colours = sample_texture(image, uv)
    return colours if triangles is None else _vertex_means(n_vertices, triangles, colours)


def _face_uvs(path: Path, head: _PlyHeader, vertex_bytes: int) -> tuple[np.ndarray, np.ndarray] | None:
    """A PLY's triangles (F, 3) and their corners' texture coordinates (3F, 2), when its second
    element is the faces with exactly a ``vertex_indices`` list of 3 and a ``texcoord`` list of 6
    (``vertex_bytes``: the binary vertex block's size)."""
    elements = head.elements
    if len(elements) < 2 or elements[1][0] != "face":
        return None
    n_vertices, (_, n_faces, props) = elements[0][1], elements[1]
    lists = {p[3]: (p[1], p[2]) for p in props if p[0] == "list" and len(p) == 4}
    if len(lists) != len(props) or set(lists) != {"vertex_indices", "texcoord"} or n_faces == 0:
        return None
    if head.fmt == "ascii":
        with path.open() as f:
            rows = f.read().splitlines()[head.body_line :]
        faces = [row.split() for row in rows[n_vertices : n_vertices + n_faces]]
        first = [p[3] for p in props].index("vertex_indices") == 0
        try:
            table = np.array([[float(x) for x in words] for words in faces])
        except ValueError:
            return None
        if table.shape != (n_faces, 11):
            return None
        tri_cols, uv_cols = (slice(1, 4), slice(5, 11)) if first else (slice(8, 11), slice(1, 7))
        triangles, uv = table[:, tri_cols].astype(np.int64), table[:, uv_cols]
    else:
        fields = []
        for p in props:
            count_type, item_type = lists[p[3]]
            if count_type not in PLY_TYPES or item_type not in PLY_TYPES:
                return None
            size = 3 if p[3] == "vertex_indices" else 6
            fields += [
                (p[3] + "_n", head.order + PLY_TYPES[count_type]),
                (p[3], head.order + PLY_TYPES[item_type], size),
            ]
        table = np.fromfile(path, dtype=np.dtype(fields), count=n_faces, offset=head.body_byte + vertex_bytes)
        if len(table) < n_faces or np.any(table["vertex_indices_n"] != 3) or np.any(table["texcoord_n"] != 6):
            return None  # not all triangles with a UV per corner: not a layout this reads
        triangles, uv = table["vertex_indices"].astype(np.int64), table["texcoord"].astype(np.float64)
    if triangles.min() < 0 or triangles.max() >= n_vertices or not np.all(np.isfinite(uv)):
        return None  # damaged: read_mesh names what is wrong with the faces
    return triangles, uv.reshape(-1, 2)


def _vertex_means(n_vertices: int, triangles: np.ndarray, corner: np.ndarray) -> np.ndarray:
    """Each vertex's mean of its triangle corners' colours (3F, 3), in ``triangles`` (F, 3)' order
    (grey where no triangle uses it)."""
    sums = np.zeros((n_vertices, 3))
    np.add.at(sums, triangles.reshape(-1), corner)
    counts = np.bincount(triangles.reshape(-1), minlength=n_vertices)[:, None]
    return np.where(counts > 0, sums / np.maximum(counts, 1), 0.5)


def _texture(ply: Path, name: str) -> np.ndarray | None:
    """The texture image a PLY names, rgb; None (with a warning) when it cannot be read."""
    image = _read_rgb(ply.parent / name)
    if image is None:
        log.warning("%s: its texture %s cannot be read; the model has no colours", ply, name)
    return image


def _corner_colours(mesh: o3d.geometry.TriangleMesh) -> np.ndarray:
    """Each vertex's colour as the mean of its triangle corners' texture colours (Open3D's UVs)."""
    triangles = np.asarray(mesh.triangles)
    uvs = np.asarray(mesh.triangle_uvs).reshape(-1, 2)
    ids = np.asarray(mesh.triangle_material_ids) if mesh.has_triangle_material_ids() else np.zeros(len(triangles), int)
    images = [np.asarray(t) for t in mesh.textures]
    images = [np.flipud(im) if im.ndim == 3 else im for im in images]  # Open3D holds them bottom row first
    corner = np.zeros((len(uvs), 3))
    for k, image in enumerate(images):
        on = np.repeat(ids == k, 3)
        if on.any() and image.ndim == 3 and image.size:
            corner[on] = sample_texture(image if image.dtype == np.uint8 else (255 * image).astype(np.uint8), uvs[on])
    return _vertex_means(len(mesh.vertices), triangles, corner)


def _read_rgb(path: Path) -> np.ndarray | None:
    bgr = cv2.imread(str(path), cv2.IMREAD_COLOR)
    return None if bgr is None else cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)
