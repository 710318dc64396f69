"""A mesh's vertex colours from its texture image, for model files that colour it that way.

Model libraries often ship a texture instead of vertex colours: BOP's YCB-V PLYs give every vertex
``texture_u`` / ``texture_v`` and name the image in a ``comment TextureFile NAME`` header line; OBJ
files give each triangle corner a UV and a material's image, which Open3D reads. Verification
judges a pixel's colour against the model's colours there, so each vertex takes the texture's
colour at its UV (v up from the image's bottom row, as OpenGL and the BOP toolkit read it; nearest
texel, coordinates wrapped). A texture that cannot be read leaves the model colourless, with a
warning: recognition then runs on depth alone for that object.
"""

from __future__ import annotations

import logging
import re
from pathlib import Path

import cv2
import numpy as np
import open3d as o3d

log = logging.getLogger(__name__)

#: PLY scalar types as numpy's.
PLY_TYPES = {"char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2", "int16": "i2", "ushort": "u2",
             "uint16": "u2", "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4", "float": "f4", "float32": "f4",
             "double": "f8", "float64": "f8"}  # fmt: skip
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
        return ply_vertex_texture_colours(Path(path), len(mesh.vertices))
    return None


def sample_texture(image: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Colours (N, 3), rgb 0-1, of an rgb image (H, W, 3, uint8) at texture coordinates uv (N, 2);
    coordinates outside 0..1 wrap (a tiled texture)."""
    H, W = image.shape[:2]
    u, v = (np.where((c < 0) | (c > 1), np.mod(c, 1.0), c) for c in (uv[:, 0], uv[:, 1]))
    cols = np.clip(np.round(u * (W - 1)).astype(np.int64), 0, W - 1)
    rows = np.clip(np.round((1.0 - v) * (H - 1)).astype(np.int64), 0, H - 1)
    return image[rows, cols, :3].astype(np.float64) / 255.0


def ply_vertex_texture_colours(path: Path, n_vertices: int) -> np.ndarray | None:
    """Vertex colours (V, 3), rgb 0-1, of a PLY whose header names a TextureFile and whose vertices
    (the file's first element, ``n_vertices`` of them) carry texture coordinates; None otherwise."""
    with path.open("rb") as f:
        head = f.read(65536)
    end = head.find(b"end_header")
    if not head.startswith(b"ply") or end < 0:
        return None
    body = head.index(b"\n", end) + 1
    lines = head[:end].decode("ascii", "replace").splitlines()
    texture = next((m.group(1).strip() for line in lines if (m := re.match(r"comment\s+TextureFile\s+(.+)", line))), None)
    fmt = next((line.split()[1] for line in lines if line.startswith("format ")), "")
    elements = [line.split() for line in lines if line.startswith(("element ", "property "))]
    if texture is None or not elements or elements[0][:2] != ["element", "vertex"] or int(elements[0][2]) != n_vertices:
        return None
    props = []
    for words in elements[1:]:
        if words[0] == "element":
            break
        if words[1] == "list" or words[1] not in PLY_TYPES:
            return None  # a vertex with a list property: not a layout this reads
        props.append((words[2], PLY_TYPES[words[1]]))
    names = [name for name, _ in props]
    uv_names = next((pair for pair in UV_NAMES if set(pair) <= set(names)), None)
    if uv_names is None:
        return None
    if fmt == "ascii":
        rows = np.loadtxt(path, skiprows=len(head[:body].splitlines()), max_rows=n_vertices, ndmin=2,
                          usecols=[names.index(n) for n in uv_names])  # fmt: skip
        uv = rows.astype(np.float64)
    elif fmt in ("binary_little_endian", "binary_big_endian"):
        order = "<" if fmt == "binary_little_endian" else ">"
        dtype = np.dtype([(name, order + t) for name, t in props])
        vertices = np.fromfile(path, dtype=dtype, count=n_vertices, offset=body)
        if len(vertices) < n_vertices:
            return None
        uv = np.stack([vertices[n].astype(np.float64) for n in uv_names], axis=1)
    else:
        return None
    image = _read_rgb(path.parent / texture)
    if image is None:
        log.warning("%s: its texture %s cannot be read; the model has no colours", path, texture)
        return None
    return sample_texture(image, uv)


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
    sums = np.zeros((len(mesh.vertices), 3))
    np.add.at(sums, triangles.reshape(-1), corner)
    counts = np.bincount(triangles.reshape(-1), minlength=len(mesh.vertices))[:, None]
    return np.where(counts > 0, sums / np.maximum(counts, 1), 0.5)


def _read_rgb(path: Path) -> np.ndarray | None:
    bgr = cv2.imread(str(path), cv2.IMREAD_COLOR)
    return None if bgr is None else cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)
