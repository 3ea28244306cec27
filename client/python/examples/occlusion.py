#!/usr/bin/python3
"""Visibility between points with test_occlusions: which of --points points around a mesh can
see a light (a segment query: the ray from the point to the light with tmin = 0 and tmax just
short of 1, so only what lies between them counts).

    python3 occlusion.py MESH [--server URL] [--points 1000] [--light X,Y,Z] [--seed 1]

Prints one JSON line: the light, how many points see it, and the first few points with their
visibility.
"""

import argparse
import json

import numpy as np

import kdrt


def segment_rays(points, target):
    """(n, 8) float32 rays from each point towards `target`: direction = target - point
    (not normalised), so t in [0, 1] spans the segment; tmax = 1 - 1e-4 leaves out the target."""
    rays = np.empty((points.shape[0], 8), np.float32)
    rays[:, 0:3] = points
    rays[:, 3:6] = np.asarray(target, np.float32) - points
    rays[:, 6] = 0.0
    rays[:, 7] = 1.0 - 1e-4
    return rays


def points_under(bounds, count, seed):
    """`count` points on a slab just under the mesh's bounds, twice as wide: some in its
    shadow, some not."""
    lo, hi = bounds
    center, size = (lo + hi) / 2, hi - lo
    rng = np.random.default_rng(seed)
    points = center + (rng.random((count, 3)) - 0.5) * size * np.array([2.0, 0.0, 2.0])
    points[:, 1] = lo[1] - 0.05 * size[1]
    return points


def main():
    parser = argparse.ArgumentParser(description="point-to-light visibility around a mesh")
    parser.add_argument("mesh", help="mesh file (.obj .ply .off .stl .raw)")
    parser.add_argument("--server", default="http://127.0.0.1:8080")
    parser.add_argument("--points", type=int, default=1000)
    parser.add_argument("--light", help="X,Y,Z (default: above the mesh)")
    parser.add_argument("--seed", type=int, default=1)
    args = parser.parse_args()

    client = kdrt.Client(args.server)
    mesh = client.upload(args.mesh)
    lo, hi = mesh.bounds
    center, size = (lo + hi) / 2, hi - lo
    light = (np.array([float(x) for x in args.light.split(",")]) if args.light
             else center + np.array([0.0, 2.0, 0.0]) * size)
    points = points_under(mesh.bounds, args.points, args.seed)
    occluded = client.test_occlusions(mesh, segment_rays(points, light))  # bool (points,)

    print(json.dumps({"light": light.tolist(), "points": args.points,
                      "visible": int((~occluded).sum()),
                      "first": [{"point": p.round(4).tolist(), "sees_light": bool(not o)}
                                for p, o in zip(points[:5], occluded[:5])]}))


if __name__ == "__main__":
    main()
