"""Twelve parts that nothing here was tuned on, as shape folders like ../shared/data's.

The evaluation keeps unseen parts of the kinds the sample shapes stand for (chamfered and stepped
blocks, prisms, shafts, plates with holes, thin walls, smooth controls); these are such parts,
made by constructive solid geometry, to check that the defaults hold on them:

- ``chamfer_block``: a 1 × 0.7 × 0.5 block whose twelve edges are 45° chamfers (faces 135° apart);
- ``stepped_shaft``: three cylinders of radius 0.16, 0.11 and 0.07 end to end, bored through along
  their axis (radius 0.035: the thin end's wall is as thick as the bore's radius);
- ``open_box``: a box open at the top, walls and floor 0.05 thick;
- ``hex_nut``: a hexagonal prism 0.35 thick with a bore of radius 0.22;
- ``slotted_plate``: a plate 0.1 thick with two slots and three holes of radius 0.05 (genus 5);
- ``rounded_box``: a block whose edges and corners are all rounded (radius 0.1): no sharp edge,
  so every point flagged is a false edge;
- ``keyed_shaft``: a shaft with a keyway in one half and a flat on the other;
- ``thin_channel``: a U-channel whose walls and floor are 0.03 thick (six noise widths);
- ``tube``: a tube 0.8 long whose wall is 0.04 thick (0.05 in the unit frame), with two flat ends;
- ``blob``: a smooth control, a sphere whose radius varies with direction;
- ``stair_block``: three steps, concave edges between treads and risers;
- ``frustum``: a square frustum, faces 63° off its base, with a hole through it.

Each mesh is written as STL and sampled by ``evaluation.shapes --mesh`` (16,384 points, noise
0.005, unit frame), as the public models are. The booleans need manifold3d (the ``bench`` extra).

    .venv/bin/python bench/parts.py --folder /tmp/parts
    .venv/bin/python bench/run.py --only quality --configs default,poisson --data /tmp/parts \\
        --clouds chamfer_block,stepped_shaft,open_box,hex_nut,slotted_plate,rounded_box --jobs 2
    .venv/bin/python bench/run.py --only quality --configs default,poisson --data /tmp/parts \\
        --clouds keyed_shaft,thin_channel,tube,blob,stair_block,frustum --jobs 2
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable
from pathlib import Path

import numpy as np
import trimesh
from scipy.spatial import ConvexHull, HalfspaceIntersection

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from evaluation import shapes  # noqa: E402


def chamfer_block(half: tuple[float, float, float] = (0.5, 0.35, 0.25), chamfer: float = 0.08) -> trimesh.Trimesh:
    """The box |x_i| <= half_i cut by a 45° plane along each edge, ``chamfer`` in from both faces."""
    planes = []  # rows (normal, offset) of n·x + offset <= 0
    for axis, limit in enumerate(half):
        for sign in (1.0, -1.0):
            normal = np.zeros(3)
            normal[axis] = sign
            planes.append([*normal, -limit])
    for i, j in ((0, 1), (1, 2), (0, 2)):
        for si in (1.0, -1.0):
            for sj in (1.0, -1.0):
                normal = np.zeros(3)
                normal[i], normal[j] = si, sj
                planes.append([*(normal / np.sqrt(2)), -(half[i] + half[j] - chamfer) / np.sqrt(2)])
    corners = HalfspaceIntersection(np.asarray(planes), np.zeros(3)).intersections
    mesh = trimesh.Trimesh(corners, ConvexHull(corners).simplices)
    mesh.fix_normals()
    return mesh


def _along_x(mesh: trimesh.Trimesh) -> trimesh.Trimesh:
    return mesh.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, [0, 1, 0]))


def stepped_shaft() -> trimesh.Trimesh:
    steps, start = [], -0.5
    for radius, length in ((0.16, 0.35), (0.11, 0.35), (0.07, 0.3)):
        step = _along_x(trimesh.creation.cylinder(radius=radius, height=length, sections=128))
        steps.append(step.apply_translation([start + length / 2, 0, 0]))
        start += length
    bore = _along_x(trimesh.creation.cylinder(radius=0.035, height=2, sections=96))
    return trimesh.boolean.union(steps).difference(bore)


def open_box() -> trimesh.Trimesh:
    inside = trimesh.creation.box((0.9, 0.65, 0.4)).apply_translation([0, 0, 0.05])
    return trimesh.creation.box((1.0, 0.75, 0.4)).difference(inside)


def hex_nut() -> trimesh.Trimesh:
    prism = trimesh.creation.cylinder(radius=0.5, height=0.35, sections=6)
    return prism.difference(trimesh.creation.cylinder(radius=0.22, height=1, sections=128))


def slotted_plate() -> trimesh.Trimesh:
    cuts = []
    for y in (-0.15, 0.15):
        ends = [trimesh.creation.cylinder(0.04, 1, sections=64).apply_translation([x, y, 0]) for x in (-0.3, 0.0)]
        middle = trimesh.creation.box((0.3, 0.08, 1)).apply_translation([-0.15, y, 0])
        cuts.append(trimesh.boolean.union([middle, *ends]))
    for y in (-0.2, 0.0, 0.2):
        cuts.append(trimesh.creation.cylinder(0.05, 1, sections=64).apply_translation([0.3, y, 0]))
    return trimesh.creation.box((1.0, 0.6, 0.1)).difference(trimesh.boolean.union(cuts))


def rounded_box(radius: float = 0.1) -> trimesh.Trimesh:
    """The hull of eight balls: flat faces, cylindrical edges and spherical corners of ``radius``."""
    ball = trimesh.creation.icosphere(subdivisions=4, radius=radius)
    centres = [
        [sx * (0.5 - radius), sy * (0.35 - radius), sz * (0.25 - radius)]
        for sx in (1, -1)
        for sy in (1, -1)
        for sz in (1, -1)
    ]
    return trimesh.convex.convex_hull(np.concatenate([ball.vertices + centre for centre in centres]))


def keyed_shaft() -> trimesh.Trimesh:
    """A shaft of radius 0.12 with a keyway (0.06 wide, 0.04 deep) in one half and a flat on the other."""
    shaft = _along_x(trimesh.creation.cylinder(radius=0.12, height=1.0, sections=128))
    keyway = trimesh.creation.box((0.3, 0.06, 0.1)).apply_translation([-0.2, 0, 0.12 + 0.05 - 0.04])
    flat = trimesh.creation.box((0.35, 0.4, 0.1)).apply_translation([0.33, 0, 0.09 + 0.05])
    return shaft.difference(trimesh.boolean.union([keyway, flat]))


def thin_channel() -> trimesh.Trimesh:
    """A U-channel 1 long, 0.5 wide and 0.35 high, its walls and floor 0.03 thick (six noise widths)."""
    inside = trimesh.creation.box((1.2, 0.44, 0.35)).apply_translation([0, 0, 0.03])
    return trimesh.creation.box((1.0, 0.5, 0.35)).difference(inside)


def tube() -> trimesh.Trimesh:
    """A tube 0.8 long, outer radius 0.25, wall 0.04 thick (scaled by 1.25 to the unit frame): genus 1."""
    outer = trimesh.creation.cylinder(radius=0.25, height=0.8, sections=128)
    return outer.difference(trimesh.creation.cylinder(radius=0.21, height=1.0, sections=128))


def blob() -> trimesh.Trimesh:
    """A smooth control: a sphere whose radius varies by up to 15 % with direction (no edge)."""
    mesh = trimesh.creation.icosphere(subdivisions=5, radius=1.0)
    x, y, z = mesh.vertices.T
    radius = 0.4 * (1 + 0.1 * np.sin(3 * np.arctan2(y, x)) * (1 - z**2) + 0.05 * np.cos(2 * np.pi * z))
    return trimesh.Trimesh(mesh.vertices * radius[:, None], mesh.faces)


def stair_block() -> trimesh.Trimesh:
    """Three steps of a stair: concave edges between treads and risers, saddles where they meet the sides."""
    steps = [
        trimesh.creation.box((1.0 - 0.3 * i, 0.6, 0.15)).apply_translation([0.15 * i, 0, 0.15 * i]) for i in range(3)
    ]
    return trimesh.boolean.union(steps)


def frustum() -> trimesh.Trimesh:
    """A square frustum (base 0.9, top 0.45, height 0.5: faces 63° off the base) with a hole of radius 0.08."""
    base, top, height = 0.45, 0.225, 0.5
    levels = ((base, -height / 2), (top, height / 2))
    corners = [[sx * h, sy * h, z] for h, z in levels for sx in (1, -1) for sy in (1, -1)]
    hull = trimesh.convex.convex_hull(np.asarray(corners))
    return hull.difference(trimesh.creation.cylinder(radius=0.08, height=1.0, sections=96))


PARTS: dict[str, Callable[[], trimesh.Trimesh]] = {
    "chamfer_block": chamfer_block,
    "stepped_shaft": stepped_shaft,
    "open_box": open_box,
    "hex_nut": hex_nut,
    "slotted_plate": slotted_plate,
    "rounded_box": rounded_box,
    "keyed_shaft": keyed_shaft,
    "thin_channel": thin_channel,
    "tube": tube,
    "blob": blob,
    "stair_block": stair_block,
    "frustum": frustum,
}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--folder", type=Path, required=True, help="one shape folder per part is written here")
    parser.add_argument("--parts", default=",".join(PARTS), help="comma-separated, from: " + ", ".join(PARTS))
    args = parser.parse_args()
    for name in args.parts.split(","):
        mesh = PARTS[name]()
        if not mesh.is_watertight:
            raise SystemExit(f"{name}: the boolean left an open mesh")
        stl = args.folder / "meshes" / f"{name}.stl"
        stl.parent.mkdir(parents=True, exist_ok=True)
        mesh.export(stl)
        shapes.main(["--mesh", str(stl), "--folder", str(args.folder / name)])
        print(f"{name}: genus {(2 - mesh.euler_number) // 2}, {len(mesh.faces)} faces -> {args.folder / name}")


if __name__ == "__main__":
    main()
