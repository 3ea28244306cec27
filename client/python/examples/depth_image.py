#!/usr/bin/python3
"""A depth image of a mesh, computed client-side from cast_rays and saved as an 8-bit grey PNG
(near = bright, misses black) with kdrt.write_png (numpy and the standard library's zlib only).

    python3 depth_image.py MESH [--server URL] [--size 256] [--out depth.png]

Prints one JSON line: the image size, the pixels that hit, and the depth range.
"""

import argparse
import json

import numpy as np

import kdrt


def pinhole_rays(eye, look_at, up, fov_deg, width, height):
    """One ray per pixel centre of a pinhole camera: (height, width, 6) float32, unit
    directions, so t_hit is the distance from the eye."""
    forward = np.asarray(look_at, np.float64) - eye
    forward /= np.linalg.norm(forward)
    right = np.cross(forward, up)
    right /= np.linalg.norm(right)
    true_up = np.cross(right, forward)
    half = np.tan(np.radians(fov_deg) / 2)
    xs = ((np.arange(width) + 0.5) / width * 2 - 1) * half * width / height
    ys = (1 - (np.arange(height) + 0.5) / height * 2) * half
    d = forward + xs[None, :, None] * right + ys[:, None, None] * true_up
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    rays = np.empty((height, width, 6), np.float32)
    rays[..., :3] = eye
    rays[..., 3:] = d
    return rays


def main():
    parser = argparse.ArgumentParser(description="depth image of a mesh as a PNG")
    parser.add_argument("mesh", help="mesh file (.obj .ply .off .stl .raw)")
    parser.add_argument("--server", default="http://127.0.0.1:8080")
    parser.add_argument("--size", type=int, default=256)
    parser.add_argument("--out", default="depth.png")
    args = parser.parse_args()

    client = kdrt.Client(args.server)
    mesh = client.upload(args.mesh)
    lo, hi = mesh.bounds
    center, extent = (lo + hi) / 2, np.linalg.norm(hi - lo)
    eye = center + np.array([0.0, 0.15, 1.1]) * extent
    rays = pinhole_rays(eye, center, [0, 1, 0], 40, args.size, args.size)
    depth = client.cast_rays(mesh, rays)["t_hit"]          # (size, size), inf on a miss

    hit = np.isfinite(depth)
    near, far = (depth[hit].min(), depth[hit].max()) if hit.any() else (0.0, 1.0)
    grey = np.zeros(depth.shape, np.uint8)
    grey[hit] = np.round(255 - 200 * (depth[hit] - near) / max(far - near, 1e-12)).astype(np.uint8)
    kdrt.write_png(args.out, grey)
    print(json.dumps({"out": args.out, "width": args.size, "height": args.size,
                      "hits": int(hit.sum()), "near": float(near), "far": float(far)}))


if __name__ == "__main__":
    main()
