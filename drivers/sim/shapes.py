"""Objects for the simulator that are no box or cylinder, as public datasets' objects are."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import open3d as o3d

from drivers.sim.scenario import ObjectSpec


def shapes(folder: Path) -> list[ObjectSpec]:
    """Objects that are no box or cylinder, their meshes written to ``folder`` (m, base centre at
    the origin, z up): a mug (a 4 cm can and its ring handle), a duck (two spheres and a beak), a
    drill (a handle under a 20 cm body that overhangs it) and a cone, 9-20 cm, as public datasets'
    objects are."""

    def turned(mesh: o3d.geometry.TriangleMesh, axis: tuple[float, float, float]) -> o3d.geometry.TriangleMesh:
        return mesh.rotate(
            o3d.geometry.get_rotation_matrix_from_axis_angle(np.radians(90.0) * np.asarray(axis)), center=(0, 0, 0)
        )

    make = o3d.geometry.TriangleMesh
    meshes = {
        "mug": (
            make.create_cylinder(0.04, 0.10, 32).translate([0, 0, 0.05])
            + turned(make.create_torus(0.03, 0.008, 24, 12), (1, 0, 0)).translate([0.045, 0, 0.05]),
            (0.9, 0.25, 0.2),
        ),
        "duck": (
            make.create_sphere(0.045, 20).translate([0, 0, 0.045])
            + make.create_sphere(0.028, 16).translate([0.035, 0, 0.105])
            + turned(make.create_cone(0.012, 0.03, 16), (0, 1, 0)).translate([0.06, 0, 0.105]),
            (0.95, 0.85, 0.1),
        ),
        "drill": (
            make.create_cylinder(0.018, 0.12, 24).translate([0, 0, 0.06])
            + make.create_box(0.20, 0.06, 0.07).translate([-0.05, -0.03, 0.12]),
            (0.2, 0.6, 0.3),
        ),
        "cone": (make.create_cone(0.045, 0.13, 32), (0.2, 0.35, 0.85)),
    }
    out = []
    for name, (mesh, colour) in meshes.items():
        path = folder / f"{name}.ply"
        o3d.io.write_triangle_mesh(str(path), mesh.compute_vertex_normals())
        lo, hi = mesh.get_min_bound(), mesh.get_max_bound()
        size = (2 * max(-lo[0], hi[0]), 2 * max(-lo[1], hi[1]), hi[2])
        out.append(ObjectSpec(id=name, shape="mesh", mesh=path, size=tuple(float(v) for v in size), color=colour))
    return out
