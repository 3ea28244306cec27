#!/usr/bin/python3
"""A lidar-style scan of a mesh, computed client-side from cast_rays: a spinning sensor with
--channels beams between -25 and +25 degrees of elevation and --azimuths steps per turn, set
beside the mesh. The hits become a point cloud saved as a binary little-endian PLY (x, y, z,
range as float32; the beam's ring and the triangle as uint32).

    python3 lidar_scan.py MESH [--server URL] [--channels 32] [--azimuths 1024] [--out scan.ply]

Prints one JSON line: the rays cast and the points written.
"""

import argparse
import json

import numpy as np

import kdrt


def lidar_rays(origin, channels, azimuths, max_range):
    """(channels, azimuths, 8) float32 rays [o, d, tmin, tmax] with unit directions."""
    elevation = np.radians(np.linspace(-25, 25, channels))[:, None]
    azimuth = np.linspace(0, 2 * np.pi, azimuths, endpoint=False)[None, :]
    rays = np.empty((channels, azimuths, 8), np.float32)
    rays[..., 0:3] = origin
    rays[..., 3] = np.cos(elevation) * np.cos(azimuth)
    rays[..., 4] = np.sin(elevation) * np.ones_like(azimuth)
    rays[..., 5] = np.cos(elevation) * np.sin(azimuth)
    rays[..., 6] = 0.0
    rays[..., 7] = max_range
    return rays


def write_ply(path, points, ranges, rings, triangles):
    vertex = np.empty(points.shape[0], dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"),
                                              ("range", "<f4"), ("ring", "<u4"),
                                              ("triangle", "<u4")])
    vertex["x"], vertex["y"], vertex["z"] = points.T
    vertex["range"], vertex["ring"], vertex["triangle"] = ranges, rings, triangles
    header = ("ply\nformat binary_little_endian 1.0\ncomment kdrt lidar_scan.py\n"
              f"element vertex {points.shape[0]}\n"
              "property float x\nproperty float y\nproperty float z\nproperty float range\n"
              "property uint ring\nproperty uint triangle\nend_header\n")
    with open(path, "wb") as f:
        f.write(header.encode("ascii"))
        f.write(vertex.tobytes())


def main():
    parser = argparse.ArgumentParser(description="lidar-style scan of a mesh as a PLY cloud")
    parser.add_argument("mesh", help="mesh file (.obj .ply .off .stl .raw)")
    parser.add_argument("--server", default="http://127.0.0.1:8080")
    parser.add_argument("--channels", type=int, default=32)
    parser.add_argument("--azimuths", type=int, default=1024)
    parser.add_argument("--out", default="scan.ply")
    args = parser.parse_args()

    client = kdrt.Client(args.server)
    mesh = client.upload(args.mesh)
    lo, hi = mesh.bounds
    center, extent = (lo + hi) / 2, np.linalg.norm(hi - lo)
    origin = center + np.array([0.8, 0.05, 0.3]) * extent     # beside the mesh
    rays = lidar_rays(origin, args.channels, args.azimuths, max_range=5 * extent)
    hits = client.cast_rays(mesh, rays)                         # arrays of shape (channels, azimuths)

    hit = np.isfinite(hits["t_hit"])
    ranges = hits["t_hit"][hit]
    points = rays[..., 0:3][hit] + ranges[:, None] * rays[..., 3:6][hit]
    rings = np.broadcast_to(np.arange(args.channels)[:, None], hit.shape)[hit]
    write_ply(args.out, points, ranges, rings, hits["primitive_ids"][hit])
    print(json.dumps({"out": args.out, "rays": int(hit.size), "points": int(hit.sum())}))


if __name__ == "__main__":
    main()
