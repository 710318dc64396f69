"""Model colours from texture images: a PLY's vertex UVs (BOP's YCB-V layout) and an OBJ's material,
read through ``read_mesh`` as ``cellsight model build --mesh`` and ``benchmarks.bop`` read them."""

from pathlib import Path

import cv2
import numpy as np
import pytest

from recognition.models import read_mesh

#: The texture's quadrants as the image file holds them (rgb): top-left, top-right, bottom-left, bottom-right.
QUADRANTS = {(0, 0): (220, 30, 30), (0, 1): (30, 200, 40), (1, 0): (40, 60, 210), (1, 1): (230, 210, 20)}
SIZE_M = 0.2
STEPS = (0.1, 0.3, 0.7, 0.9)  # grid positions as shares of the side: none on a quadrant's edge


def write_texture(path: Path) -> None:
    image = np.zeros((64, 64, 3), np.uint8)
    for (row, col), rgb in QUADRANTS.items():
        image[32 * row : 32 * (row + 1), 32 * col : 32 * (col + 1)] = rgb
    cv2.imwrite(str(path), cv2.cvtColor(image, cv2.COLOR_RGB2BGR))


def grid() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A flat 4 x 4 vertex grid in z = 0 (m), its texture coordinates (u along x, v along y) and triangles."""
    uv = np.array([(u, v) for v in STEPS for u in STEPS])
    vertices = np.c_[SIZE_M * uv, np.zeros(len(uv))]
    triangles = [(4 * r + c, 4 * r + c + 1, 4 * (r + 1) + c + 1) for r in range(3) for c in range(3)]
    triangles += [(4 * r + c, 4 * (r + 1) + c + 1, 4 * (r + 1) + c) for r in range(3) for c in range(3)]
    return vertices, uv, np.array(triangles)


def expected(uv: np.ndarray) -> np.ndarray:
    """Each vertex's colour (rgb 0-1) read off the quadrant its UV falls in: v counts up from the image's bottom row."""
    return np.array([QUADRANTS[(int(v < 0.5), int(u >= 0.5))] for u, v in uv]) / 255.0


def write_ply(path: Path, fmt: str, uv_on: str = "vertex") -> None:
    """The grid as a PLY with its texture coordinates per vertex (``texture_u``, ``texture_v``) or
    per face (a ``texcoord`` list of its three corners' u, v)."""
    vertices, uv, triangles = grid()
    vertex_uv = "property float texture_u\nproperty float texture_v\n" if uv_on == "vertex" else ""
    face_uv = "property list uchar float texcoord\n" if uv_on == "face" else ""
    header = (
        f"ply\nformat {fmt} 1.0\ncomment TextureFile tex.png\nelement vertex {len(vertices)}\n"
        "property float x\nproperty float y\nproperty float z\nproperty float nx\nproperty float ny\nproperty float nz\n"
        f"{vertex_uv}element face {len(triangles)}\nproperty list uchar int vertex_indices\n{face_uv}end_header\n"
    )
    rows = np.c_[vertices, np.tile([0.0, 0.0, 1.0], (len(vertices), 1))]
    rows = np.c_[rows, uv] if uv_on == "vertex" else rows
    corners = uv[triangles].reshape(len(triangles), 6)
    if fmt == "ascii":
        body = "".join(" ".join(f"{x:.6f}" for x in row) + "\n" for row in rows)
        for tri, c in zip(triangles, corners):
            body += (
                f"3 {tri[0]} {tri[1]} {tri[2]}"
                + ("" if uv_on == "vertex" else " 6 " + " ".join(f"{x:.6f}" for x in c))
                + "\n"
            )
        path.write_text(header + body)
        return
    order = "<" if fmt == "binary_little_endian" else ">"
    fields = [("n", "u1"), ("v", order + "i4", 3)] + ([("m", "u1"), ("uv", order + "f4", 6)] if uv_on == "face" else [])
    faces = np.zeros(len(triangles), np.dtype(fields))
    faces["n"], faces["v"] = 3, triangles
    if uv_on == "face":
        faces["m"], faces["uv"] = 6, corners
    path.write_bytes(header.encode() + rows.astype(order + "f4").tobytes() + faces.tobytes())


@pytest.mark.parametrize("uv_on", ["vertex", "face"])
@pytest.mark.parametrize("fmt", ["binary_little_endian", "binary_big_endian", "ascii"])
@pytest.mark.slow
def test_a_ply_with_texture_coordinates_is_coloured_from_its_texture(tmp_path: Path, fmt: str, uv_on: str) -> None:
    """A PLY laid out as BOP's YCB-V models are (vertex x, y, z, normal, texture_u, texture_v and a
    TextureFile comment), or with each face's corners' UVs instead: each vertex takes the colour of
    the texture quadrant its UV names (per face: every corner at a vertex names the same)."""
    write_texture(tmp_path / "tex.png")
    write_ply(tmp_path / "obj_000001.ply", fmt, uv_on)
    mesh = read_mesh(tmp_path / "obj_000001.ply")
    _, uv, _ = grid()
    np.testing.assert_allclose(np.asarray(mesh.vertex_colors), expected(uv), atol=1.5 / 255)


def test_an_obj_with_a_textured_material_is_coloured_from_its_texture(tmp_path: Path) -> None:
    """An OBJ with per-corner texture coordinates and a material's image: the same colours as the PLY."""
    write_texture(tmp_path / "tex.png")
    vertices, uv, triangles = grid()
    lines = [
        "mtllib box.mtl",
        *(f"v {x} {y} {z}" for x, y, z in vertices),
        *(f"vt {u} {v}" for u, v in uv),
        "usemtl painted",
    ]
    lines += [f"f {a + 1}/{a + 1} {b + 1}/{b + 1} {c + 1}/{c + 1}" for a, b, c in triangles]
    (tmp_path / "box.obj").write_text("\n".join(lines) + "\n")
    (tmp_path / "box.mtl").write_text("newmtl painted\nmap_Kd tex.png\n")
    mesh = read_mesh(tmp_path / "box.obj")
    # Open3D may reorder an OBJ's vertices: compare by position.
    order = [int(np.argmin(np.linalg.norm(vertices - p, axis=1))) for p in np.asarray(mesh.vertices)]
    np.testing.assert_allclose(np.asarray(mesh.vertex_colors), expected(uv[order]), atol=1.5 / 255)


def test_a_texture_that_cannot_be_read_leaves_the_model_without_colour(tmp_path: Path) -> None:
    """The TextureFile names a file that is not there: the mesh still reads, without colours."""
    write_ply(tmp_path / "obj_000001.ply", "binary_little_endian")
    mesh = read_mesh(tmp_path / "obj_000001.ply")
    assert len(mesh.triangles) == 18 and not mesh.has_vertex_colors()
